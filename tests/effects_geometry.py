"""Analytic test geometry for the effect and diagnose tests: a plane, optionally a rectangle in front of it.

Ray casting is exact and needs no meshes: camera at the origin (OpenCV axes), the
projector at (+b, 0, 0), a background plane and an optional fronto-parallel rectangle
(which casts a projector shadow on the plane and makes depth edges).
"""

from __future__ import annotations

import math

import numpy as np
import torch

from ddsgen.preset import load_preset
from ddsgen.sensor.geometry import SensorGeometry


def small_preset(width: int = 160, height: int = 120, **changes):
    """The Kinect V1 preset scaled down to a small image (same field of view and baseline)."""
    base = load_preset("kinect_v1")
    scale = width / base.width_px
    changes = {"registration_shift_px": base.registration_shift_px * scale, **changes}
    return base.replace(width_px=width, height_px=height, focal_px=base.focal_px * scale, focal_y_px=None,
                        cx_px=None, cy_px=None, band_rows=height, **changes)  # fmt: skip


def plane_geometry(intr, normal=(0.0, 0.0, -1.0), distance=1.5, albedo=0.6, rect=None, baseline=0.075) -> SensorGeometry:
    """Ray-cast a plane {P : n.P = -distance} (n facing the camera) and an optional rectangle.

    Args:
        intr: Intrinsics.
        normal: plane normal (pointing towards the camera side); normalised here.
        distance: distance of the plane from the camera (m).
        albedo: plane albedo.
        rect: optional dict(z, x0, x1, y0, y1, albedo): fronto-parallel rectangle at depth z (m),
            extent in camera x and y (m).
        baseline: projector position (+b, 0, 0) for the shadow test (m).
    """
    n = np.asarray(normal, np.float64)
    n = n / np.linalg.norm(n)
    u, v = np.meshgrid(np.arange(intr.width, dtype=np.float64), np.arange(intr.height, dtype=np.float64))
    d = np.stack([(u - intr.cx) / intr.fx, (v - intr.cy) / intr.fy, np.ones_like(u)], -1)
    denom = d @ n
    t = np.where(denom < -1e-9, -distance / np.where(denom < -1e-9, denom, -1.0), 0.0)
    hit = t > 0
    points = d * t[..., None]
    normals = np.broadcast_to(n, points.shape).copy()
    alb = np.full(t.shape, albedo)
    shadow = np.zeros(t.shape, bool)
    if rect is not None:
        zr = rect["z"]
        pr = d * zr
        inside = (pr[..., 0] >= rect["x0"]) & (pr[..., 0] <= rect["x1"]) & (pr[..., 1] >= rect["y0"]) & (pr[..., 1] <= rect["y1"])
        front = inside & (~hit | (zr < points[..., 2]))
        # Projector shadow of the rectangle on the plane: segment P -> (b, 0, 0) crosses z = zr inside the rectangle.
        pz = points[..., 2]
        s = np.where(pz > zr, (pz - zr) / np.maximum(pz, 1e-9), -1.0)
        q = points + s[..., None] * (np.array([baseline, 0.0, 0.0]) - points)
        shadow = hit & ~front & (s > 0) & (q[..., 0] >= rect["x0"]) & (q[..., 0] <= rect["x1"]) & (q[..., 1] >= rect["y0"]) & (q[..., 1] <= rect["y1"])
        points[front] = pr[front]
        normals[front] = (0.0, 0.0, -1.0)
        alb[front] = rect.get("albedo", albedo)
        hit = hit | front
    points[~hit] = 0.0
    normals[~hit] = 0.0

    def f(a, dtype=torch.float32):
        return torch.as_tensor(np.ascontiguousarray(a)).to(dtype)

    return SensorGeometry(
        points=f(points), normals=f(normals), albedo=f(np.where(hit, alb, 0.0)), hit=f(hit, torch.bool),
        shadow=f(shadow, torch.bool), clean_depth=f(np.where(hit, points[..., 2], 0.0)),
    )  # fmt: skip


def tilted_normal(angle_deg: float, axis: str = "x") -> tuple[float, float, float]:
    """Unit normal facing the camera, tilted by ``angle_deg`` from the optical axis about ``axis``."""
    a = math.radians(angle_deg)
    if axis == "x":  # floor-like: normal rotates towards -y (up)
        return (0.0, -math.sin(a), -math.cos(a))
    return (-math.sin(a), 0.0, -math.cos(a))
