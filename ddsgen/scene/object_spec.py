"""One entry of a scene's object pool (:class:`ObjectSpec`): what the scene list says of an object, apart from the
scene list's parser, so that the distractors' parser can build entries too."""

from __future__ import annotations

import dataclasses

from ddsgen.scene.meshes import load_mesh


@dataclasses.dataclass(frozen=True)
class ObjectSpec:
    """One entry of a scene's object pool."""

    class_name: str
    mesh_ref: str  # absolute file path, or "shape:NAME(params)"
    scale: float = 1.0  # file units -> metres (1 for shapes)
    albedo: tuple[float, float] = (0.5, 0.5)  # uniform range
    weight: float = 1.0
    rest: str = "stable"  # "stable" | "upright"
    obj_id: int | None = None  # the entry's `obj_id:` key; the resolved id is in SceneList.classes

    @property
    def is_shape(self) -> bool:
        return self.mesh_ref.startswith("shape:")

    def mesh(self):
        """The mesh in metres, object frame (cached per process)."""
        return load_mesh(self.mesh_ref, self.scale)
