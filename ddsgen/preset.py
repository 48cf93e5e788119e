"""Sensor presets: load, validate, resolve and save the YAML that describes a depth sensor.

A preset is flat YAML; every key carries its unit in its name or in :data:`FIELDS`.
Loading checks every field (unknown key with the nearest valid name, wrong type,
out-of-range value) and raises :class:`~ddsgen.errors.InputError` with one line
``FILE: KEY: problem``. The resolved preset (defaults filled in) is what
``render`` writes to ``sensor.yaml`` and what ``fit`` writes back.
"""

from __future__ import annotations

import dataclasses
import math
from importlib.resources import files
from pathlib import Path
from typing import Any

import yaml

from ddsgen.errors import InputError, did_you_mean, where
from ddsgen.yamlfile import read_yaml

# The shipped presets and dot patterns: package data (presets/ and pattern_assets/ of the
# repository, ddsgen/presets and ddsgen/pattern_assets in the wheel), found through the import
# system, so they are there in a checkout, an editable and a wheel install alike. pip unpacks
# wheels, so these are real folders (pathlib.Path).
PRESET_DIR = files("ddsgen.presets")
PATTERN_DIR = files("ddsgen.pattern_assets")


REQUIRED = object()  # marks a key with no default


@dataclasses.dataclass(frozen=True)
class Field:
    """One preset key: its type, allowed range and meaning (with unit)."""

    kind: type
    help: str
    low: float | None = None
    high: float | None = None
    low_open: bool = False  # True: value must be > low (not >=)
    default: Any = REQUIRED


# The schema. Order is the order of keys in a written preset.
FIELDS: dict[str, Field] = {
    "name": Field(str, "preset name"),
    "width_px": Field(int, "image width (px)", 8, 16384),
    "height_px": Field(int, "image height (px)", 8, 16384),
    "focal_px": Field(float, "camera intrinsics fx: horizontal focal length f of IR camera and projector (px);"
                      " disparity = f x baseline / depth", 0, 1e5, low_open=True),
    "focal_y_px": Field(float, "camera intrinsics fy: vertical focal length (px); default = focal_px", 0, 1e5,
                        low_open=True, default=None),
    "cx_px": Field(float, "camera intrinsics cx: principal point column (px, 0 = centre of the first pixel);"
                   " default = (width-1)/2", default=None),
    "cy_px": Field(float, "camera intrinsics cy: principal point row (px, 0 = centre of the first pixel);"
                   " default = (height-1)/2", default=None),
    "baseline_m": Field(float, "projector-camera baseline b along +x (m)", 0, 2.0, low_open=True),
    "z_min_m": Field(float, "nearest measurable depth (m)", 0, 1e3, low_open=True),
    "z_max_m": Field(float, "farthest measurable depth (m)", 0, 1e3, low_open=True),
    "block_size_px": Field(int, "block-matching window w (px, odd)", 3, 255),
    "emitted_intensity": Field(float, "emitted intensity eta_c (IR counts * mm^2 per unit dot intensity; a lit dot is 393 units, so 1.5e6 gives Landau et al.'s 5.9e8 counts*mm^2)", 0, 1e20, low_open=True),
    "shadow_bias_m": Field(float, "shadow-ray bias xi (m)", 0, 1.0),
    "softargmax_beta": Field(float, "soft-argmax temperature beta (1/ZNCC)", 0, 1e4, low_open=True),
    "subpixel_level": Field(int, "sub-pixel refinement level n_sub (steps of 2^-n_sub px)", 0, 6),
    "speckle_shape": Field(float, "multiplicative speckle ~ Gamma(shape, scale): shape", 0, 1e4, low_open=True, default=4.54),
    "speckle_scale": Field(float, "multiplicative speckle ~ Gamma(shape, scale): scale", 0, 1e3, low_open=True, default=0.196),
    "speckle_grain_px": Field(float, "speckle grain: correlation sigma of the speckle field (camera px); 0 = independent per pixel", 0, 50, default=0.0),
    "speckle_fixed_to_scene": Field(bool, "speckle seeded by the scene's geometry (the same static scene shows the same speckle) instead of per frame", default=False),
    "read_noise_mean_counts": Field(float, "additive detector noise mean (IR counts)", -1e4, 1e4, default=-0.126),
    "read_noise_std_counts": Field(float, "additive detector noise std (IR counts)", 0, 1e4, default=10.4),
    "electrons_per_count": Field(float, "IR camera gain (photo-electrons per count): > 0 adds photon shot noise, variance = light / gain (counts^2); 0 = read noise only", 0, 1e6, default=0.0),
    "ambient_counts": Field(float, "ambient IR level added everywhere (IR counts)", 0, 1e6, default=0.0),
    "projector_falloff_exponent": Field(float, "projector beam profile: signal x cos^m(angle off the projector's axis); 0 = flat", 0, 32, default=0.0),
    "vignetting_exponent": Field(float, "IR lens vignetting: signal x cos^n(angle off the camera's axis); 4 = the cos^4 law, 0 = none", 0, 32, default=0.0),
    "lens_aperture_m": Field(float, "IR lens aperture diameter (m): > 0 blurs the dots by the defocus at their depth; 0 = pinhole", 0, 0.1, default=0.0),
    "focus_distance_m": Field(float, "IR lens focus distance (m), where the dots are sharpest", 0, 1e3, low_open=True, default=2.0),
    "ir_bits": Field(int, "IR sensor bit depth (clip and quantise to 2^bits - 1)", 4, 16, default=10),
    "min_confidence": Field(float, "matcher confidence (best minus second-best ZNCC) below which depth is invalid", 0, 1, default=0.15),
    "shadow_always_invalid": Field(bool, "pixels the projector cannot light are invalid whatever the matcher finds (true: the paper's shadow map); false: only matching decides, so windows at a shadow's edges keep the surface they see", default=True),
    "no_hit_always_invalid": Field(bool, "pixels whose ray meets no surface are invalid whatever the matcher finds (true: the ray cast's mask); false: only matching decides, so a window at an object's edge over empty space keeps the object's depth", default=True),
    "row_smoothing_weight": Field(float, "the device averages each valid disparity with its left and right neighbours on the same surface (within 1 px), weights [w, 1 - 2w, w], before its 2^-n px quantum: real depth's noise is grained along the rows (ddsgen/sensor/row_smoothing.py); 0 = off", 0, 0.5, default=0.0),
    "confirmed_match_zncc": Field(float, "a match that fails min_confidence (a close second peak) is still valid when its best ZNCC exceeds this and a unique match within its window has its disparity (+-1 px): a window across a depth edge sees two surfaces; 1 = off (uniqueness only)", 0, 1, default=1.0),
    "cleanup_speckle_px": Field(int, "device clean-up: valid regions smaller than this are removed (px; 0 = off)", 0, 1_000_000, default=0),
    "cleanup_max_diff_px": Field(float, "device clean-up: neighbours differing by more disparity than this are separate regions (px)", 0, 1000, low_open=True, default=1.0),
    "cleanup_hole_px": Field(int, "device clean-up: invalid holes smaller than this take their nearest valid pixel's disparity (px; 0 = off)", 0, 1_000_000, default=0),
    "cleanup_fill_width_px": Field(int, "device clean-up: an invalid pixel whose (2w+1) x (2w+1) window sees a gap at most this wide (w) on average, to the nearest pixel, takes its nearest valid pixel's disparity along its row or column, at depth edges too (px; 0 = off): a matching window centred in so narrow a shadow or crack is mostly lit and matches", 0, 1000, default=0),
    "output_left_border_px": Field(int, "the device outputs no depth in this many leftmost columns (px; 0 = none)", 0, 16384, default=0),
    "output_right_border_px": Field(int, "the device outputs no depth in this many rightmost columns (px; 0 = none; depth registered to an RGB camera leaves such a band)", 0, 16384, default=0),
    "ir_margin_right_px": Field(int, "the IR camera sees this many columns beyond the depth image's right edge, so matching windows there are whole (px; 0 = the IR image is the depth image's grid). Takes effect where the caller ray-casts the margin (render, compare, fit, diagnose, study)", 0, 64, default=0),
    "registration_ir_offset_m": Field(float, "depth registered to an RGB camera: the IR camera sits this far left (-x) of the output (RGB) camera, so near points shift by f b / z px and RGB-view pixels the IR camera does not see get no depth (m; 0 = depth in the IR camera's own image). Takes effect where the caller casts the IR view (render, compare, fit, diagnose, study)", 0, 1, default=0.0),
    "registration_shift_px": Field(float, "depth registered to an RGB camera: the IR camera's principal point is this many px left of the output camera's (px; with the IR frame's blind left columns it sets the registered left band, output_left_border_px + this - f b / z)", -1000, 1000, default=0.0),
    "registration_dense": Field(bool, "depth registered to an RGB camera: the device writes each depth to a 2x2 block (OpenNI's dense registration), so pixels without depth of their own take a lower or right neighbour's: 1-px holes and cracks close", default=False),
    "registration_fill_band_holes": Field(bool, "depth registered to an RGB camera: a small hole (fewer than cleanup_hole_px pixels) inside one surface (rim within cleanup_max_diff_px), most of whose pixels the IR camera does not see, takes its nearest valid pixel's depth. The device maps its measured depth forward, so the matcher's near surface, carried past a depth edge, covers such a band; the simulation maps back by the ray-cast geometry and would leave it open", default=False),
    "registration_forward_gap_px": Field(int, "depth registered to an RGB camera: 0 = map each output pixel back to the IR pixel that sees its ray-cast surface point; N >= 1 = map each valid IR depth forward by its measured depth, as the device does (z-buffer: the nearest wins), and close a run of at most N empty pixels between two written pixels whose IR sources are neighbours (a rasteriser's gap fill): the band right of a near surface stays open when wider than N, and the near surface the matcher carried past its edge lands next to it", 0, 64, default=0),
    "registration_forward_fill_rows": Field(int, "with registration_forward_gap_px: close a run of at most N empty pixels in a column, between two written pixels, where the IR camera saw a valid surface (its depth was carried elsewhere) or saw nothing; the nearer source wins. A forward map by rows leaves a dashed line along a near-horizontal depth edge where consecutive rows' bands overlap; real frames show no such dashes (their isolated dropouts are as often horizontal as vertical)", 0, 16, default=0),
    "output_top_border_px": Field(int, "the device outputs no depth in this many top rows (px; 0 = none)", 0, 16384, default=0),
    "output_bottom_border_px": Field(int, "the device outputs no depth in this many bottom rows (px; 0 = none)", 0, 16384, default=0),
    "band_rows": Field(int, "rows per matching band (bounds matcher memory)", 1, 16384, default=64),
    "pattern": Field(str, "dot pattern: a file in pattern_assets/ or a path (relative to the preset)", default="kinect_like_640.png"),
    "pattern_psf_px": Field(float, "Gaussian point-spread sigma of a projected dot (px)", 0, 10, low_open=True, default=0.5),
    "pattern_dot_jitter_px": Field(float, "projected dots sit this far (uniform, +-half, projector px) off the pattern's pixel lattice; 0 = on the lattice", 0, 2, default=0.0),
    "reference_speckle_contrast": Field(float, "speckle of the device's stored reference image (captured at calibration): each reference pixel times 1 + c N(0, 1), fixed per unit; it grains the disparity noise down the columns as well as along the rows (ddsgen/sensor/reference_speckle.py); 0 = off", 0, 2, default=0.0),
    "effects": Field(list, "extra physical effects: list of {name: EFFECT, PARAM: value}", default=()),
    "postprocess": Field(str, "optional post-processing CNN weights file (relative to the preset)", default=None),
}


@dataclasses.dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics (px)."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float

    def as_dict(self) -> dict:
        return dataclasses.asdict(self)

    def matrix(self):
        import numpy as np

        return np.array([[self.fx, 0, self.cx], [0, self.fy, self.cy], [0, 0, 1]], dtype=np.float64)


@dataclasses.dataclass(frozen=True)
class SensorPreset:
    """A resolved, validated sensor preset. Build with :func:`load_preset` or :func:`preset_from_dict`."""

    name: str
    width_px: int
    height_px: int
    focal_px: float
    focal_y_px: float
    cx_px: float
    cy_px: float
    baseline_m: float
    z_min_m: float
    z_max_m: float
    block_size_px: int
    emitted_intensity: float
    shadow_bias_m: float
    softargmax_beta: float
    subpixel_level: int
    speckle_shape: float
    speckle_scale: float
    speckle_grain_px: float
    speckle_fixed_to_scene: bool
    read_noise_mean_counts: float
    read_noise_std_counts: float
    electrons_per_count: float
    ambient_counts: float
    projector_falloff_exponent: float
    vignetting_exponent: float
    lens_aperture_m: float
    focus_distance_m: float
    ir_bits: int
    min_confidence: float
    row_smoothing_weight: float
    confirmed_match_zncc: float
    shadow_always_invalid: bool
    no_hit_always_invalid: bool
    cleanup_speckle_px: int
    cleanup_max_diff_px: float
    cleanup_hole_px: int
    cleanup_fill_width_px: int
    output_left_border_px: int
    output_right_border_px: int
    ir_margin_right_px: int
    registration_ir_offset_m: float
    registration_shift_px: float
    registration_dense: bool
    registration_fill_band_holes: bool
    registration_forward_gap_px: int
    registration_forward_fill_rows: int
    output_top_border_px: int
    output_bottom_border_px: int
    band_rows: int
    pattern: str
    pattern_psf_px: float
    pattern_dot_jitter_px: float
    reference_speckle_contrast: float
    effects: tuple
    postprocess: str | None
    source: str = ""  # file the preset came from (for messages and relative paths)

    @property
    def intrinsics(self) -> Intrinsics:
        return Intrinsics(self.width_px, self.height_px, self.focal_px, self.focal_y_px, self.cx_px, self.cy_px)

    @property
    def disparity_min_px(self) -> float:
        """Smallest disparity f*b/z_max (px)."""
        return self.focal_px * self.baseline_m / self.z_max_m

    @property
    def disparity_max_px(self) -> float:
        """Largest disparity f*b/z_min (px)."""
        return self.focal_px * self.baseline_m / self.z_min_m

    @property
    def subpixel_step_px(self) -> float:
        return 2.0 ** -self.subpixel_level

    def replace(self, **changes) -> "SensorPreset":
        """A copy with some fields changed, validated again."""
        data = self.to_dict()
        data.update(changes)
        return preset_from_dict(data, source=self.source)

    def to_dict(self) -> dict:
        """Plain dict in schema order (what :func:`save_preset` writes)."""
        out = {}
        for key in FIELDS:
            value = getattr(self, key)
            out[key] = [dict(e) for e in value] if key == "effects" else value
        return out

    def resolve_path(self, relative: str) -> Path:
        """A path named in the preset: absolute, relative to the preset file's folder, else a
        shipped pattern asset (``pattern: kinect_like_640.png`` works from any folder). A path
        found nowhere is returned relative to the preset's folder (for the error message)."""
        path = Path(relative).expanduser()
        if path.is_absolute():
            return path
        if self.source:
            candidate = Path(self.source).parent / path
            if candidate.exists():
                return candidate
        asset = PATTERN_DIR / path
        if asset.exists():
            return asset
        return Path(self.source).parent / path if self.source else path


def _check_number(source, key: str, field: Field, value):
    if isinstance(value, str):
        # YAML 1.1 reads "1.5e6" (no dot in the mantissa sign rule) as a string; accept it.
        try:
            value = float(value.strip())
        except ValueError:
            pass
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise InputError(f"{where(source, key)}expected a number ({field.help}), got {value!r}")
    if field.kind is int:
        if isinstance(value, float):
            if not value.is_integer():
                raise InputError(f"{where(source, key)}expected an integer ({field.help}), got {value!r}")
            value = int(value)
    value = field.kind(value)
    if not math.isfinite(value):
        raise InputError(f"{where(source, key)}must be a finite number, got {value!r}")
    if field.low is not None:
        if field.low_open and not value > field.low:
            raise InputError(f"{where(source, key)}must be > {field.low:g}, got {value!r}")
        if not field.low_open and value < field.low:
            raise InputError(f"{where(source, key)}must be >= {field.low:g}, got {value!r}")
    if field.high is not None and value > field.high:
        raise InputError(f"{where(source, key)}must be <= {field.high:g}, got {value!r}")
    return value


def _finite_number(x) -> bool:
    return not isinstance(x, bool) and isinstance(x, (int, float)) and math.isfinite(x)


def _check_effects(source, value) -> tuple:
    if value is None:
        return ()
    if not isinstance(value, (list, tuple)):
        raise InputError(f"{where(source, 'effects')}expected a list of {{name: EFFECT, ...}}, got {value!r}")
    effects = []
    for index, entry in enumerate(value):
        key = f"effects[{index}]"
        if isinstance(entry, str):
            entry = {"name": entry}
        if not isinstance(entry, dict) or not isinstance(entry.get("name"), str):
            raise InputError(f"{where(source, key)}expected {{name: EFFECT, PARAM: value}}, got {entry!r}")
        for param, number in entry.items():
            if param == "name" or isinstance(number, str):  # a string is an effect's option (e.g. axis: radius)
                continue
            numbers = number if isinstance(number, (list, tuple)) else [number]  # a list fills a parameter group
            if not all(_finite_number(x) for x in numbers) or not numbers:
                raise InputError(f"{where(source, key + '.' + str(param))}expected a finite number, got {number!r}")
        effects.append(dict(entry))
    # The effect library validates names and parameters (imported lazily: it needs torch).
    try:
        from ddsgen.sensor.effects import validate_effects
    except ImportError:
        return tuple(effects)
    return tuple(validate_effects(effects, source))


def preset_from_dict(data: Any, source: str | Path = "") -> SensorPreset:
    """Validate a mapping of preset keys and fill in defaults.

    Raises:
        InputError: one line naming ``source``, the key and the problem.
    """
    source = str(source)
    if not isinstance(data, dict):
        raise InputError(f"{where(source)}a preset must be a YAML mapping of keys to values, got {type(data).__name__}")
    for key in data:
        if key not in FIELDS:
            hint = did_you_mean(key, FIELDS)
            raise InputError(f"{where(source, str(key))}unknown key{hint}")
    values: dict[str, Any] = {}
    for key, field in FIELDS.items():
        if key not in data or (data[key] is None and field.default is not REQUIRED):
            if field.default is REQUIRED:
                raise InputError(f"{where(source, key)}missing required key ({field.help})")
            values[key] = field.default
            continue
        value = data[key]
        if field.kind in (int, float):
            values[key] = _check_number(source, key, field, value)
        elif field.kind is str:
            if not isinstance(value, str) or not value.strip():
                raise InputError(f"{where(source, key)}expected a non-empty string ({field.help}), got {value!r}")
            values[key] = value
        elif field.kind is bool:
            if not isinstance(value, bool):
                raise InputError(f"{where(source, key)}expected true or false ({field.help}), got {value!r}")
            values[key] = value
        elif key == "effects":
            values[key] = _check_effects(source, value)
    width, height = values["width_px"], values["height_px"]
    if values["focal_y_px"] is None:
        values["focal_y_px"] = values["focal_px"]
    if values["cx_px"] is None:
        values["cx_px"] = (width - 1) / 2.0
    if values["cy_px"] is None:
        values["cy_px"] = (height - 1) / 2.0
    if values["z_min_m"] >= values["z_max_m"]:
        raise InputError(
            f"{where(source, 'z_min_m')}must be smaller than z_max_m ({values['z_min_m']} >= {values['z_max_m']})"
        )
    block = values["block_size_px"]
    if block % 2 == 0:
        raise InputError(f"{where(source, 'block_size_px')}must be odd, got {block}")
    if block > min(width, height):
        raise InputError(f"{where(source, 'block_size_px')}must not exceed the image ({block} > {min(width, height)} px)")
    d_max = values["focal_px"] * values["baseline_m"] / values["z_min_m"]
    if d_max >= width:
        raise InputError(
            f"{where(source, 'z_min_m')}largest disparity f*b/z_min = {d_max:.0f} px is not smaller than the image width {width}"
        )
    return SensorPreset(**values, source=source)


def shipped_preset(name: str) -> Path | None:
    """The shipped preset file called ``name`` (``kinect_v1`` or ``kinect_v1.yaml``), or None."""
    if not name or Path(name).name != name:
        return None
    candidate = PRESET_DIR / (name if name.endswith(".yaml") else f"{name}.yaml")
    return Path(candidate) if candidate.is_file() else None


def source_label(preset: SensorPreset) -> str:
    """Where a preset came from, the same on every install: "shipped preset NAME" or the user's file path."""
    source = Path(preset.source) if preset.source else None
    if source is not None and source.parent.resolve() == Path(str(PRESET_DIR)).resolve():
        return f"shipped preset {source.stem}"
    return str(source) if source is not None else "built in code"


def shipped_preset_names() -> list[str]:
    """Names of the shipped presets (``ddsgen render NAME``), sorted."""
    return sorted(entry.name[: -len(".yaml")] for entry in PRESET_DIR.iterdir() if entry.name.endswith(".yaml"))


def load_preset(path: str | Path) -> SensorPreset:
    """Read and validate a preset YAML file, or a shipped preset by name (``kinect_v1``).

    A file of that name in the current folder wins over the shipped preset.
    """
    path = Path(path)
    if not path.exists():
        shipped = shipped_preset(str(path))
        if shipped is None and len(path.parts) == 1:
            names = ", ".join(shipped_preset_names())
            raise InputError(f"{path}: preset file not found, and no shipped preset of that name ({names})")
        path = shipped or path
    data = read_yaml(path, "preset")
    return preset_from_dict(data, source=path)


def save_preset(preset: SensorPreset, path: str | Path, comment: str | None = None) -> None:
    """Write a resolved preset as YAML (loadable by :func:`load_preset`); atomic."""
    from ddsgen.io.atomic import atomic_write_text

    header = "".join(f"# {line}\n" for line in (comment or "").splitlines())
    body = yaml.safe_dump(preset.to_dict(), sort_keys=False, default_flow_style=None)
    atomic_write_text(path, header + body)
