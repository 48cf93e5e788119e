"""DepthSensor: the differentiable structured-light sensor, from hit geometry to depth.

The sensor is a composition of stages (:mod:`ddsgen.sensor.stages`), each built from its keys of the preset, with
the preset's optional physics (effects) plugged in as stages of their own (:mod:`ddsgen.sensor.effect_stages`)::

    geometry (ray cast, constant) -> projector -> IR image -> ir effects -> block matcher
    -> row smoothing and quantum -> disparity effects -> depth z = f b / d -> depth effects
    -> validity effects -> validity -> image effects -> clean-up -> output borders (-> optional post-processing CNN)
    -> registration

Everything in :meth:`DepthSensor.forward` is a torch function of the sensor's
parameters. Positive parameters are stored as logarithms (baseline, focal length,
emitted intensity, noise scales, soft-argmax temperature), so a gradient step can
never make them negative.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import nn

from ddsgen.preset import Intrinsics, SensorPreset
from ddsgen.sensor.effect_stages import effect_stages
from ddsgen.sensor.effects import build_effects
from ddsgen.sensor.effects.context import EffectContext
from ddsgen.sensor.geometry import SensorGeometry
from ddsgen.sensor.ir import IRNoise
from ddsgen.sensor.ir_lens import IRLens, recorded_reference
from ddsgen.sensor.pattern import PatternField
from ddsgen.sensor.postprocess import load_postprocess
from ddsgen.sensor.stages import (
    BlockMatcher, Cleanup, IRImage, OutputBorders, Projector, Registration, RowSmoothing, Stage, Validity,
)  # fmt: skip

# Fraction of disparity range added to the reference padding, so that fitting the
# baseline or focal length a little up does not run out of reference pattern.
_PAD_MARGIN = 1.15

#: The sensor's stages: attribute name -> the class built from the preset when none is handed in, in the order a
#: frame passes them.
STAGES: dict[str, type[Stage]] = {
    "projector": Projector, "ir_lens": IRLens, "ir_image": IRImage, "matcher": BlockMatcher,
    "row_smoothing": RowSmoothing, "validity": Validity, "cleanup": Cleanup, "output_borders": OutputBorders,
    "registration": Registration,
}  # fmt: skip


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
    validity; keep: keep-probability from the confidence and the lit mask; ctx: what the effects read of the frame.
    """

    ir: torch.Tensor
    disparity: torch.Tensor
    raw_depth: torch.Tensor
    confidence: torch.Tensor
    matched: torch.Tensor
    keep: torch.Tensor
    ctx: EffectContext


def _log_param(value: float) -> nn.Parameter:
    return nn.Parameter(torch.tensor(math.log(value), dtype=torch.float32))


class DepthSensor(nn.Module):
    """A structured-light depth sensor with differentiable parameters.

    Args:
        preset: the sensor preset (physics constants, matcher settings, effects).
        intrinsics: override the preset's intrinsics (e.g. a real scan's); same image size
            as the geometry passed to :meth:`forward`.
        device: torch device for the computation.
        stage_cache: see below (None: every stage is computed).
        stages: {name: stage} of :data:`STAGES` to use instead of the preset's own (given the preset's settings;
            e.g. a :class:`~ddsgen.sensor.stages.BlockMatcher` with another matching function).

    Trainable parameters (all ``nn.Parameter``; callers choose which require grad):
    ``log_emitted_intensity``, ``log_speckle_scale``, ``log_read_noise_std``,
    ``read_noise_mean``, ``log_ambient``, ``log_beta``, ``log_baseline``,
    ``log_focal_scale`` (f / f_preset, scales fx and fy together), and the effects'.

    The stages (:data:`STAGES`: ``projector``, ``ir_lens``, ``ir_image``, ``matcher``, ``row_smoothing``,
    ``validity``, ``cleanup``, ``output_borders``, ``registration``) hold the preset's settings; setting
    :attr:`preset` gives each its new settings. The sensor itself owns the camera (intrinsics, baseline, depth
    range), the effects (``effects``: their parameters, in the preset's order) and the optional post-processing CNN
    (``postprocess``). The effects run as the stages ``ir_effects``, ``disparity_effects``, ``depth_effects``,
    ``validity_effects`` and ``image_effects`` (:func:`~ddsgen.sensor.effect_stages.effect_stages`), each holding
    the effects that act on its signal.

    ``unit`` (int, 0 by default) says which unit of the device model this is. Every unit has the same
    parameters; each has its own scene-fixed random patterns: the laser speckle a static scene shows and the
    dots' sub-pixel positions. A real scan was taken by a unit whose patterns the model cannot know, so the
    noise floor of a comparison is measured against another unit (:func:`ddsgen.realscan.simulate.simulate_twin`).
    Renders use unit 0.

    ``stage_cache`` is an object sensors may share to have stage results served while their inputs do not change
    (:class:`ddsgen.diagnose.stage_cache.StageCache`): the sensor asks its ``noise(sensor, seed, geometry, draw)``,
    ``front_end(sensor, geometry, noise, quantise, compute)`` and ``match(matching_function, *args, **kwargs)`` for
    those values, passing the function that computes each, and calls its ``count(stage)`` for each "front_end" and
    "validity_stage" it computes.
    """

    def __init__(self, preset: SensorPreset, intrinsics: Intrinsics | None = None, device="cpu", stage_cache=None,
                 stages: dict[str, Stage] | None = None):  # fmt: skip
        super().__init__()
        unknown = sorted(set(stages or {}) - set(STAGES))
        if unknown:
            raise ValueError(f"unknown sensor stage(s) {unknown} (known: {', '.join(STAGES)})")
        for name, default in STAGES.items():
            setattr(self, name, (stages or {}).get(name) or default.from_preset(preset))
        self.preset = preset  # gives every stage the preset's settings
        self.intr = intrinsics or preset.intrinsics
        self.device_ = torch.device(device)
        self.unit = 0
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
        stages_of_effects = effect_stages(self.effects)
        self.ir_effects = stages_of_effects["ir"]
        self.disparity_effects = stages_of_effects["disparity"]
        self.depth_effects = stages_of_effects["depth"]
        self.validity_effects = stages_of_effects["validity"]
        self.image_effects = stages_of_effects["image"]
        # Optional post-processing CNN (ddsgen.sensor.postprocess): called as
        # (depth, valid, valid_soft, geometry) -> (depth, valid, valid_soft).
        self.postprocess: nn.Module | None = None
        if preset.postprocess:
            self.postprocess = load_postprocess(preset.resolve_path(preset.postprocess))
        # Reference padding: the largest disparity the matcher may search, plus the window.
        self.pad = int(math.ceil(preset.disparity_max_px * _PAD_MARGIN)) + preset.block_size_px
        # Columns the IR camera sees beyond the depth image's right edge (ddsgen.sensor.ir_margin).
        self.ir_margin_px = self.ir_image.margin_px
        # Columns of pattern beyond the image (and the reference padding) on every side; covers the IR margin.
        self.margin = preset.block_size_px + 2 + self.ir_margin_px
        self.to(self.device_)

    @property
    def preset(self) -> SensorPreset:
        return self._preset

    @preset.setter
    def preset(self, preset: SensorPreset) -> None:
        self._preset = preset
        for name in STAGES:
            setattr(self, name, getattr(self, name).configured(preset))

    def stages(self) -> dict[str, Stage]:
        """{name: stage} of :data:`STAGES`, in the order a frame passes them."""
        return {name: getattr(self, name) for name in STAGES}

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
    def pattern_field(self) -> PatternField:
        intr = self.intr
        return self.projector.field(intr.width, intr.height, self.pad, self.margin, self.unit).to(self.device_)

    def reference_phases(self, ir_width: int | None = None, cx: float | None = None) -> torch.Tensor:
        """(S, H, ir_width + pad) reference images at infinity (default ``ir_width``: the image width W),
        cached once per process and sensor; with an IR lens (:mod:`ddsgen.sensor.ir_lens`) the reference the device
        recorded through it, for the IR camera's principal point ``cx`` (default: the intrinsics')."""
        intr = self.intr
        width = intr.width if ir_width is None else int(ir_width)
        if self.ir_lens.active:
            cx = intr.cx if cx is None else float(cx)
            phases = recorded_reference(self.ir_lens, self.pattern_field(), width, intr.height, self.pad,
                                       self.matcher.subpixel_level, float(intr.fx), float(intr.fy), cx,
                                       float(intr.cy), float(self.preset.baseline_m))  # fmt: skip
        else:
            phases = self.projector.reference_phases(intr.width, intr.height, self.pad, self.margin, self.unit,
                                                     self.matcher.subpixel_level, width)  # fmt: skip
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
        # Drawn for the whole IR image (the margin included); a geometry without a margin uses the first W columns.
        height, width = self.intr.height, self.intr.width + self.ir_margin_px
        return self.ir_image.draw_noise(seed, geometry, height, width, self.unit, self.device_)

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
        """Everything before the validity stage: IR image, ir effects, block matching, row smoothing, disparity and
        depth effects, and the matcher's keep-probability. Depends on the geometry, the noise and every parameter
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
        lit = (geometry.hit & ~geometry.shadow).float()
        # The IR camera's pixels look along its lens's bent rays (ddsgen.sensor.ir_lens; a pinhole lens: the cast).
        lens = self.ir_lens
        view = lens.distorted_view(seen, intr.fx, intr.fy, cx, intr.cy) if lens.active else seen
        ir, signal = self.ir_image(view, (view.hit & ~view.shadow).float(), self.pattern_field(), fx, fy, cx, intr.cy,
                                   baseline, self.emitted_intensity, self.ambient, self.speckle_scale,
                                   self.read_noise_mean, self.read_noise_std, noise, quantise)  # fmt: skip
        ctx = EffectContext(fx=fx, fy=fy, cx=cx, cy=intr.cy, baseline=baseline, geometry=view, signal=signal,
                            ir_max=self.ir_image.ir_max, noise=noise)  # fmt: skip
        ir = self.ir_effects(ir, ctx)

        # Disparity search range from the current geometry (plain floats: the range is discrete).
        fb = float((fx * baseline).detach())
        # With an IR lens the search reaches a pixel below the range's end: a surface beyond it then matches where it
        # is and the range check after the lens's calibration drops it, instead of matching at the search's edge.
        d_min = max(fb / p.z_max_m - (1.0 if lens.active else 0.0), 0.0)
        d_max = min(fb / p.z_min_m, float(self.pad - self.matcher.block_size_px))
        # A device that smooths along its rows averages the matcher's sub-pixel estimates and quantises once after:
        # smoothing values already on the 2^-n px quantum and rounding again moves a pixel only when w times its
        # neighbours' offset reaches half a step (a step function of w, with ties at w = 1/4).
        # The device's quantum comes last: after the row smoothing, and after its lens calibration.
        quantum = self.matcher.step_px if quantise and not self.row_smoothing.active else None
        result = self.matcher(ir, self.reference_phases(ir_width, cx), self.pad, d_min, d_max, self.beta,
                              quantize=quantum is not None and not lens.active, cache=self.stage_cache)
        if lens.active:  # the device's calibration: the undistorted rays' disparity, on the depth image's grid
            result, (ir, signal) = lens.to_undistorted(result, (ir, signal), width, intr.fx, intr.fy, cx, intr.cy,
                                                       p.baseline_m, quantum)  # fmt: skip
            ctx.on_grid(geometry, signal, noise.columns(width))
        elif ir_width != width:  # back to the depth image's grid
            result = result.columns(width)
            ir, signal = ir[:, :width], signal[:, :width]
            ctx.on_grid(geometry, signal, noise.columns(width))
        disparity = self.row_smoothing(result.disparity, result.valid, self.matcher.step_px if quantise else None)
        disparity = self.disparity_effects(disparity, ctx)

        positive = disparity > 1e-3
        safe = torch.where(positive, disparity, torch.ones_like(disparity))
        raw_depth = torch.where(positive, fx * baseline / safe, torch.zeros_like(disparity))
        ctx.raw_depth = raw_depth
        raw_depth = self.depth_effects(raw_depth, ctx)

        keep = self.validity.keep(self.matcher.keep_probability(result.confidence), lit, geometry)
        return FrontEnd(ir=ir, disparity=disparity, raw_depth=raw_depth, confidence=result.confidence,
                        matched=result.valid, keep=keep, ctx=ctx)  # fmt: skip

    def validity_stage(self, front: "FrontEnd", geometry: SensorGeometry) -> SensorOutput:
        """Validity effects, validity, the device's clean-up, output borders, post-processing and registration ->
        SensorOutput."""
        if self.stage_cache is not None:
            self.stage_cache.count("validity_stage")
        p, intr = self.preset, self.intr
        ctx, raw_depth, disparity = front.ctx, front.raw_depth, front.disparity
        keep = self.validity_effects(front.keep, raw_depth, ctx)
        valid, valid_soft = self.validity(front.matched, raw_depth, keep, p.z_min_m, p.z_max_m, geometry)
        confidence, ir = front.confidence, front.ir
        # The device's pixels may see another grid (a lens warp); its clean-up runs on that grid.
        raw_depth, disparity, valid, valid_soft, confidence, ir = self.image_effects(
            (raw_depth, disparity, valid, valid_soft, confidence, ir), ctx)
        raw_depth, disparity, valid, valid_soft = self.cleanup(raw_depth, disparity, valid, valid_soft)
        valid, valid_soft = self.output_borders(valid, valid_soft, intr, p.width_px, p.height_px, p.cx_px, p.cy_px)
        depth = torch.where(valid, raw_depth, torch.zeros_like(raw_depth))
        if self.postprocess is not None:
            depth, valid, valid_soft = self.postprocess(depth, valid, valid_soft, geometry)
        disparity = torch.where(valid, disparity, torch.zeros_like(disparity))
        if geometry.registration is not None:  # the IR camera's depth, written in the RGB camera's image
            depth, valid, valid_soft, disparity, confidence, raw_depth = self.registration(
                (depth, valid, valid_soft, disparity, confidence, raw_depth), valid, depth, geometry.registration,
                intr.fx)  # fmt: skip
        return SensorOutput(depth=depth, valid=valid, valid_soft=valid_soft, ir=ir, disparity=disparity,
                            confidence=confidence, raw_depth=raw_depth)  # fmt: skip
