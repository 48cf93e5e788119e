"""DepthSensor: the differentiable structured-light sensor, from hit geometry to depth.

    geometry (ray cast, constant) -> IR image -> [ir effects] -> block matching
    -> the device's smoothing along the rows -> [disparity effects] -> depth z = f b / d -> [depth effects] -> validity
    -> the device's clean-up (specks and small holes) (-> optional post-processing CNN)

Everything in :meth:`DepthSensor.forward` is a torch function of the sensor's
parameters. Positive parameters are stored as logarithms (baseline, focal length,
emitted intensity, noise scales, soft-argmax temperature), so a gradient step can
never make them negative.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import nn

from ddsgen.preset import Intrinsics, SensorPreset
from ddsgen.sensor.cleanup import device_cleanup
from ddsgen.sensor.effects import build_effects
from ddsgen.sensor.geometry import SensorGeometry
from ddsgen.sensor.ir import IRNoise, render_ir
from ddsgen.sensor.matcher import match
from ddsgen.sensor.output_window import OutputWindow
from ddsgen.sensor.pattern import PatternField, fit_pattern, load_pattern
from ddsgen.sensor.registration import (
    band_hole_fill_index, dense_splat_index, forward_registration_index, gather_flat, register, register_images,
)
from ddsgen.sensor.reference_speckle import reference_speckle_factor
from ddsgen.sensor.row_smoothing import smooth_along_rows
from ddsgen.sensor.speckle import scene_speckle

# Fraction of disparity range added to the reference padding, so that fitting the
# baseline or focal length a little up does not run out of reference pattern.
_PAD_MARGIN = 1.15
# Width of the soft validity step around the confidence threshold (confidence units).
_SOFT_VALIDITY_WIDTH = 0.02


@dataclass
class SensorOutput:
    """One simulated frame. All (H, W).

    depth: m, 0 where invalid (differentiable where valid); valid: bool;
    valid_soft: keep-probability in [0, 1] (differentiable, for validity losses);
    ir: IR image (counts); disparity: px (0 where invalid); confidence: [0, 1];
    raw_depth: depth before the validity mask (m, 0 where the disparity is not positive).
    """

    depth: torch.Tensor
    valid: torch.Tensor
    valid_soft: torch.Tensor
    ir: torch.Tensor
    disparity: torch.Tensor
    confidence: torch.Tensor
    raw_depth: torch.Tensor


@dataclass
class FrontEnd:
    """The sensor's state before its validity stage (:meth:`DepthSensor.front_end`). All (H, W).

    ir: IR image (counts, after ir effects); disparity: px (after disparity effects); raw_depth: m (after depth
    effects, 0 where the disparity is not positive); confidence: matcher's [0, 1]; matched: matcher's bool
    validity; keep: keep-probability from the confidence and the lit mask; ctx: per-frame values effects read.
    """

    ir: torch.Tensor
    disparity: torch.Tensor
    raw_depth: torch.Tensor
    confidence: torch.Tensor
    matched: torch.Tensor
    keep: torch.Tensor
    ctx: dict


@functools.lru_cache(maxsize=8)
def _pattern_field(pattern_path: str, psf_px: float, width: int, height: int, pad: int, margin: int,
                   dot_jitter_px: float = 0.0, unit: int = 0) -> PatternField:
    """The pattern field for one sensor geometry (and unit), built once per process."""
    pattern = load_pattern(pattern_path)
    geometry = fit_pattern(pattern.shape, width, height, pad_left=pad, margin=margin)
    return PatternField(pattern, geometry, psf_px=psf_px, dot_jitter_px=dot_jitter_px, unit=unit)


@functools.lru_cache(maxsize=8)
def _reference_phases(pattern_path: str, psf_px: float, width: int, height: int, pad: int, margin: int,
                      dot_jitter_px: float, unit: int, n_sub: int, ir_width: int, speckle_contrast: float):
    """Reference images for an IR image ``ir_width`` columns wide (>= ``width`` with an IR margin), with the
    stored reference's own speckle of ``speckle_contrast`` (:mod:`ddsgen.sensor.reference_speckle`)."""
    field = _pattern_field(pattern_path, psf_px, width, height, pad, margin, dot_jitter_px, unit)
    phases = field.reference_phases(ir_width, height, pad, n_sub)
    if speckle_contrast > 0:
        phases = phases * reference_speckle_factor(*phases.shape, speckle_contrast, unit).to(phases.device)
    return phases


def _log_param(value: float) -> nn.Parameter:
    return nn.Parameter(torch.tensor(math.log(value), dtype=torch.float32))


class DepthSensor(nn.Module):
    """A structured-light depth sensor with differentiable parameters.

    Args:
        preset: the sensor preset (physics constants, matcher settings, effects).
        intrinsics: override the preset's intrinsics (e.g. a real scan's); same image size
            as the geometry passed to :meth:`forward`.
        device: torch device for the computation.

    Trainable parameters (all ``nn.Parameter``; callers choose which require grad):
    ``log_emitted_intensity``, ``log_speckle_scale``, ``log_read_noise_std``,
    ``read_noise_mean``, ``log_ambient``, ``log_beta``, ``log_baseline``,
    ``log_focal_scale`` (f / f_preset, scales fx and fy together), and the effects'.

    ``unit`` (int, 0 by default) says which unit of the device model this is. Every unit has the same
    parameters; each has its own scene-fixed random patterns: the laser speckle a static scene shows and the
    dots' sub-pixel positions. A real scan was taken by a unit whose patterns the model cannot know, so the
    noise floor of a comparison is measured against another unit (:func:`ddsgen.realscan.simulate.simulate_twin`).
    Renders use unit 0.

    ``matcher`` is the block matcher, :func:`ddsgen.sensor.matcher.match` or a callable with its signature.
    ``stage_cache`` (None by default: every stage is computed) is an object sensors may share to have stage results
    served while their inputs do not change (:class:`ddsgen.diagnose.stage_cache.StageCache`): the sensor asks its
    ``noise(sensor, seed, geometry, draw)``, ``front_end(sensor, geometry, noise, quantise, compute)`` and
    ``match(matcher, *args, **kwargs)`` for those values, passing the function that computes each, and calls its
    ``count(stage)`` for each "front_end" and "validity_stage" it computes.
    """

    def __init__(self, preset: SensorPreset, intrinsics: Intrinsics | None = None, device="cpu", stage_cache=None):
        super().__init__()
        self.preset = preset
        self.intr = intrinsics or preset.intrinsics
        self.device_ = torch.device(device)
        self.unit = 0
        self.matcher = match
        self.stage_cache = stage_cache
        self.log_emitted_intensity = _log_param(preset.emitted_intensity)
        self.log_speckle_scale = _log_param(preset.speckle_scale)
        self.log_read_noise_std = _log_param(max(preset.read_noise_std_counts, 1e-6))
        self.read_noise_mean = nn.Parameter(torch.tensor(float(preset.read_noise_mean_counts)))
        self.log_ambient = _log_param(max(preset.ambient_counts, 1e-6))
        self.log_beta = _log_param(preset.softargmax_beta)
        self.log_baseline = _log_param(preset.baseline_m)
        self.log_focal_scale = nn.Parameter(torch.tensor(0.0))
        self.effects = nn.ModuleList(build_effects(preset.effects))
        # Optional post-processing CNN (ddsgen.sensor.postprocess): called as
        # (depth, valid, valid_soft, geometry) -> (depth, valid, valid_soft).
        self.postprocess: nn.Module | None = None
        if preset.postprocess:
            from ddsgen.sensor.postprocess import load_postprocess

            self.postprocess = load_postprocess(preset.resolve_path(preset.postprocess))
        # Reference padding: the largest disparity the matcher may search, plus the window.
        self.pad = int(math.ceil(preset.disparity_max_px * _PAD_MARGIN)) + preset.block_size_px
        # Columns the IR camera sees beyond the depth image's right edge (ddsgen.sensor.ir_margin).
        self.ir_margin_px = int(preset.ir_margin_right_px)
        # Columns of pattern beyond the image (and the reference padding) on every side; covers the IR margin.
        self.margin = preset.block_size_px + 2 + self.ir_margin_px
        self.to(self.device_)

    # ---- physical parameter values -------------------------------------------------
    @property
    def emitted_intensity(self) -> torch.Tensor:
        return self.log_emitted_intensity.exp()

    @property
    def speckle_scale(self) -> torch.Tensor:
        return self.log_speckle_scale.exp()

    @property
    def read_noise_std(self) -> torch.Tensor:
        return self.log_read_noise_std.exp()

    @property
    def ambient(self) -> torch.Tensor:
        return self.log_ambient.exp()

    @property
    def beta(self) -> torch.Tensor:
        return self.log_beta.exp()

    @property
    def baseline(self) -> torch.Tensor:
        return self.log_baseline.exp()

    @property
    def focal_scale(self) -> torch.Tensor:
        return self.log_focal_scale.exp()

    def physical_parameters(self) -> dict[str, float]:
        """Current values as preset keys (plain floats)."""
        with torch.no_grad():
            scale = float(self.focal_scale)
            ambient = float(self.ambient)
            return {
                "emitted_intensity": float(self.emitted_intensity),
                "speckle_scale": float(self.speckle_scale),
                "read_noise_std_counts": float(self.read_noise_std),
                "read_noise_mean_counts": float(self.read_noise_mean),
                "ambient_counts": ambient if ambient > 1e-5 else 0.0,
                "softargmax_beta": float(self.beta),
                "baseline_m": float(self.baseline),
                "focal_px": self.preset.focal_px * scale,
                "focal_y_px": self.preset.focal_y_px * scale,
            }

    def to_preset(self) -> SensorPreset:
        """The preset with the current (fitted) parameter and effect values."""
        return self.preset.replace(**self.physical_parameters(), effects=[e.to_entry() for e in self.effects])

    # ---- cached per-sensor data ---------------------------------------------------------
    def _pattern_key(self) -> tuple:
        p = self.preset
        return (str(p.resolve_path(p.pattern)), p.pattern_psf_px, self.intr.width, self.intr.height, self.pad, self.margin,
                p.pattern_dot_jitter_px, self.unit)  # fmt: skip

    def pattern_field(self) -> PatternField:
        return _pattern_field(*self._pattern_key()).to(self.device_)

    def reference_phases(self, ir_width: int | None = None) -> torch.Tensor:
        """(S, H, ir_width + pad) reference images at infinity (default ``ir_width``: the image width W),
        cached once per process and sensor."""
        width = self.intr.width if ir_width is None else int(ir_width)
        p = self.preset
        phases = _reference_phases(*self._pattern_key(), p.subpixel_level, width, 0.0)
        return phases.to(self.device_)

    def draw_noise(self, seed, geometry: SensorGeometry | None = None) -> IRNoise:
        """Unit noise draws for a frame; ``seed`` is an int, a sequence of ints or a numpy Generator.

        With ``speckle_fixed_to_scene`` and a ``geometry``, the speckle is seeded by the geometry
        and the sensor's ``unit`` (the same static scene gets the same speckle whatever the frame
        seed; another unit sees another speckle); the read noise always comes from ``seed``.
        """
        if self.stage_cache is not None:
            return self.stage_cache.noise(self, seed, geometry, self._draw_noise)
        return self._draw_noise(seed, geometry)

    def _draw_noise(self, seed, geometry: SensorGeometry | None) -> IRNoise:
        p = self.preset
        rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
        # Drawn for the whole IR image (the margin included); a geometry without a margin uses the first W columns.
        height, width = self.intr.height, self.intr.width + self.ir_margin_px
        speckle = None
        if p.speckle_fixed_to_scene and geometry is not None:
            unit_salt = [self.unit] if self.unit else []  # unit 0: the seed renders have always used
            speckle = scene_speckle(geometry, unit_salt, height, width, p.speckle_shape, p.speckle_grain_px)
        return IRNoise.draw(height, width, p.speckle_shape, rng, self.device_, p.speckle_grain_px, speckle)

    # ---- the pipeline ---------------------------------------------------------------------
    def forward(
        self, geometry: SensorGeometry, seed=0, noise: IRNoise | None = None, quantise: bool = True
    ) -> SensorOutput:
        """Simulate one frame.

        Args:
            geometry: ray-cast geometry of shape (H, W) = (intrinsics.height, intrinsics.width).
            seed: seed of the frame's IR noise (ignored when ``noise`` is given).
            noise: pre-drawn unit noise (to reuse the same draws across calls, e.g. in fitting).
            quantise: quantise IR counts and disparity like the device (straight-through
                gradients). False gives the smooth function, for finite-difference checks.
        """
        intr = self.intr
        if geometry.shape != (intr.height, intr.width):
            raise ValueError(f"geometry is {geometry.shape}, sensor expects {(intr.height, intr.width)}")
        if noise is None:
            noise = self.draw_noise(seed, geometry)
        return self.validity_stage(self.front_end(geometry, noise, quantise), geometry)

    def front_end(self, geometry: SensorGeometry, noise: IRNoise, quantise: bool = True) -> "FrontEnd":
        """Everything before the validity stage: IR image, ir effects, block matching, disparity and depth
        effects, and the matcher's keep-probability. Depends on the geometry, the noise and every parameter
        except those of validity-stage effects and the post-processing (see
        :func:`ddsgen.diagnose.stage_cache.front_end_state`)."""
        if self.stage_cache is not None:
            return self.stage_cache.front_end(self, geometry, noise, quantise, self._front_end)
        return self._front_end(geometry, noise, quantise)

    def _front_end(self, geometry: SensorGeometry, noise: IRNoise, quantise: bool) -> "FrontEnd":
        if self.stage_cache is not None:
            self.stage_cache.count("front_end")
        p, intr = self.preset, self.intr
        fx = intr.fx * self.focal_scale
        fy = intr.fy * self.focal_scale
        cx = intr.cx - geometry.registration_shift_px  # the IR camera's (registered: left of the output's)
        baseline = self.baseline
        # The IR image: the depth image's grid plus the margin strip the caller cast (same cx, more columns).
        seen = geometry.with_ir_margin()
        width, ir_width = geometry.shape[1], seen.shape[1]
        noise = noise.columns(ir_width)
        lit_seen = (seen.hit & ~seen.shadow).float()
        ir, signal = render_ir(
            seen.points, seen.normals, seen.albedo, lit_seen, self.pattern_field(),
            fx, fy, cx, intr.cy, baseline, self.emitted_intensity, self.ambient,
            self.speckle_scale, self.read_noise_mean, self.read_noise_std, noise, p.ir_bits, quantise,
            p.projector_falloff_exponent, p.vignetting_exponent, p.electrons_per_count, 0.0,
            2.0,
        )  # fmt: skip
        ctx = {
            "geometry": seen, "signal": signal, "fx": fx, "fy": fy, "cx": cx, "cy": intr.cy,
            "baseline": baseline, "ir_max": 2.0**p.ir_bits - 1.0, "noise": noise,
        }  # fmt: skip
        for effect in self.effects:
            if effect.stage == "ir":
                ir = effect(ir, ctx)
        lit = lit_seen[:, :width]

        # Disparity search range from the current geometry (plain floats: the range is discrete).
        fb = float((fx * baseline).detach())
        d_min = max(fb / p.z_max_m, 0.0)
        d_max = min(fb / p.z_min_m, float(self.pad - p.block_size_px))
        # A device that smooths along its rows averages the matcher's sub-pixel estimates and quantises once after:
        # smoothing values already on the 2^-n px quantum and rounding again moves a pixel only when w times its
        # neighbours' offset reaches half a step (a step function of w, with ties at w = 1/4).
        smooths = p.row_smoothing_weight > 0
        args = (ir, self.reference_phases(ir_width), self.pad, d_min, d_max, p.block_size_px, self.beta,
                p.subpixel_level, p.band_rows, p.min_confidence)  # fmt: skip
        settings = {"quantize": quantise and not smooths, "confirmed_match_zncc": p.confirmed_match_zncc}
        if self.stage_cache is not None:
            result = self.stage_cache.match(self.matcher, *args, **settings)
        else:
            result = self.matcher(*args, **settings)
        if ir_width != width:  # back to the depth image's grid
            result = result.columns(width)
            ir, signal = ir[:, :width], signal[:, :width]
            ctx.update(geometry=geometry, signal=signal, noise=noise.columns(width))
        quantum = p.subpixel_step_px if quantise else None
        disparity = smooth_along_rows(result.disparity, result.valid, p.row_smoothing_weight, quantum)
        for effect in self.effects:
            if effect.stage == "disparity":
                disparity = effect(disparity, ctx)

        positive = disparity > 1e-3
        safe = torch.where(positive, disparity, torch.ones_like(disparity))
        raw_depth = torch.where(positive, fx * baseline / safe, torch.zeros_like(disparity))
        ctx["raw_depth"] = raw_depth
        for effect in self.effects:
            if effect.stage == "depth":
                raw_depth = effect(raw_depth, ctx)

        keep = torch.sigmoid((result.confidence - p.min_confidence) / _SOFT_VALIDITY_WIDTH)
        if p.shadow_always_invalid:
            keep = keep * lit
        elif p.no_hit_always_invalid:
            keep = keep * geometry.hit.float()
        return FrontEnd(ir=ir, disparity=disparity, raw_depth=raw_depth, confidence=result.confidence,
                        matched=result.valid, keep=keep, ctx=ctx)  # fmt: skip

    def validity_stage(self, front: "FrontEnd", geometry: SensorGeometry) -> SensorOutput:
        """Validity effects, range, the device's clean-up, output window and post-processing -> SensorOutput."""
        if self.stage_cache is not None:
            self.stage_cache.count("validity_stage")
        p, intr = self.preset, self.intr
        ctx, raw_depth, disparity = front.ctx, front.raw_depth, front.disparity
        keep = front.keep
        for effect in self.effects:
            if effect.stage == "validity":
                keep = keep * effect(raw_depth, ctx)
        in_range = (raw_depth >= p.z_min_m) & (raw_depth <= p.z_max_m)
        valid = front.matched & in_range & (keep > 0.5)
        if p.no_hit_always_invalid or p.shadow_always_invalid:
            valid = valid & geometry.hit
        if p.shadow_always_invalid:
            valid = valid & ~geometry.shadow
        valid_soft = keep * in_range.float()
        if p.cleanup_speckle_px or p.cleanup_hole_px or p.cleanup_fill_width_px:
            # A selection: each pixel keeps its own value or copies its nearest valid neighbour's.
            cleaned, source = device_cleanup(disparity, valid, p.cleanup_speckle_px, p.cleanup_max_diff_px,
                                             p.cleanup_hole_px, p.cleanup_fill_width_px)  # fmt: skip
            raw_depth, disparity, valid_soft = (gather_flat(x, source) for x in (raw_depth, disparity, valid_soft))
            removed = valid & ~cleaned
            valid_soft = valid_soft * (~removed).float()
            valid = cleaned
        window = OutputWindow.of(p)
        if not window.is_full:
            # The device's output window in the full image; a crop of it (compare --crop) is offset
            # by the shift of its principal point.
            crop_x, crop_y = intr.width < p.width_px, intr.height < p.height_px
            x0 = int(round(p.cx_px - intr.cx)) if crop_x else 0
            y0 = int(round(p.cy_px - intr.cy)) if crop_y else 0
            full_h, full_w = (p.height_px if crop_y else intr.height), (p.width_px if crop_x else intr.width)
            inside = torch.from_numpy(window.inside(*valid.shape, full_h, full_w, x0, y0)).to(valid.device)
            valid = valid & inside
            valid_soft = valid_soft * inside.to(valid_soft.dtype)
        depth = torch.where(valid, raw_depth, torch.zeros_like(raw_depth))
        if self.postprocess is not None:
            depth, valid, valid_soft = self.postprocess(depth, valid, valid_soft, geometry)
        disparity = torch.where(valid, disparity, torch.zeros_like(disparity))
        confidence = front.confidence
        if geometry.registration is not None:  # the IR camera's depth, written in the RGB camera's image
            index = geometry.registration
            if p.registration_forward_gap_px:  # mapped forward by the measured depth, as the device does
                index = forward_registration_index(valid, depth, p.registration_shift_px,
                                                   intr.fx * p.registration_ir_offset_m, p.registration_forward_gap_px,
                                                   p.registration_forward_fill_rows, geometry.registration)  # fmt: skip
            if p.registration_dense:  # the device's 2x2 splat closes 1-px holes
                index = dense_splat_index(index, valid)
            if False and p.cleanup_hole_px:  # as the device's forward map would
                index = band_hole_fill_index(index, geometry.registration < 0, register(valid, index),
                                             register(disparity, index), p.cleanup_hole_px, p.cleanup_max_diff_px)
            depth, valid, valid_soft, disparity, confidence, raw_depth = register_images(
                (depth, valid, valid_soft, disparity, confidence, raw_depth), index)  # fmt: skip
        return SensorOutput(depth=depth, valid=valid, valid_soft=valid_soft, ir=front.ir, disparity=disparity,
                            confidence=confidence, raw_depth=raw_depth)  # fmt: skip
