"""The library of effects (each registers itself under its preset name).

Every effect is a differentiable torch module (or a soft relaxation of a discrete rule) -- except the lens
warp, a nearest-pixel resampling that diagnose searches on a grid (``differentiable = False``) -- acting at one
stage of :class:`~ddsgen.sensor.depth_sensor.DepthSensor`; with its parameters at their ``neutral`` values it
leaves the sensor's output unchanged. The
``axis`` of an effect names the residual axis of ``ddsgen diagnose`` along which its
signature shows: ``depth``, ``incidence``, ``radius``, ``row``, ``column``,
``edge_distance`` or ``signal``.

Validity effects return a keep-probability in [0, 1]; the sensor multiplies it into its
soft validity and keeps a pixel when the product exceeds 0.5, so each rule below drops a
pixel once its keep-probability falls under 0.5 and is differentiable around that point.
"""

from __future__ import annotations

import numpy as np
import torch

from ddsgen.effect_params import EFFECTS
from ddsgen.sensor.effects import REGISTRY, register
from ddsgen.sensor.effects.base import Effect
from ddsgen.sensor.effects.context import EffectContext
from ddsgen.sensor.effects.features import (
    edge_distance,
    incidence_angle_deg,
    local_signal,
    normalised_coordinates,
)


def bilinear_sample(image: torch.Tensor, us: torch.Tensor, vs: torch.Tensor) -> torch.Tensor:
    """Sample ``image`` (H, W) at pixel coordinates (us, vs) (each (H, W)), bilinear, border-clamped.

    Differentiable in the image and in the coordinates. Exact at integer coordinates (a zero
    displacement returns the image bit for bit, which keeps neutral effects neutral).
    """
    h, w = image.shape
    us = us.clamp(0.0, w - 1.0)
    vs = vs.clamp(0.0, h - 1.0)
    u0 = us.detach().floor().clamp(max=w - 2)
    v0 = vs.detach().floor().clamp(max=h - 2)
    fu = us - u0
    fv = vs - v0
    u0, v0 = u0.long(), v0.long()
    flat = image.reshape(-1)
    top = flat[v0 * w + u0] * (1 - fu) + flat[v0 * w + u0 + 1] * fu
    bottom = flat[(v0 + 1) * w + u0] * (1 - fu) + flat[(v0 + 1) * w + u0 + 1] * fu
    return top * (1 - fv) + bottom * fv


def radial_displacement(k1: torch.Tensor, k2: torch.Tensor, height: int, width: int,
                        ctx: EffectContext) -> tuple[torch.Tensor, torch.Tensor]:  # fmt: skip
    """(du, dv) (H, W) px of Brown's radial model: pixel (u, v) of the distorted image shows the ideal image at
    (u + du, v + dv) = the ideal point x (1 + k1 r^2 + k2 r^4), x = (u - cx) / fx normalised (likewise y)."""
    x, y = normalised_coordinates(height, width, ctx.fx, ctx.fy, ctx.cx, ctx.cy, k1.device)
    r2 = x * x + y * y
    radial = k1 * r2 + k2 * r2 * r2
    return x * ctx.fx * radial, y * ctx.fy * radial


@register
class LensWarp(Effect):
    """Uncalibrated radial distortion of the pixel grid (Brown model, k1 and k2): the depth image is warped."""

    name = "lens_warp"
    stage = "image"
    description = (
        "The IR camera's lens bends each pixel's viewing ray radially (uncorrected k1, k2 distortion) while the "
        "depth along the ray stays right, because the reference pattern was captured through the same lens: "
        "the depth image is the ideal one warped, objects shifted towards or away from the image centre."
    )
    signature = (
        "depth edges displaced radially by up to a few pixels towards the corners (positive and negative "
        "residuals on opposite sides of every object), flat surfaces nearly unbiased"
    )
    axis = "radius"
    params = EFFECTS["lens_warp"].params
    differentiable = False

    def forward(self, maps: tuple[torch.Tensor, ...], ctx: EffectContext) -> tuple[torch.Tensor, ...]:
        """Each of ``maps`` (H, W; the third is the validity, bool) sampled at the ideal pixel nearest to where each
        device pixel looks (nearest: depth is never mixed across an edge)."""
        h, w = maps[0].shape
        index = warp_index(self.value("k1").detach(), self.value("k2").detach(), h, w, ctx, scene_box(maps[2]))
        return tuple(m.reshape(-1)[index].reshape(h, w) for m in maps)

    def warp_labels(self, labels: tuple[np.ndarray, ...], fx: float, fy: float, cx: float, cy: float):
        """Each of ``labels`` ((H, W) numpy arrays of the ideal camera: instance ids, clean depth) resampled as the
        depth is, so that a render's masks stay on its depth (no device bands: the whole image is the scene's)."""
        h, w = labels[0].shape
        ctx = EffectContext(fx=fx, fy=fy, cx=cx, cy=cy, baseline=0.0)
        index = warp_index(self.value("k1").detach(), self.value("k2").detach(), h, w, ctx).numpy()
        return tuple(np.asarray(a).reshape(-1)[index].reshape(h, w) for a in labels)


def scene_box(valid: torch.Tensor) -> tuple[int, int, int, int]:
    """(u_lo, u_hi, v_lo, v_hi) px, inclusive: the image without its border bands, the whole columns and rows at its
    edges with no valid pixel (the matcher's margin, a window the device cuts). Those bands belong to the device's
    pixel grid, not to the scene: a warp leaves them where they are and does not spread them inward."""
    cols = torch.nonzero(valid.any(0)).reshape(-1)
    rows = torch.nonzero(valid.any(1)).reshape(-1)
    if not cols.numel():
        return 0, valid.shape[1] - 1, 0, valid.shape[0] - 1
    return int(cols[0]), int(cols[-1]), int(rows[0]), int(rows[-1])


def warp_index(k1: torch.Tensor, k2: torch.Tensor, height: int, width: int, ctx: EffectContext,
               box: tuple[int, int, int, int] | None = None) -> torch.Tensor:  # fmt: skip
    """(H W,) flat index of the ideal pixel nearest to where each pixel of a Brown-warped grid looks
    (:func:`radial_displacement`). Within ``box`` (:func:`scene_box`; default the whole image) a pixel looking beyond
    it takes the box's nearest border pixel: the ray cast covers the ideal image only, and beyond it the scene goes
    on (an invalid band there would be an artefact); pixels outside the box keep their own value."""
    u_lo, u_hi, v_lo, v_hi = box or (0, width - 1, 0, height - 1)
    du, dv = radial_displacement(k1, k2, height, width, ctx)
    u0 = torch.arange(width, device=du.device).reshape(1, width)
    v0 = torch.arange(height, device=du.device).reshape(height, 1)
    u = torch.round(u0 + du).long().clamp(u_lo, u_hi)
    v = torch.round(v0 + dv).long().clamp(v_lo, v_hi)
    inside = (u0 >= u_lo) & (u0 <= u_hi) & (v0 >= v_lo) & (v0 <= v_hi)
    return torch.where(inside, v * width + u, v0 * width + u0).reshape(-1)


@register
class LensDistortion(Effect):
    """Uncalibrated radial distortion of the IR camera (Brown model, k1 and k2)."""

    name = "lens_distortion"
    stage = "ir"
    description = (
        "The IR camera lens bends rays radially (uncorrected k1, k2 distortion), so dots near the "
        "image corners land off their calibrated positions and the matcher reads a wrong disparity there."
    )
    signature = (
        "depth bias that is zero at the image centre, grows like r^3 towards the corners and like z^2 "
        "with depth, with opposite signs left and right of the principal point; more dropout in the corners"
    )
    axis = "radius"
    params = EFFECTS["lens_distortion"].params

    def displacement(self, height: int, width: int, ctx: EffectContext) -> tuple[torch.Tensor, torch.Tensor]:
        """(du, dv) (H, W) px: pixel (u, v) of the distorted image shows the ideal image at (u + du, v + dv)."""
        return radial_displacement(self.value("k1"), self.value("k2"), height, width, ctx)

    def forward(self, ir: torch.Tensor, ctx: EffectContext) -> torch.Tensor:
        """ir (H, W) counts -> the same image seen through the distorting lens."""
        h, w = ir.shape
        du, dv = self.displacement(h, w, ctx)
        u = torch.arange(w, dtype=ir.dtype, device=ir.device).reshape(1, w)
        v = torch.arange(h, dtype=ir.dtype, device=ir.device).reshape(h, 1)
        return bilinear_sample(ir, u + du, v + dv)


@register
class DisparityOffset(Effect):
    """The reference pattern is mis-registered by delta px: every disparity is off by delta."""

    name = "disparity_offset"
    stage = "disparity"
    description = (
        "The factory reference pattern is mis-registered by a constant disparity offset, "
        "so depth is biased by an amount that grows with the square of the distance."
    )
    signature = "depth bias proportional to z^2 (sign of -offset), independent of angle and image position"
    axis = "depth"
    params = EFFECTS["disparity_offset"].params

    def forward(self, disparity: torch.Tensor, ctx: EffectContext) -> torch.Tensor:
        return disparity + self.value("offset_px")


@register
class DepthScale(Effect):
    """Depth is scaled by (1 + epsilon): a mis-calibrated depth conversion (e.g. f*b of the firmware)."""

    name = "depth_scale"
    stage = "depth"
    description = (
        "The sensor converts disparity to depth with a slightly wrong focal-length-times-baseline "
        "constant, so every depth is off by the same percentage."
    )
    signature = "depth bias proportional to z (a constant relative error), independent of angle and image position"
    axis = "depth"
    params = EFFECTS["depth_scale"].params

    def forward(self, depth: torch.Tensor, ctx: EffectContext) -> torch.Tensor:
        return depth * (1.0 + self.value("scale_error"))


@register
class GrazingDropout(Effect):
    """No usable return from surfaces seen beyond an incidence angle (soft ramp of 3 degrees)."""

    name = "grazing_dropout"
    stage = "validity"
    description = (
        "Surfaces seen at a grazing angle smear the projected dots and return too little light, "
        "so the sensor reports no depth beyond a maximum incidence angle."
    )
    signature = "missing depth on steeply tilted surfaces (floor far away, object sides), none on surfaces facing the camera"
    axis = "incidence"
    RAMP_DEG = 3.0  # keep-probability falls from 1 to 0 between angle_deg and angle_deg + RAMP_DEG
    params = EFFECTS["grazing_dropout"].params

    def forward(self, depth: torch.Tensor, ctx: EffectContext) -> torch.Tensor:
        g = ctx.geometry
        theta = ctx.feature("incidence_deg", lambda: incidence_angle_deg(g.points, g.normals))
        return 1.0 - ((theta - self.value("angle_deg")) / self.RAMP_DEG).clamp(0.0, 1.0)


@register
class EdgeDropout(Effect):
    """The matcher fails in a band of ``width_px`` px on either side of depth discontinuities."""

    name = "edge_dropout"
    stage = "validity"
    description = (
        "Matching windows that straddle an object boundary see two depths at once and the sensor "
        "rejects them, leaving a band of missing depth along every depth discontinuity."
    )
    signature = "missing depth within a few pixels of depth edges (object silhouettes), full coverage elsewhere"
    axis = "edge_distance"
    params = EFFECTS["edge_dropout"].params

    def forward(self, depth: torch.Tensor, ctx: EffectContext) -> torch.Tensor:
        dist = ctx.feature("edge_distance", lambda: edge_distance(ctx.geometry.clean_depth))
        # Soft band: keep = 0 inside (dist < w - 1), 1 outside (dist > w), linear in between.
        return 1.0 - (self.value("width_px") - dist).clamp(0.0, 1.0)


@register
class LowSignalDropout(Effect):
    """Matching fails where the local projected signal falls below a threshold (dark or distant surfaces)."""

    name = "low_signal_dropout"
    stage = "validity"
    description = (
        "On dark or distant surfaces the projected dots are too faint for the sensor's detector, "
        "which reports no depth where the local dot signal falls below a threshold."
    )
    signature = "missing depth on low-albedo objects and far surfaces, growing as the IR signal falls"
    axis = "signal"
    SHARPNESS = 4.0  # keep = 1 / (1 + (threshold / signal)^SHARPNESS), computed as a sigmoid of the log ratio
    params = EFFECTS["low_signal_dropout"].params

    def forward(self, depth: torch.Tensor, ctx: EffectContext) -> torch.Tensor:
        level = ctx.feature("local_signal", lambda: local_signal(ctx.signal))
        log_ratio = torch.log(level.clamp_min(1e-12)) - torch.log(self.value("threshold_counts").clamp_min(1e-12))
        return torch.sigmoid(self.SHARPNESS * log_ratio)


def describe_library() -> list[dict]:
    """The library as plain data (name, stage, description, signature, axis, params) for reports and --help."""
    out = []
    for name, cls in sorted(REGISTRY.items()):
        out.append(
            {
                "name": name,
                "stage": cls.stage,
                "description": cls.description,
                "signature": cls.signature,
                "axis": cls.axis,
                "generic": cls.generic,
                "options": {k: list(v) for k, v in cls.options.items()},
                "params": {
                    k: {"neutral": p.neutral, "low": p.low, "high": p.high, "unit": p.unit, "typical": p.typical, "help": p.help}
                    for k, p in cls.params.items()
                },
            }
        )
    return out

