"""Scene lists: YAML files that say what to put in front of the sensor.

A scene list holds one or more *scenes*. A scene is an object pool (meshes from
files or built-in procedural shapes), a ground plane (the support: a floor, or a table
top when a `floor` lies below it), an optional floor, an optional back wall, a
clutter rule (how many objects are dropped on the ground, where) and a camera rule
(distance, elevation, azimuth, look-at jitter). Frames cycle through the scenes in
blocks: scene 0 for its ``frames`` frames, then scene 1, ..., then scene 0 again. The
frames of one block share one object layout and see it from different camera poses
(like a BOP scene); see :func:`ddsgen.scene.sampling.sample_frame`.

Schema (sizes in metres, angles in degrees; ``[lo, hi]`` = uniform range, a single
number means a fixed value)::

    description: free text                 # optional
    scenes:
      - name: tabletop                     # optional, default scene<i>
        frames: 4                          # frames per layout (block length), default 1
        objects:                           # the pool, at least one
          - shape: box                     # built-in: box cylinder sphere capsule cone torus mug l_bracket
            size: [0.12, 0.08, 0.06]       # the shape's sizes (m), defaults per shape
            class: box                     # default: shape name / file stem
            albedo: [0.3, 0.8]             # IR reflectance 0..1, fixed or range (per placed object)
            weight: 1.0                    # relative probability of being picked, default 1
            rest: stable                   # stable (random stable pose) | upright (as modelled), default stable
          - mesh: models/obj_000001.ply    # OBJ/PLY/STL/GLB, relative to this file
            scale: 0.001                   # file units -> metres (0.001 for millimetre models)
            class: ape
            obj_id: 1                      # optional stable id (default: from an obj_NNNNNN file name, else
                                           # assigned once per scene list; see ddsgen/scene/identity.py)
        clutter:
          count: [3, 6]                    # objects per layout (integers), default [3, 6]
          area: [0.5, 0.5]                 # x, y extent of the drop area centred on the origin (m)
          min_gap: 0.005                   # minimum footprint gap (m), default 0.005
          max_tries: 100                   # placement attempts per object before it is left out
          unique: false                    # true: each pool entry at most once per layout
        ground: {size: [5, 5], albedo: [0.4, 0.7]}   # or `ground: null` for none
        floor: {depth: 0.75, size: [6, 6], albedo: [0.2, 0.6]}   # optional: a floor `depth` m below the
                                           # ground, which is then a table top (objects stay on it)
        wall: {distance: 0.6, width: 4, height: 2, albedo: 0.6}   # optional back wall at y = +distance
        distractors:                       # optional: unlabelled objects (instance id 0, no pose), see
          - surface: floor                 # ddsgen/scene/distractors.py: floor (around the table) | ground
            count: [4, 8]
            area: [5, 5]                   # the region they stand in, centred on `centre: [x, y]`
            objects: [{shape: box, size: [0.6, 0.4, 0.3], albedo: [0.05, 0.8]}]
        camera:
          distance: [0.8, 1.8]             # camera to look-at point (m)
          elevation_deg: [25, 70]          # above the ground plane, 0..89
          azimuth_deg: [-180, 180]         # 0 = camera on the -y side looking towards +y (the wall)
          roll_deg: [0, 0]                 # rotation about the optical axis
          look_at_jitter: 0.05             # uniform +- jitter of the look-at point per axis (m)

A mesh path not found relative to the file (or the working folder) is looked up by its file name in the
models folder, when one is given (``render --models DIR`` or the environment variable ``DDSGEN_MODELS``).

Every problem raises :class:`~ddsgen.errors.InputError` with one line
``FILE: KEY: problem`` where KEY is a path such as ``scenes[0].objects[2].scale``.
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path
from typing import Any

import numpy as np

from ddsgen.errors import InputError, did_you_mean, where
from ddsgen.scene import shapes
from ddsgen.scene.default_scenes import default_scene_list_dict
from ddsgen.scene.distractors import DistractorSpec, parse_distractors
from ddsgen.scene.fields import (
    check_keys,
    describe,
    field_number,
    field_range,
    field_size2,
    field_text,
    field_vector,
)
from ddsgen.scene.identity import ClassEntry, class_table
from ddsgen.scene.meshes import load_mesh
from ddsgen.scene.object_spec import ObjectSpec
from ddsgen.yamlfile import read_yaml

DEFAULT_SOURCE = "<built-in default scene list>"

#: Environment variable naming a folder where mesh files not found at their scene-list path are looked up.
MODELS_ENV = "DDSGEN_MODELS"


# ----------------------------------------------------------------------------------------------------------------
# Specs (plain, picklable: they travel to worker processes; meshes are loaded and cached per process)


@dataclasses.dataclass(frozen=True)
class ClutterSpec:
    count: tuple[int, int] = (3, 6)
    area: tuple[float, float] = (0.5, 0.5)
    min_gap: float = 0.005
    max_tries: int = 100
    unique: bool = False


@dataclasses.dataclass(frozen=True)
class PlaneSpec:
    size: tuple[float, float] = (5.0, 5.0)
    albedo: tuple[float, float] = (0.4, 0.7)


@dataclasses.dataclass(frozen=True)
class FloorSpec:
    """A floor ``depth`` m below the ground plane (which is then a table top), centred under it."""

    depth: float = 0.75
    size: tuple[float, float] = (6.0, 6.0)
    albedo: tuple[float, float] = (0.2, 0.6)


@dataclasses.dataclass(frozen=True)
class WallSpec:
    distance: float = 0.6  # y of the wall plane (m); the wall faces -y
    width: float = 4.0
    height: float = 2.0
    albedo: tuple[float, float] = (0.5, 0.8)


@dataclasses.dataclass(frozen=True)
class CameraSpec:
    distance: tuple[float, float] = (0.8, 1.8)
    elevation_deg: tuple[float, float] = (25.0, 70.0)
    azimuth_deg: tuple[float, float] = (-180.0, 180.0)
    roll_deg: tuple[float, float] = (0.0, 0.0)
    look_at_jitter: float = 0.05


@dataclasses.dataclass(frozen=True)
class SceneSpec:
    name: str
    frames: int
    objects: tuple[ObjectSpec, ...]
    clutter: ClutterSpec
    ground: PlaneSpec | None
    wall: WallSpec | None
    camera: CameraSpec
    floor: FloorSpec | None = None
    distractors: tuple[DistractorSpec, ...] = ()  # unlabelled objects (background, id 0)


@dataclasses.dataclass(frozen=True)
class SceneList:
    """A validated scene list. ``source`` is the file it came from (or the built-in marker)."""

    scenes: tuple[SceneSpec, ...]
    source: str = DEFAULT_SOURCE
    description: str = ""
    classes: tuple[ClassEntry, ...] = ()  # the class table: one obj_id per labelled pool entry

    def class_entry(self, mesh_ref: str, mesh_scale: float, class_name: str) -> ClassEntry:
        """The class-table row of a placed object (KeyError if the scene list has no such entry)."""
        wanted = (str(mesh_ref), float(mesh_scale), str(class_name))
        for entry in self.classes:
            if entry.key == wanted:
                return entry
        raise KeyError(wanted)

    @property
    def cycle_length(self) -> int:
        return sum(s.frames for s in self.scenes)

    def scene_for_frame(self, frame_index: int) -> tuple[int, int]:
        """``(scene index, first frame of the block)`` for frame ``frame_index`` (deterministic, no randomness)."""
        if frame_index < 0:
            raise ValueError(f"frame_index must be >= 0, got {frame_index}")
        cycle = self.cycle_length
        base = (frame_index // cycle) * cycle
        offset = frame_index - base
        for index, scene in enumerate(self.scenes):
            if offset < scene.frames:
                return index, base
            offset -= scene.frames
            base += scene.frames
        raise AssertionError("unreachable")

    def block_start(self, frame_index: int) -> int:
        """First frame of the block (shared layout) that frame ``frame_index`` belongs to."""
        scene_index, base = self.scene_for_frame(frame_index)
        return base


# ----------------------------------------------------------------------------------------------------------------
# Sections

OBJECT_KEYS_COMMON = ("class", "albedo", "weight", "rest", "obj_id")


def _resolve_mesh_path(source: str, key: str, value: Any, base_dir: Path | None, models_dir: Path | None) -> str:
    text = field_text(source, key, value)
    path = Path(text).expanduser()
    candidates = [path] if path.is_absolute() else []
    if not path.is_absolute():
        if base_dir is not None:
            candidates.append(base_dir / path)
        candidates.append(Path.cwd() / path)
    if models_dir is not None:
        candidates.append(models_dir / path.name)
    for candidate in candidates:
        if candidate.is_file():
            return os.path.abspath(candidate)
    tried = candidates[-1] if models_dir is not None else candidates[0] if candidates else path
    hint = "" if models_dir is not None else f"; give the folder holding {path.name} with --models DIR or {MODELS_ENV}=DIR"
    raise InputError(f"{where(source, key)}{text}: mesh file not found (looked at {tried}){hint}")


def models_folder(models_dir: str | Path | None) -> Path | None:
    """The models folder to look mesh files up in: ``models_dir``, else ``$DDSGEN_MODELS``, else None."""
    chosen = models_dir if models_dir is not None else os.environ.get(MODELS_ENV) or None
    if chosen is None:
        return None
    folder = Path(chosen).expanduser()
    if not folder.is_dir():
        origin = "--models" if models_dir is not None else MODELS_ENV
        raise InputError(f"{origin}: {folder}: models folder not found")
    return folder


def _object(source, key: str, data: Any, base_dir: Path | None, models_dir: Path | None = None) -> ObjectSpec:
    if isinstance(data, str) and data in shapes.SHAPES:
        data = {"shape": data}
    if not isinstance(data, dict):
        raise InputError(f"{where(source, key)}expected a mapping with `shape:` or `mesh:`, got {describe(data)}")
    if ("shape" in data) == ("mesh" in data):
        raise InputError(f"{where(source, key)}give exactly one of `shape:` (built-in) or `mesh:` (a file)")
    if "shape" in data:
        name = data["shape"]
        if not isinstance(name, str) or name not in shapes.SHAPES:
            hint = did_you_mean(name, shapes.SHAPES, f"built-in: {', '.join(shapes.SHAPES)}")
            raise InputError(f"{where(source, key + '.shape')}unknown shape {name!r}{hint}")
        schema = shapes.shape_params(name)
        check_keys(source, key, data, ("shape", *schema, *OBJECT_KEYS_COMMON), f"a {name}")
        params = {}
        for param, spec in schema.items():
            if param in data and data[param] is not None:
                params[param] = field_vector(source, f"{key}.{param}", data[param], spec.length, low=0, low_open=True, high=100)
            else:
                params[param] = spec.default
        problem = shapes.check_shape_params(name, params)
        if problem:
            raise InputError(f"{where(source, key)}{name}: {problem}")
        mesh_ref = shapes.shape_ref(name, params)
        scale = 1.0
        default_class = name
    else:
        check_keys(source, key, data, ("mesh", "scale", *OBJECT_KEYS_COMMON), "a mesh file entry")
        mesh_ref = _resolve_mesh_path(source, f"{key}.mesh", data["mesh"], base_dir, models_dir)
        scale = field_number(source, f"{key}.scale", data.get("scale", 1.0), low=0, low_open=True, high=1e6)
        default_class = Path(mesh_ref).stem
        mesh = load_mesh(mesh_ref, scale, source, f"{key}.mesh")  # validate now (and warm the cache)
        extent = float(np.max(mesh.extents))
        if not 1e-3 <= extent <= 20.0:
            raise InputError(
                f"{where(source, key + '.scale')}{data['mesh']}: object is {extent:.4g} m across after scale {scale:g};"
                " expected 1 mm..20 m (millimetre models need scale: 0.001)"
            )
    class_name = field_text(source, f"{key}.class", data["class"]) if "class" in data else default_class
    albedo = field_range(source, f"{key}.albedo", data.get("albedo", 0.6), low=0, high=1)
    weight = field_number(source, f"{key}.weight", data.get("weight", 1.0), low=0, low_open=True, high=1e6)
    rest = data.get("rest", "stable")
    if rest not in ("stable", "upright"):
        raise InputError(f"{where(source, key + '.rest')}expected 'stable' or 'upright', got {describe(rest)}")
    obj_id = None
    if "obj_id" in data:
        obj_id = field_number(source, f"{key}.obj_id", data["obj_id"], low=1, high=2**31 - 1, integer=True)
    return ObjectSpec(class_name=class_name, mesh_ref=mesh_ref, scale=scale, albedo=albedo, weight=weight, rest=rest,
                      obj_id=obj_id)  # fmt: skip


def _clutter(source, key: str, data: Any, pool_size: int) -> ClutterSpec:
    if data is None:
        data = {}
    check_keys(source, key, data, ("count", "area", "min_gap", "max_tries", "unique"), "the clutter rule")
    default = ClutterSpec()
    count = field_range(source, f"{key}.count", data.get("count", list(default.count)), low=0, high=1000, integer=True)
    area = field_size2(source, f"{key}.area", data.get("area", list(default.area)))
    min_gap = field_number(source, f"{key}.min_gap", data.get("min_gap", default.min_gap), low=0, high=10)
    max_tries = field_number(source, f"{key}.max_tries", data.get("max_tries", default.max_tries), low=1, high=100000, integer=True)
    unique = data.get("unique", default.unique)
    if not isinstance(unique, bool):
        raise InputError(f"{where(source, key + '.unique')}expected true or false, got {describe(unique)}")
    if unique and count[1] > pool_size:
        raise InputError(
            f"{where(source, key + '.count')}at most {count[1]} unique objects asked for but the pool holds {pool_size}"
        )
    return ClutterSpec(count=count, area=area, min_gap=min_gap, max_tries=max_tries, unique=unique)


def _plane(source, key: str, data: Any) -> PlaneSpec | None:
    if data is None:
        return None
    default = PlaneSpec()
    check_keys(source, key, data, ("size", "albedo"), "the ground plane")
    size = field_size2(source, f"{key}.size", data.get("size", list(default.size)))
    albedo = field_range(source, f"{key}.albedo", data.get("albedo", list(default.albedo)), low=0, high=1)
    return PlaneSpec(size=size, albedo=albedo)


def _floor(source, key: str, data: Any, ground: PlaneSpec | None) -> FloorSpec | None:
    if data is None or data is False:
        return None
    if data is True:
        data = {}
    if ground is None:
        raise InputError(f"{where(source, key)}a floor lies below the ground plane (the table top): give a `ground`")
    default = FloorSpec()
    check_keys(source, key, data, ("depth", "size", "albedo"), "the floor")
    return FloorSpec(
        depth=field_number(source, f"{key}.depth", data.get("depth", default.depth), low=0, low_open=True, high=1e3),
        size=field_size2(source, f"{key}.size", data.get("size", list(default.size))),
        albedo=field_range(source, f"{key}.albedo", data.get("albedo", list(default.albedo)), low=0, high=1),
    )


def _wall(source, key: str, data: Any) -> WallSpec | None:
    if data is None or data is False:
        return None
    if data is True:
        data = {}
    default = WallSpec()
    check_keys(source, key, data, ("distance", "width", "height", "albedo"), "the back wall")
    return WallSpec(
        distance=field_number(source, f"{key}.distance", data.get("distance", default.distance), low=0, low_open=True, high=1e3),
        width=field_number(source, f"{key}.width", data.get("width", default.width), low=0, low_open=True, high=1e4),
        height=field_number(source, f"{key}.height", data.get("height", default.height), low=0, low_open=True, high=1e4),
        albedo=field_range(source, f"{key}.albedo", data.get("albedo", list(default.albedo)), low=0, high=1),
    )


def _camera(source, key: str, data: Any, has_wall: bool) -> CameraSpec:
    if data is None:
        data = {}
    default = CameraSpec()
    check_keys(
        source, key, data, ("distance", "elevation_deg", "azimuth_deg", "roll_deg", "look_at_jitter"), "the camera rule"
    )
    camera = CameraSpec(
        distance=field_range(source, f"{key}.distance", data.get("distance", list(default.distance)), low=0.01, high=1e3),
        elevation_deg=field_range(
            source, f"{key}.elevation_deg", data.get("elevation_deg", list(default.elevation_deg)), low=0.0, high=89.0
        ),
        azimuth_deg=field_range(
            source, f"{key}.azimuth_deg", data.get("azimuth_deg", list(default.azimuth_deg)), low=-360.0, high=360.0
        ),
        roll_deg=field_range(source, f"{key}.roll_deg", data.get("roll_deg", list(default.roll_deg)), low=-180.0, high=180.0),
        look_at_jitter=field_number(
            source, f"{key}.look_at_jitter", data.get("look_at_jitter", default.look_at_jitter), low=0, high=10
        ),
    )
    if has_wall and (camera.azimuth_deg[0] < -90.0 or camera.azimuth_deg[1] > 90.0):
        raise InputError(
            f"{where(source, key + '.azimuth_deg')}must lie within [-90, 90] when the scene has a wall"
            f" (the wall stands at +y behind the clutter; 0 = camera facing it), got {list(camera.azimuth_deg)}"
        )
    return camera


SCENE_KEYS = ("name", "frames", "objects", "clutter", "ground", "floor", "wall", "camera", "distractors")


def _scene(source, key: str, data: Any, base_dir: Path | None, index: int, models_dir: Path | None) -> SceneSpec:
    check_keys(source, key, data, SCENE_KEYS, "a scene")
    name = field_text(source, f"{key}.name", data["name"]) if "name" in data else f"scene{index}"
    frames = field_number(source, f"{key}.frames", data.get("frames", 1), low=1, high=10**9, integer=True)
    pool = data.get("objects")
    if pool is None:
        raise InputError(f"{where(source, key + '.objects')}missing: a scene needs a pool of at least one object")
    if not isinstance(pool, list) or not pool:
        raise InputError(f"{where(source, key + '.objects')}expected a non-empty list of objects, got {describe(pool)}")
    objects = tuple(_object(source, f"{key}.objects[{i}]", entry, base_dir, models_dir) for i, entry in enumerate(pool))
    wall = _wall(source, f"{key}.wall", data.get("wall"))
    ground = _plane(source, f"{key}.ground", data.get("ground", {}))
    floor = _floor(source, f"{key}.floor", data.get("floor"), ground)
    distractors = parse_distractors(source, f"{key}.distractors", data.get("distractors"),
                                    lambda sub, entry: _object(source, sub, entry, base_dir, models_dir),
                                    has_floor=floor is not None, has_ground=ground is not None)  # fmt: skip
    return SceneSpec(
        name=name,
        frames=frames,
        objects=objects,
        clutter=_clutter(source, f"{key}.clutter", data.get("clutter"), len(objects)),
        ground=ground,
        wall=wall,
        camera=_camera(source, f"{key}.camera", data.get("camera"), wall is not None),
        floor=floor,
        distractors=distractors,
    )


def scene_list_from_dict(data: Any, source: str | Path = "", base_dir: str | Path | None = None,
                         models_dir: str | Path | None = None) -> SceneList:  # fmt: skip
    """Validate a parsed scene list; relative mesh paths are resolved against ``base_dir``, then looked up by
    file name in the models folder (``models_dir``, else ``$DDSGEN_MODELS``, see :func:`models_folder`)."""
    source = str(source)
    base = Path(base_dir) if base_dir is not None else None
    if not isinstance(data, dict):
        raise InputError(f"{where(source)}a scene list must be a YAML mapping with `scenes:`, got {describe(data)}")
    check_keys(source, "", data, ("scenes", "description"), "a scene list")
    if "scenes" not in data:
        raise InputError(f"{where(source, 'scenes')}missing: a scene list needs `scenes:` with at least one scene")
    scenes = data["scenes"]
    if not isinstance(scenes, list) or not scenes:
        raise InputError(f"{where(source, 'scenes')}expected a non-empty list of scenes, got {describe(scenes)}")
    description = data.get("description", "")
    if not isinstance(description, str):
        raise InputError(f"{where(source, 'description')}expected text, got {describe(description)}")
    models = models_folder(models_dir)
    specs = tuple(_scene(source, f"scenes[{i}]", scene, base, i, models) for i, scene in enumerate(scenes))
    labelled = [(f"scenes[{i}].objects[{j}]", obj)
                for i, scene in enumerate(specs) for j, obj in enumerate(scene.objects)]  # fmt: skip
    return SceneList(scenes=specs, source=source, description=description, classes=class_table(labelled, source))


_DEFAULT: SceneList | None = None


def load_scene_list(path: str | Path | None, models_dir: str | Path | None = None) -> SceneList:
    """Read and validate a scene list YAML file; ``None`` gives the built-in default (no files needed).

    ``models_dir``: where mesh files not found at their path are looked up by name (default ``$DDSGEN_MODELS``).
    """
    global _DEFAULT
    if path is None:
        if _DEFAULT is None:
            _DEFAULT = scene_list_from_dict(default_scene_list_dict(), source=DEFAULT_SOURCE)
        return _DEFAULT
    path = Path(path)
    data = read_yaml(path, "scene list")
    if data is None:
        raise InputError(f"{path}: scene list is empty (expected `scenes:` with at least one scene)")
    return scene_list_from_dict(data, source=path, base_dir=path.parent, models_dir=models_dir)
