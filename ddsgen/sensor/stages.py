"""The sensor's stages: small objects, each built from the preset keys of one stage of the parameter registry.

:class:`~ddsgen.sensor.depth_sensor.DepthSensor` composes them, in the order a frame passes them::

    Projector -> IRLens (ddsgen.sensor.ir_lens) -> IRImage -> BlockMatcher -> RowSmoothing -> Validity -> Cleanup
        -> OutputBorders -> Registration

Each stage class names its registry stage (``stage``, :data:`ddsgen.parameters.STAGES`) and the keys it owns
(``keys``: that stage's keys in :mod:`ddsgen.parameters`; ``tests/test_sensor_stages.py`` checks both and that a stage
reads no other key). A stage holds settings only: the values the sensor fits are ``nn.Parameter`` s of the sensor
(``tensor_keys``: the stage's keys it holds; the sensor passes them in), and what the camera decides (focal length,
baseline, the depth range, the image size) comes with each call. A stage is a frozen dataclass: :meth:`Stage.configured`
gives it another preset's settings and keeps everything else (a swapped matching function, say), so a stage handed to a
sensor survives a change of its preset.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Callable, ClassVar

import numpy as np
import torch

from ddsgen.sensor.cleanup import device_cleanup
from ddsgen.sensor.geometry import SensorGeometry
from ddsgen.sensor.ir import IRNoise, render_ir
from ddsgen.sensor.matcher import MatchResult, match
from ddsgen.sensor.output_window import OutputWindow
from ddsgen.sensor.pattern import PatternField, fit_pattern, load_pattern
from ddsgen.sensor.registration import dense_splat_index, forward_registration_index, gather_flat, register_images
from ddsgen.sensor.row_smoothing import smooth_along_rows
from ddsgen.sensor.speckle import scene_speckle

# Width of the soft validity step around the confidence threshold (confidence units).
SOFT_VALIDITY_WIDTH = 0.02


class Stage:
    """What every stage declares: its registry ``stage``, the ``keys`` it owns, the ``tensor_keys`` among them that
    the sensor holds as parameters, and :meth:`settings`, its field values read off a preset."""

    stage: ClassVar[str]
    keys: ClassVar[tuple[str, ...]]
    tensor_keys: ClassVar[tuple[str, ...]] = ()

    @classmethod
    def settings(cls, preset) -> dict:
        """{field: value} of the stage's settings in ``preset`` (it reads only :attr:`keys`)."""
        raise NotImplementedError

    @classmethod
    def from_preset(cls, preset):
        return cls(**cls.settings(preset))

    def configured(self, preset):
        """This stage with ``preset``'s settings (fields that are not settings stay)."""
        return dataclasses.replace(self, **self.settings(preset))


# ------------------------------------------------------------------------------------------ projector


@functools.lru_cache(maxsize=8)
def _pattern_field(pattern_path: str, psf_px: float, width: int, height: int, pad: int, margin: int,
                   dot_jitter_px: float = 0.0, unit: int = 0) -> PatternField:
    """The pattern field for one sensor geometry (and unit), built once per process."""
    pattern = load_pattern(pattern_path)
    geometry = fit_pattern(pattern.shape, width, height, pad_left=pad, margin=margin)
    return PatternField(pattern, geometry, psf_px=psf_px, dot_jitter_px=dot_jitter_px, unit=unit)


@functools.lru_cache(maxsize=8)
def _reference_phases(pattern_path: str, psf_px: float, width: int, height: int, pad: int, margin: int,
                      dot_jitter_px: float, unit: int, n_sub: int, ir_width: int):
    """Reference images for an IR image ``ir_width`` columns wide (>= ``width`` with an IR margin)."""
    field = _pattern_field(pattern_path, psf_px, width, height, pad, margin, dot_jitter_px, unit)
    return field.reference_phases(ir_width, height, pad, n_sub)


@dataclasses.dataclass(frozen=True)
class Projector(Stage):
    """The dot pattern and its blur: the projected field and the matcher's reference images at infinity, both
    built once per process and sensor geometry (image size, reference padding and margin in px, unit)."""

    stage: ClassVar[str] = "pattern"
    keys: ClassVar[tuple[str, ...]] = ("pattern", "pattern_psf_px", "pattern_dot_jitter_px")

    pattern_path: str
    psf_px: float
    dot_jitter_px: float

    @classmethod
    def settings(cls, preset) -> dict:
        return {"pattern_path": str(preset.resolve_path(preset.pattern)), "psf_px": preset.pattern_psf_px,
                "dot_jitter_px": preset.pattern_dot_jitter_px}  # fmt: skip

    def _key(self, width: int, height: int, pad: int, margin: int, unit: int) -> tuple:
        return (self.pattern_path, self.psf_px, width, height, pad, margin, self.dot_jitter_px, unit)

    def field(self, width: int, height: int, pad: int, margin: int, unit: int) -> PatternField:
        return _pattern_field(*self._key(width, height, pad, margin, unit))

    def reference_phases(self, width: int, height: int, pad: int, margin: int, unit: int, n_sub: int,
                         ir_width: int) -> torch.Tensor:  # fmt: skip
        """(2^n_sub, H, ir_width + pad) reference images at infinity."""
        return _reference_phases(*self._key(width, height, pad, margin, unit), n_sub, ir_width)


# ------------------------------------------------------------------------------------------ IR image


@dataclasses.dataclass(frozen=True)
class IRImage(Stage):
    """The IR camera's image of the projected pattern: light, speckle, read and shot noise, ADC (:func:`render_ir`).
    The intensity and noise levels are the sensor's parameters (``tensor_keys``)."""

    stage: ClassVar[str] = "ir"
    keys: ClassVar[tuple[str, ...]] = (
        "emitted_intensity", "speckle_shape", "speckle_scale", "speckle_grain_px", "speckle_fixed_to_scene",
        "read_noise_mean_counts", "read_noise_std_counts", "electrons_per_count", "ambient_counts",
        "projector_falloff_exponent", "vignetting_exponent", "ir_bits", "ir_margin_right_px",
    )  # fmt: skip
    tensor_keys: ClassVar[tuple[str, ...]] = (
        "emitted_intensity", "speckle_scale", "read_noise_mean_counts", "read_noise_std_counts", "ambient_counts")

    speckle_shape: float
    speckle_grain_px: float
    speckle_fixed_to_scene: bool
    electrons_per_count: float
    projector_falloff_exponent: float
    vignetting_exponent: float
    ir_bits: int
    margin_px: int  # columns the IR camera sees beyond the depth image's right edge (ddsgen.sensor.ir_margin)

    @classmethod
    def settings(cls, preset) -> dict:
        return {
            "speckle_shape": preset.speckle_shape, "speckle_grain_px": preset.speckle_grain_px,
            "speckle_fixed_to_scene": preset.speckle_fixed_to_scene, "electrons_per_count": preset.electrons_per_count,
            "projector_falloff_exponent": preset.projector_falloff_exponent,
            "vignetting_exponent": preset.vignetting_exponent, "ir_bits": preset.ir_bits,
            "margin_px": int(preset.ir_margin_right_px),
        }  # fmt: skip

    @property
    def ir_max(self) -> float:
        """The largest count the ADC writes."""
        return 2.0**self.ir_bits - 1.0

    def draw_noise(self, seed, geometry: SensorGeometry | None, height: int, width: int, unit: int,
                   device) -> IRNoise:  # fmt: skip
        """Unit noise draws for an (height, width) IR image (see :meth:`DepthSensor.draw_noise`)."""
        rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
        speckle = None
        if self.speckle_fixed_to_scene and geometry is not None:
            unit_salt = [unit] if unit else []  # unit 0: the seed renders have always used
            speckle = scene_speckle(geometry, unit_salt, height, width, self.speckle_shape, self.speckle_grain_px)
        return IRNoise.draw(height, width, self.speckle_shape, rng, device, self.speckle_grain_px, speckle)

    def __call__(self, seen: SensorGeometry, lit: torch.Tensor, field: PatternField, fx, fy, cx, cy, baseline,
                 emitted_intensity, ambient, speckle_scale, read_noise_mean, read_noise_std, noise: IRNoise,
                 quantise: bool) -> tuple[torch.Tensor, torch.Tensor]:  # fmt: skip
        """(IR image, signal), both (H, W) counts, of the geometry ``seen`` (lit: (H, W) float, 1 where the
        projector lights a hit)."""
        return render_ir(
            seen.points, seen.normals, seen.albedo, lit, field, fx, fy, cx, cy, baseline, emitted_intensity, ambient,
            speckle_scale, read_noise_mean, read_noise_std, noise, self.ir_bits, quantise,
            self.projector_falloff_exponent, self.vignetting_exponent, self.electrons_per_count,
        )  # fmt: skip


# ------------------------------------------------------------------------------------------ matching


@dataclasses.dataclass(frozen=True)
class BlockMatcher(Stage):
    """Block matching of the IR image against the reference (``function``: :func:`ddsgen.sensor.matcher.match` or
    a callable with its signature), and the keep-probability of its confidence. The soft-argmax temperature is the
    sensor's parameter (``log_beta``)."""

    stage: ClassVar[str] = "matcher"
    keys: ClassVar[tuple[str, ...]] = ("block_size_px", "softargmax_beta", "subpixel_level", "min_confidence",
                                       "confirmed_match_zncc", "band_rows")  # fmt: skip
    tensor_keys: ClassVar[tuple[str, ...]] = ("softargmax_beta",)

    block_size_px: int
    subpixel_level: int
    min_confidence: float
    confirmed_match_zncc: float
    band_rows: int
    function: Callable[..., MatchResult] = match

    @classmethod
    def settings(cls, preset) -> dict:
        return {"block_size_px": preset.block_size_px, "subpixel_level": preset.subpixel_level,
                "min_confidence": preset.min_confidence, "confirmed_match_zncc": preset.confirmed_match_zncc,
                "band_rows": preset.band_rows}  # fmt: skip

    @property
    def step_px(self) -> float:
        """The sub-pixel quantum 2^-n_sub (px)."""
        return 2.0**-self.subpixel_level

    def __call__(self, ir: torch.Tensor, reference_phases: torch.Tensor, pad: int, d_min: float, d_max: float, beta,
                 quantize: bool, cache=None) -> MatchResult:  # fmt: skip
        """Match ``ir`` (H, W) over disparities [d_min, d_max] px; ``cache``: the sensor's stage cache, asked for
        the result (``cache.match(function, ...)``) when given."""
        args = (ir, reference_phases, pad, d_min, d_max, self.block_size_px, beta, self.subpixel_level,
                self.band_rows, self.min_confidence)  # fmt: skip
        settings = {"quantize": quantize, "confirmed_match_zncc": self.confirmed_match_zncc}
        if cache is not None:
            return cache.match(self.function, *args, **settings)
        return self.function(*args, **settings)

    def keep_probability(self, confidence: torch.Tensor) -> torch.Tensor:
        """A soft step of the confidence at ``min_confidence`` (differentiable, for validity losses)."""
        return torch.sigmoid((confidence - self.min_confidence) / SOFT_VALIDITY_WIDTH)


@dataclasses.dataclass(frozen=True)
class RowSmoothing(Stage):
    """The device's smoothing of the disparity along its rows, then its sub-pixel quantum
    (:func:`ddsgen.sensor.row_smoothing.smooth_along_rows`)."""

    stage: ClassVar[str] = "row_smoothing"
    keys: ClassVar[tuple[str, ...]] = ("row_smoothing_weight",)

    weight: float

    @classmethod
    def settings(cls, preset) -> dict:
        return {"weight": preset.row_smoothing_weight}

    @property
    def active(self) -> bool:
        return self.weight > 0

    def __call__(self, disparity: torch.Tensor, valid: torch.Tensor, quantum_px: float | None) -> torch.Tensor:
        """(H, W) disparity (px) smoothed and put on the ``quantum_px`` lattice (None: not quantised)."""
        return smooth_along_rows(disparity, valid, self.weight, quantum_px)


# ------------------------------------------------------------------------------------------ validity


@dataclasses.dataclass(frozen=True)
class Validity(Stage):
    """Which matches the device keeps: the matcher's own, in the depth range, and (as the preset says) not in the
    projector's shadow nor where the ray meets nothing."""

    stage: ClassVar[str] = "validity"
    keys: ClassVar[tuple[str, ...]] = ("shadow_always_invalid", "no_hit_always_invalid")

    shadow_always_invalid: bool
    no_hit_always_invalid: bool

    @classmethod
    def settings(cls, preset) -> dict:
        return {"shadow_always_invalid": preset.shadow_always_invalid,
                "no_hit_always_invalid": preset.no_hit_always_invalid}  # fmt: skip

    def keep(self, keep: torch.Tensor, lit: torch.Tensor, geometry: SensorGeometry) -> torch.Tensor:
        """The matcher's keep-probability (H, W) times the lit mask or the hit mask."""
        if self.shadow_always_invalid:
            return keep * lit
        if self.no_hit_always_invalid:
            return keep * geometry.hit.float()
        return keep

    def __call__(self, matched: torch.Tensor, raw_depth: torch.Tensor, keep: torch.Tensor, z_min: float,
                 z_max: float, geometry: SensorGeometry) -> tuple[torch.Tensor, torch.Tensor]:  # fmt: skip
        """(valid (H, W) bool, valid_soft (H, W) keep-probability) of depth ``raw_depth`` (m)."""
        in_range = (raw_depth >= z_min) & (raw_depth <= z_max)
        valid = matched & in_range & (keep > 0.5)
        if self.no_hit_always_invalid or self.shadow_always_invalid:
            valid = valid & geometry.hit
        if self.shadow_always_invalid:
            valid = valid & ~geometry.shadow
        return valid, keep * in_range.float()


@dataclasses.dataclass(frozen=True)
class Cleanup(Stage):
    """The device's clean-up of its matches: specks removed, small holes and narrow gaps filled
    (:func:`ddsgen.sensor.cleanup.device_cleanup`)."""

    stage: ClassVar[str] = "cleanup"
    keys: ClassVar[tuple[str, ...]] = ("cleanup_speckle_px", "cleanup_max_diff_px", "cleanup_hole_px",
                                       "cleanup_fill_width_px")  # fmt: skip

    speckle_px: int
    max_diff_px: float
    hole_px: int
    fill_width_px: int

    @classmethod
    def settings(cls, preset) -> dict:
        return {"speckle_px": preset.cleanup_speckle_px, "max_diff_px": preset.cleanup_max_diff_px,
                "hole_px": preset.cleanup_hole_px, "fill_width_px": preset.cleanup_fill_width_px}  # fmt: skip

    def __call__(self, raw_depth: torch.Tensor, disparity: torch.Tensor, valid: torch.Tensor,
                 valid_soft: torch.Tensor) -> tuple[torch.Tensor, ...]:  # fmt: skip
        """(raw_depth, disparity, valid, valid_soft) after the clean-up, all (H, W)."""
        if not (self.speckle_px or self.hole_px or self.fill_width_px):
            return raw_depth, disparity, valid, valid_soft
        # A selection: each pixel keeps its own value or copies its nearest valid neighbour's.
        cleaned, source = device_cleanup(disparity, valid, self.speckle_px, self.max_diff_px, self.hole_px,
                                         self.fill_width_px)  # fmt: skip
        raw_depth, disparity, valid_soft = (gather_flat(x, source) for x in (raw_depth, disparity, valid_soft))
        removed = valid & ~cleaned
        return raw_depth, disparity, cleaned, valid_soft * (~removed).float()


@dataclasses.dataclass(frozen=True)
class OutputBorders(Stage):
    """The device's output window (:class:`~ddsgen.sensor.output_window.OutputWindow`): border bands without depth."""

    stage: ClassVar[str] = "output_window"
    keys: ClassVar[tuple[str, ...]] = ("output_left_border_px", "output_right_border_px", "output_top_border_px",
                                       "output_bottom_border_px")  # fmt: skip

    window: OutputWindow

    @classmethod
    def settings(cls, preset) -> dict:
        return {"window": OutputWindow.of(preset)}

    def __call__(self, valid: torch.Tensor, valid_soft: torch.Tensor, intr, full_width: int, full_height: int,
                 full_cx: float, full_cy: float) -> tuple[torch.Tensor, torch.Tensor]:  # fmt: skip
        """(valid, valid_soft) without the bands, for an image of camera ``intr`` that may be a crop of the
        device's full (full_width x full_height px) image with principal point (full_cx, full_cy)."""
        if self.window.is_full:
            return valid, valid_soft
        # The device's output window in the full image; a crop of it (compare --crop) is offset by the shift of
        # its principal point.
        crop_x, crop_y = intr.width < full_width, intr.height < full_height
        x0 = int(round(full_cx - intr.cx)) if crop_x else 0
        y0 = int(round(full_cy - intr.cy)) if crop_y else 0
        full_h, full_w = (full_height if crop_y else intr.height), (full_width if crop_x else intr.width)
        inside = torch.from_numpy(self.window.inside(*valid.shape, full_h, full_w, x0, y0)).to(valid.device)
        return valid & inside, valid_soft * inside.to(valid_soft.dtype)


@dataclasses.dataclass(frozen=True)
class Registration(Stage):
    """Depth registered to an RGB camera: the IR camera's images written in the output camera's image
    (:mod:`ddsgen.sensor.registration`), mapped back by the ray cast or forward by the measured depth."""

    stage: ClassVar[str] = "registration"
    keys: ClassVar[tuple[str, ...]] = ("registration_ir_offset_m", "registration_shift_px", "registration_dense",
                                       "registration_forward_gap_px", "registration_forward_fill_rows")  # fmt: skip

    ir_offset_m: float
    shift_px: float
    dense: bool
    forward_gap_px: int
    forward_fill_rows: int

    @classmethod
    def settings(cls, preset) -> dict:
        return {"ir_offset_m": preset.registration_ir_offset_m, "shift_px": preset.registration_shift_px,
                "dense": preset.registration_dense, "forward_gap_px": preset.registration_forward_gap_px,
                "forward_fill_rows": preset.registration_forward_fill_rows}  # fmt: skip

    def __call__(self, images: tuple, valid: torch.Tensor, depth: torch.Tensor, index: torch.Tensor,
                 fx: float) -> tuple[torch.Tensor, ...]:  # fmt: skip
        """``images`` (each (H, W), IR camera) written in the output camera's image; ``index``: the geometry's
        registration index (output pixel -> flat IR pixel, -1: unseen); valid, depth: the IR camera's; fx: the
        camera's focal length (px)."""
        ray_cast = index
        if self.forward_gap_px:  # mapped forward by the measured depth, as the device does
            index = forward_registration_index(valid, depth, self.shift_px, fx * self.ir_offset_m,
                                               self.forward_gap_px, self.forward_fill_rows, ray_cast)  # fmt: skip
        if self.dense:  # the device's 2x2 splat closes 1-px holes
            index = dense_splat_index(index, valid)
        return register_images(images, index)
