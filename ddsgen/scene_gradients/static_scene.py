"""Refine a static scene seen in several frames: each object's pose correction shared by every view.

One frame's depth pins an object's pose only to its own noise: the speckle is fixed to the scene and
correlated over the matching window, so an object of ~100 px holds some 100 independent depth errors,
and the pose fitted to them is off by ~0.5 deg (docs/scene_gradients.md). Another viewpoint sees
another speckle on the object, so views of one static scene (a BOP scene's frames, a turntable or
hand-held sequence) average it down, if the object is moved alike in all of them. A correction in
the object's own frame does that (:class:`~ddsgen.scene_gradients.poses.SharedObjectCorrections`);
each view keeps its own support-plane correction.

The views' initial poses must place each object consistently (the same object-to-world pose, as the
poses of a static scene's frames do); the refinement then finds the one correction that fits all.
"""

from __future__ import annotations

import numpy as np

from ddsgen.scene_gradients.poses import SharedObjectCorrections
from ddsgen.scene_gradients.refine import RefineSettings, refine_views


def refine_static_scene(sensor, scenes: list, real_depths: list, settings: RefineSettings | None = None,
                        progress: bool = False) -> list:  # fmt: skip
    """Refine the objects of several views of one static scene together.

    Args:
        sensor: :class:`~ddsgen.sensor.depth_sensor.DepthSensor` (given each view's camera in turn).
        scenes: V :class:`~ddsgen.scene_gradients.scene.RefinableScene`, each with the same objects in
            the same order (checked by mesh identity and vertex count) at consistent initial poses.
        real_depths: V (H_v, W_v) float32 real depth images (m, 0 = invalid), one per view.
        settings: :class:`RefineSettings` (the step count is per refinement, not per view).
        progress: show a progress bar.

    Returns:
        one :class:`~ddsgen.scene_gradients.refine.RefineResult` per view; ``refined`` of an object is
        its initial pose of that view with the shared correction applied.
    """
    if not scenes:
        raise ValueError("no views to refine")
    n = scenes[0].n_objects
    for k, scene in enumerate(scenes[1:], start=1):
        if scene.n_objects != n or any(_mesh_key(a.mesh) != _mesh_key(b.mesh)
                                        for a, b in zip(scene.parts[:n], scenes[0].parts[:n])):  # fmt: skip
            raise ValueError(f"view {k} does not hold the objects of view 0 in the same order")
    shared = SharedObjectCorrections(n)
    for scene in scenes:
        scene.poses.share_objects(shared)
    return refine_views(sensor, scenes, real_depths, settings, progress)


def _mesh_key(mesh) -> tuple:
    return len(mesh.vertices), tuple(np.round(np.asarray(mesh.bounds, dtype=np.float64).ravel(), 6))
