"""Analytic test geometry for the sensor: planes seen by a pinhole camera (no ray caster needed)."""

from __future__ import annotations

import math

import numpy as np
import torch

from ddsgen.preset import Intrinsics, load_preset
from ddsgen.sensor.geometry import SensorGeometry


def small_kinect(width: int = 160, height: int = 120, **changes):
    """kinect_v1 at reduced resolution: focal scaled with the width so angles stay the same."""
    base = load_preset("kinect_v1")
    scale = width / base.width_px
    return base.replace(width_px=width, height_px=height, focal_px=base.focal_px * scale,
                        focal_y_px=base.focal_y_px * scale, cx_px=None, cy_px=None,
                        registration_shift_px=base.registration_shift_px * scale, **changes)  # fmt: skip


def plane_geometry(intr: Intrinsics, z: float, tilt_deg: float = 0.0, albedo: float = 0.8) -> SensorGeometry:
    """A plane through (0, 0, z), rotated by ``tilt_deg`` about the camera's vertical axis.

    Returns the exact hit points, normals (facing the camera) and z-depth per pixel.
    """
    u, v = np.meshgrid(np.arange(intr.width, dtype=np.float64), np.arange(intr.height, dtype=np.float64))
    rays = np.stack([(u - intr.cx) / intr.fx, (v - intr.cy) / intr.fy, np.ones_like(u)], axis=-1)
    a = math.radians(tilt_deg)
    normal = np.array([math.sin(a), 0.0, -math.cos(a)])  # towards the camera
    t = (normal @ np.array([0.0, 0.0, z])) / (rays @ normal)
    points = rays * t[..., None]
    hit = (t > 0) & np.isfinite(t)
    shape = (intr.height, intr.width)
    return SensorGeometry(
        points=torch.tensor(points, dtype=torch.float32),
        normals=torch.tensor(np.broadcast_to(normal, points.shape).copy(), dtype=torch.float32),
        albedo=torch.full(shape, albedo),
        hit=torch.tensor(hit),
        shadow=torch.zeros(shape, dtype=torch.bool),
        clean_depth=torch.tensor(np.where(hit, points[..., 2], 0.0), dtype=torch.float32),
    )
