"""Per-pixel geometric features shared by the effects and by the residual analysis of ``diagnose``.

Plain functions on tensors of one frame, all (H, W) unless stated. They depend only on
the ray-cast geometry (a constant w.r.t. the sensor parameters) and the intrinsics, so
they carry no gradient.
"""

from __future__ import annotations

import numpy as np
import torch

from ddsgen.sensor.box_filter import box_mean
from ddsgen.sensor.effects.context import EffectContext

# A depth step larger than this fraction of the local depth is a discontinuity (5 %: 10 cm at 2 m).
EDGE_RELATIVE_STEP = 0.05
# Window (px) over which the projected signal is averaged for signal-based effects (the matcher's block).
SIGNAL_WINDOW_PX = 9


def incidence_angle_deg(points: torch.Tensor, normals: torch.Tensor) -> torch.Tensor:
    """Angle between the surface normal and the ray back to the camera (degrees, 0 = facing).

    Args:
        points: (H, W, 3) hit points in the camera frame (m).
        normals: (H, W, 3) unit normals facing the camera.

    Returns:
        (H, W) angle in [0, 90] degrees (90 where there is no hit).
    """
    ray = -points / torch.linalg.vector_norm(points, dim=-1, keepdim=True).clamp_min(1e-9)
    cos = (normals * ray).sum(-1).clamp(0.0, 1.0)
    return torch.rad2deg(torch.acos(cos))


def image_radius(height: int, width: int, fx, fy, cx, cy, device=None) -> torch.Tensor:
    """Normalised image radius sqrt(x^2 + y^2), x = (u - cx) / fx, y = (v - cy) / fy (dimensionless)."""
    x, y = normalised_coordinates(height, width, fx, fy, cx, cy, device)
    return torch.sqrt(x * x + y * y)


def normalised_coordinates(height: int, width: int, fx, fy, cx, cy, device=None) -> tuple[torch.Tensor, torch.Tensor]:
    """(x, y) = ((u - cx) / fx, (v - cy) / fy) on the pixel grid, each (H, W).

    fx, fy may be 0-d tensors (the result then carries their gradient).
    """
    u = torch.arange(width, dtype=torch.float32, device=device)
    v = torch.arange(height, dtype=torch.float32, device=device)
    x = ((u - float(cx)) / fx).reshape(1, width).expand(height, width)
    y = ((v - float(cy)) / fy).reshape(height, 1).expand(height, width)
    return x, y


def depth_edges(clean_depth: torch.Tensor, relative_step: float = EDGE_RELATIVE_STEP) -> torch.Tensor:
    """Pixels on either side of a depth discontinuity (bool (H, W)).

    A pixel is an edge pixel when one of its 4-neighbours differs in depth by more than
    ``relative_step`` times the nearer of the two depths, or when exactly one of them is a
    hit (object silhouette against nothing).
    """
    z = clean_depth
    hit = z > 0
    edge = torch.zeros_like(hit)
    for a, b, sa, sb in (
        (z[:, 1:], z[:, :-1], (slice(None), slice(1, None)), (slice(None), slice(None, -1))),
        (z[1:, :], z[:-1, :], (slice(1, None), slice(None)), (slice(None, -1), slice(None))),
    ):
        ha, hb = a > 0, b > 0
        near = torch.minimum(torch.where(ha, a, b), torch.where(hb, b, a))
        step = ((a - b).abs() > relative_step * near) & ha & hb
        step = step | (ha != hb)
        edge[sa] |= step
        edge[sb] |= step
    return edge


def edge_distance(clean_depth: torch.Tensor, relative_step: float = EDGE_RELATIVE_STEP) -> torch.Tensor:
    """Euclidean distance (px) from each pixel to the nearest depth-discontinuity pixel (0 on edges).

    A frame without any discontinuity gets a large constant (the image diagonal).
    """
    from scipy.ndimage import distance_transform_edt

    edge = depth_edges(clean_depth, relative_step).cpu().numpy()
    if not edge.any():
        h, w = edge.shape
        return torch.full(edge.shape, float(np.hypot(h, w)), dtype=torch.float32, device=clean_depth.device)
    dist = distance_transform_edt(~edge).astype(np.float32)
    return torch.from_numpy(dist).to(clean_depth.device)


def local_signal(signal: torch.Tensor, window: int = SIGNAL_WINDOW_PX) -> torch.Tensor:
    """Mean of the projected IR signal (counts) over a ``window`` x ``window`` box, same size as the input."""
    return box_mean(signal[None, None], window, padding="replicate")[0, 0]


#: Pixel axes an effect may follow (the residual axes of ``ddsgen diagnose``), with their units here.
PIXEL_AXES: dict[str, str] = {
    "radius": "normalised image radius sqrt(x^2 + y^2), x = (u - cx) / fx, y = (v - cy) / fy",
    "row": "normalised image row y = (v - cy) / fy (positive below the principal point)",
    "column": "normalised image column x = (u - cx) / fx (positive right of the principal point)",
    "edge_distance": "distance to the nearest depth edge of the clean depth (px)",
    "incidence": "incidence angle between surface normal and viewing ray (deg)",
    "depth": "measured depth (m)",
    "signal": "local mean of the projected IR signal over the matching window (counts)",
}


def pixel_axis(axis: str, ctx: EffectContext, x: torch.Tensor, stage: str) -> torch.Tensor:
    """The value of ``axis`` at every pixel (H, W), in the units of :data:`PIXEL_AXES`.

    Args:
        axis: a key of :data:`PIXEL_AXES`.
        ctx: the frame's context (:class:`~ddsgen.sensor.effects.context.EffectContext`).
        x: (H, W) the stage's input: disparity (px) at stage ``"disparity"``, depth (m) at
            ``"depth"`` and ``"validity"``; only the ``depth`` axis reads it.
        stage: the calling effect's stage.

    Image coordinates are normalised by the intrinsics, so a crop of a frame (with its
    shifted principal point) sees the same values as the full frame. The measured depth
    carries the gradient of the matcher's disparity; the geometric axes carry none.
    """
    h, w = x.shape
    if axis in ("radius", "row", "column"):
        xn, yn = normalised_coordinates(h, w, ctx.fx, ctx.fy, ctx.cx, ctx.cy, x.device)
        return {"radius": lambda: torch.sqrt(xn * xn + yn * yn), "row": lambda: yn, "column": lambda: xn}[axis]()
    if axis == "edge_distance":
        return ctx.feature("edge_distance", lambda: edge_distance(ctx.geometry.clean_depth))
    if axis == "incidence":
        g = ctx.geometry
        return ctx.feature("incidence_deg", lambda: incidence_angle_deg(g.points, g.normals))
    if axis == "signal":
        return ctx.feature("local_signal", lambda: local_signal(ctx.signal))
    if axis == "depth":
        if stage != "disparity":
            return x
        positive = x > 1e-3  # z = f b / d where there is a match, as the sensor converts it
        safe = torch.where(positive, x, torch.ones_like(x))
        return torch.where(positive, ctx.fx * ctx.baseline / safe, torch.zeros_like(x))
    raise KeyError(f"unknown pixel axis {axis!r} (known: {', '.join(PIXEL_AXES)})")
