"""The differentiable scene-to-depth renderer: poses -> posed hits -> DepthSensor -> SensorOutput."""

from __future__ import annotations

import torch

from ddsgen.scene_gradients.hits import SceneTensors, posed_geometry


def render_depth(sensor, scene: SceneTensors, rotations: torch.Tensor, translations: torch.Tensor,
                 albedo: torch.Tensor, noise=None, seed=0, quantise: bool = True):  # fmt: skip
    """Simulate the sensor's depth of a scene whose parts are at the given poses.

    Differentiable with respect to ``rotations``, ``translations``, ``albedo`` and the sensor's
    parameters (the triangle assignment, visibility and shadows are the last ray cast's).

    Args:
        sensor: a :class:`~ddsgen.sensor.depth_sensor.DepthSensor` whose intrinsics match the cast
            (image (H, W)).
        scene: :class:`SceneTensors` of a ray cast (:meth:`RefinableScene.cast` or :func:`scene_tensors`).
        rotations: (N, 3, 3) ``cam_T_obj`` rotations of the N parts (objects then background).
        translations: (N, 3) their translations (m).
        albedo: (N,) their IR reflectances.
        noise: pre-drawn :class:`~ddsgen.sensor.ir.IRNoise` (reuse it across steps), else drawn from ``seed``.
        quantise: False gives the smooth function (IR counts and disparity not rounded), for gradient checks.

    Returns:
        :class:`~ddsgen.sensor.depth_sensor.SensorOutput` ((H, W): depth m, valid, ir, ...). For the
        noise-free depth, :func:`posed_geometry` (its ``clean_depth``) is the same computation without
        the sensor.
    """
    geometry = posed_geometry(scene, rotations, translations, albedo)
    return sensor(geometry, seed=seed, noise=noise, quantise=quantise)
