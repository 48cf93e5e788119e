"""A scene whose rigid parts' poses are learnable, re-cast on demand."""

from __future__ import annotations

import dataclasses

import numpy as np

from ddsgen.preset import Intrinsics
from ddsgen.raycast import cast, ray_directions
from ddsgen.scene_gradients.hits import SceneTensors, scene_tensors
from ddsgen.scene_gradients.poses import ScenePoses
from ddsgen.sensor.ir_margin import margin_intrinsics


class RefinableScene:
    """A :class:`~ddsgen.scene.sampling.FrameScene` with a :class:`ScenePoses` over its parts.

    Parts are ``scene.objects + scene.background`` in that order (the ray cast's ``owner`` order).
    Objects are always free; background parts (the support plane, walls) only with ``refine_background``.

    Args:
        scene: the FrameScene at the initial poses.
        intrinsics: the camera (image (H, W)); may be a crop of a larger image.
        baseline_m, shadow_bias_m: the sensor's projector offset and shadow bias (for the shadow rays).
        refine_background: let the background parts (support plane) move too.
        ir_margin_px: columns the IR camera sees beyond the right edge (the preset's ``ir_margin_right_px``):
            cast and posed like the image, so the sensor's last columns have whole windows.
    """

    def __init__(self, scene, intrinsics: Intrinsics, baseline_m: float, shadow_bias_m: float,
                 refine_background: bool = True, ir_margin_px: int = 0):  # fmt: skip
        self.scene = scene
        self.intrinsics = intrinsics
        self.ir_margin_px = int(ir_margin_px)
        self.baseline_m = float(baseline_m)
        self.shadow_bias_m = float(shadow_bias_m)
        self.parts = list(scene.objects) + list(scene.background)
        self.cam_T_world = np.linalg.inv(np.asarray(scene.world_T_cam, dtype=np.float64))
        initial = np.stack([self.cam_T_world @ np.asarray(p.world_T_obj, dtype=np.float64) for p in self.parts])
        centres = np.stack([_centre(p.mesh, T) for p, T in zip(self.parts, initial)])
        free = [True] * len(scene.objects) + [bool(refine_background)] * len(scene.background)
        self.poses = ScenePoses(initial, centres, [p.albedo for p in self.parts], free)
        self.n_objects = len(scene.objects)

    def current_scene(self):
        """The FrameScene with every part at its current pose and albedo (a copy; the input is untouched)."""
        T = self.poses.matrices()
        world_T_cam = np.asarray(self.scene.world_T_cam, dtype=np.float64)
        albedo = self.poses.albedo.detach().numpy()
        placed = [dataclasses.replace(p, world_T_obj=world_T_cam @ T[k], albedo=float(albedo[k]))
                  for k, p in enumerate(self.parts)]  # fmt: skip
        n = self.n_objects
        return dataclasses.replace(self.scene, objects=placed[:n], background=placed[n:])

    def cast(self) -> SceneTensors:
        """Ray-cast the scene at the current poses (visibility, triangle ids, projector shadows)."""
        scene, meshes = self.current_scene(), [p.mesh for p in self.parts]
        hits = cast(scene, self.intrinsics, self.baseline_m, self.shadow_bias_m)
        tensors = scene_tensors(meshes, hits, ray_directions(self.intrinsics))
        if self.ir_margin_px > 0:
            strip = margin_intrinsics(self.intrinsics, self.ir_margin_px)
            margin_hits = cast(scene, strip, self.baseline_m, self.shadow_bias_m)
            tensors.ir_margin = scene_tensors(meshes, margin_hits, ray_directions(strip))
        return tensors

    def object_poses(self) -> np.ndarray:
        """(n_objects, 4, 4) current ``cam_T_obj`` of the objects (m)."""
        return self.poses.matrices()[: self.n_objects]


def _centre(mesh, cam_T_obj: np.ndarray) -> np.ndarray:
    """The mesh's bounding-box centre in the camera frame (planes: the pose's origin)."""
    bounds = np.asarray(mesh.bounds, dtype=np.float64)
    local = bounds.mean(axis=0)
    return cam_T_obj[:3, :3] @ local + cam_T_obj[:3, 3]
