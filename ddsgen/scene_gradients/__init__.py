"""Scene gradients: the simulated depth as a differentiable function of the scene's object poses.

Ray casting (Embree) is not differentiable; it fixes, per pixel, the part and triangle hit. The hit
points are then recomputed in torch from the posed triangles (:mod:`.hits`), so the IR dots, the
matcher's disparity and the depth all follow a pose change; the scene is re-cast every few steps so
that visibility, silhouettes and shadows follow too.

Python API (tensors in, tensors out)::

    from ddsgen.scene_gradients import RefinableScene, render_depth, refine_poses

    scene = RefinableScene(frame_scene, intrinsics, preset.baseline_m, preset.shadow_bias_m,
                           ir_margin_px=preset.ir_margin_right_px)
    tensors = scene.cast()                       # SceneTensors: triangle ids of every pixel
    R, t = scene.poses()                         # (N, 3, 3), (N, 3): differentiable
    out = render_depth(sensor, tensors, R, t, scene.poses.albedo)   # SensorOutput, (H, W)
    out.depth[mask].sub(real[mask]).abs().mean().backward()         # d loss / d pose

    result = refine_poses(sensor, scene, real_depth)                # the whole loop (Adam + re-casts)
    results = refine_static_scene(sensor, views, real_depths)       # views of one static scene, together

Your own pose estimator can produce R, t (and albedo) any way it likes and call :func:`render_depth`.
"""

from ddsgen.scene_gradients.hits import SceneTensors, posed_geometry, scene_tensors
from ddsgen.scene_gradients.poses import ScenePoses, axis_angle_to_matrix, pose_difference
from ddsgen.scene_gradients.refine import RefineResult, RefineSettings, refine_poses, robust_depth_loss
from ddsgen.scene_gradients.render import render_depth
from ddsgen.scene_gradients.scene import RefinableScene
from ddsgen.scene_gradients.static_scene import refine_static_scene

__all__ = [
    "RefinableScene", "RefineResult", "RefineSettings", "ScenePoses", "SceneTensors", "axis_angle_to_matrix",
    "pose_difference", "posed_geometry", "refine_poses", "refine_static_scene", "render_depth", "robust_depth_loss",
    "scene_tensors",
]  # fmt: skip
