"""Spatially varying disparity distortion (Herrera, Kannala & Heikkilä 2012, TPAMI 34(10)).

Herrera et al. found that a Kinect's disparity carries a fixed per-pixel pattern whose
effect fades as disparity grows (near surfaces):

    d' = d + D(u, v) exp(alpha0 - alpha1 d)

They fitted D per pixel from many calibration frames. Here D is a smooth field given by a
coarse grid of GRID_ROWS x GRID_COLS control values over the normalised image plane
(x = (u - cx) / fx in [-X_EXTENT, X_EXTENT], y likewise with Y_EXTENT), bicubically
interpolated (``torch.nn.functional.grid_sample``), so that a few frames constrain it and a
crop of a frame sees the same field as the whole frame. D is the distortion (px) at zero
disparity (infinitely far) when alpha0 = 0; alpha1 (1/px) sets how fast it fades.

Neutral: every control value 0 (then d' = d bit for bit, whatever alpha0 and alpha1).

A typical device (an example, not a default; kinect_v1 keeps it off): Herrera et al. report
a pattern of a few Kinect disparity units (1 unit = 1/8 px), i.e. a few tenths of a pixel,
strongest toward the image corners and edges; the real LineMOD/IC-BIN frames of
shared/data show a smooth radial depth pattern of about +-6 mm at ~1 m, i.e. +-0.25 px::

    {name: disparity_distortion, alpha0: 0.0, alpha1: 0.02,
     grid: [0.3, 0.1, 0.0, 0.1, 0.3,
            0.1, -0.05, -0.1, -0.05, 0.1,
            0.3, 0.1, 0.0, 0.1, 0.3]}

(with alpha1 = 0.02 /px the pattern keeps 81 % of its strength at 4 m (d = 10.7 px), 65 % at 2 m,
42 % at 1 m and 12 % at 0.4 m, for the Kinect's f b = 42.9 px m).
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from ddsgen.sensor.effects import register
from ddsgen.sensor.effects.axis_terms import least_squares
from ddsgen.effect_params import EFFECTS, GRID_COLS, GRID_KEYS, GRID_ROWS
from ddsgen.sensor.effects.base import Effect
from ddsgen.sensor.effects.context import EffectContext
from ddsgen.sensor.effects.features import normalised_coordinates

#: Half-extent of the control grid in normalised image coordinates (a 57 x 43 deg Kinect image spans
#: |x| <= 0.56, |y| <= 0.42); points beyond it take the value at the grid's border.
X_EXTENT, Y_EXTENT = 0.6, 0.48


def sample_field(grid: torch.Tensor, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """Bicubic interpolation of control values at normalised image coordinates.

    Args:
        grid: (GRID_ROWS, GRID_COLS) control values, row 0 at y = -Y_EXTENT (top), column 0 at
            x = -X_EXTENT (left).
        x, y: normalised coordinates, any equal shape.

    Returns:
        The field at (x, y), shape of ``x``; differentiable in ``grid`` and the coordinates.
    """
    loc = torch.stack([x / X_EXTENT, y / Y_EXTENT], -1).to(grid.dtype).reshape(1, -1, 1, 2)
    out = F.grid_sample(grid[None, None], loc, mode="bicubic", padding_mode="border", align_corners=True)
    return out.reshape(x.shape)


@register
class DisparityDistortion(Effect):
    """Herrera 2012's per-pixel disparity distortion pattern, fading with disparity."""

    name = "disparity_distortion"
    stage = "disparity"
    description = (
        "The sensor's disparity carries a fixed smooth per-pixel distortion pattern, strongest at far range "
        "and fading as disparity grows, so flat surfaces come out warped by the same pattern in every frame."
    )
    signature = (
        "a fixed smooth depth-error pattern over the image (typically stronger toward corners and edges), "
        "growing faster than z^2 with depth, the same in every frame"
    )
    axis = "radius"
    params = EFFECTS["disparity_distortion"].params
    groups = EFFECTS["disparity_distortion"].groups

    def grid(self) -> torch.Tensor:
        """(GRID_ROWS, GRID_COLS) control values (px, differentiable)."""
        return torch.stack([self.value(k) for k in GRID_KEYS]).reshape(GRID_ROWS, GRID_COLS)

    def pattern(self, height: int, width: int, ctx: EffectContext) -> torch.Tensor:
        """D(u, v) (H, W) px: the distortion at zero disparity over the pixel grid."""
        grid = self.grid()
        x, y = normalised_coordinates(height, width, ctx.fx, ctx.fy, ctx.cx, ctx.cy, grid.device)
        return sample_field(grid, x, y)

    def decay(self, disparity: torch.Tensor) -> torch.Tensor:
        """exp(alpha0 - alpha1 d) (same shape as ``disparity``, px)."""
        return torch.exp(self.value("alpha0") - self.value("alpha1") * disparity)

    def forward(self, disparity: torch.Tensor, ctx: EffectContext) -> torch.Tensor:
        """disparity (H, W) px -> d + D(u, v) exp(alpha0 - alpha1 d) where a match exists (d > 0)."""
        h, w = disparity.shape
        shift = self.pattern(h, w, ctx).to(disparity.dtype) * self.decay(disparity)
        return torch.where(disparity > 0, disparity + shift, disparity)


def fit_distortion_grid(x, y, disparity, target, alpha0: float = 0.0, alpha1: float = 0.0, weights=None,
                        nuisance=None, keep_quantile: float = 1.0) -> list[float]:  # fmt: skip
    """Least-squares control values of ``disparity_distortion`` for a disparity residual, alpha0/alpha1 given.

    The effect is linear in its control values: d' - d = sum_k g_k B_k(x, y) exp(alpha0 - alpha1 d),
    with B_k the interpolation of the k-th unit grid. A starting point of a search (e.g. diagnose's).

    Args:
        x, y: (N,) normalised image coordinates of the pixels.
        disparity: (N,) their disparity (px).
        target: (N,) what the effect should add, e.g. d_real - d_sim (px).
        weights: optional (N,) non-negative weights.
        nuisance: optional (N, M) regressors fitted jointly and discarded (see
            :func:`~ddsgen.sensor.effects.axis_terms.least_squares`).
        keep_quantile: trimmed fit (see :func:`~ddsgen.sensor.effects.axis_terms.least_squares`), e.g. 0.8.

    Returns:
        len(GRID_KEYS) control values (row-major, clipped to +-2 px): the entry's ``grid`` list.
    """
    xs = torch.as_tensor(np.asarray(x, np.float64))
    ys = torch.as_tensor(np.asarray(y, np.float64))
    decay = np.exp(alpha0 - alpha1 * np.asarray(disparity, np.float64))
    unit = torch.eye(len(GRID_KEYS), dtype=torch.float64).reshape(-1, GRID_ROWS, GRID_COLS)
    design = np.stack([sample_field(g, xs, ys).numpy() for g in unit], 1) * decay[:, None]
    coef = least_squares(design, target, weights, nuisance, keep_quantile)
    bound = DisparityDistortion.params[GRID_KEYS[0]].high
    return [float(np.clip(c, -bound, bound)) for c in coef]
