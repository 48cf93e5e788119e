"""Sensor presets: load, validate, resolve and save the YAML that describes a depth sensor.

A preset is flat YAML; every key carries its unit in its name or in :data:`FIELDS` (the parameter
registry, :mod:`ddsgen.parameters`).
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

from ddsgen.atomic import atomic_write_text
from ddsgen.effect_params import validate_effects
from ddsgen.errors import InputError, did_you_mean, where
from ddsgen.parameters import PARAMETERS, REQUIRED, Parameter
from ddsgen.yamlfile import read_yaml

# The shipped presets and dot patterns: package data (presets/ and pattern_assets/ of the
# repository, ddsgen/presets and ddsgen/pattern_assets in the wheel), found through the import
# system, so they are there in a checkout, an editable and a wheel install alike. pip unpacks
# wheels, so these are real folders (pathlib.Path).
PRESET_DIR = files("ddsgen.presets")
PATTERN_DIR = files("ddsgen.pattern_assets")


#: The schema: every preset key as declared in the parameter registry (:mod:`ddsgen.parameters`), in the order of
#: keys in a written preset. Each entry's ``kind``, ``doc``, ``low`` / ``high`` / ``low_open`` and ``default``
#: are what loading checks.
FIELDS: dict[str, Parameter] = PARAMETERS


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
    ir_bits: int
    min_confidence: float
    shadow_always_invalid: bool
    no_hit_always_invalid: bool
    row_smoothing_weight: float
    confirmed_match_zncc: float
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
    registration_forward_gap_px: int
    registration_forward_fill_rows: int
    output_top_border_px: int
    output_bottom_border_px: int
    band_rows: int
    pattern: str
    pattern_psf_px: float
    pattern_dot_jitter_px: float
    ir_lens_k1: float
    reference_distance_m: float
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


def _check_number(source, key: str, field: Parameter, value):
    if isinstance(value, str):
        # YAML 1.1 reads "1.5e6" (no dot in the mantissa sign rule) as a string; accept it.
        try:
            value = float(value.strip())
        except ValueError:
            pass
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise InputError(f"{where(source, key)}expected a number ({field.doc}), got {value!r}")
    if field.kind is int:
        if isinstance(value, float):
            if not value.is_integer():
                raise InputError(f"{where(source, key)}expected an integer ({field.doc}), got {value!r}")
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
                raise InputError(f"{where(source, key)}missing required key ({field.doc})")
            values[key] = field.default
            continue
        value = data[key]
        if field.kind in (int, float):
            values[key] = _check_number(source, key, field, value)
        elif field.kind is str:
            if not isinstance(value, str) or not value.strip():
                raise InputError(f"{where(source, key)}expected a non-empty string ({field.doc}), got {value!r}")
            values[key] = value
        elif field.kind is bool:
            if not isinstance(value, bool):
                raise InputError(f"{where(source, key)}expected true or false ({field.doc}), got {value!r}")
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

    A file of that name in the current folder wins over the shipped preset; a folder of that name does not (a render
    into ``kinect_v1/`` must not hide the shipped ``kinect_v1``).
    """
    path = Path(path)
    if path.is_dir() and shipped_preset(str(path)) is None:
        raise InputError(f"{path}: is a folder, not a preset file")
    if not path.is_file():
        shipped = shipped_preset(str(path))
        if shipped is None and len(path.parts) == 1:
            names = ", ".join(shipped_preset_names())
            raise InputError(f"{path}: preset file not found, and no shipped preset of that name ({names})")
        path = shipped or path
    data = read_yaml(path, "preset")
    return preset_from_dict(data, source=path)


def save_preset(preset: SensorPreset, path: str | Path, comment: str | None = None) -> None:
    """Write a resolved preset as YAML (loadable by :func:`load_preset`); atomic."""
    header = "".join(f"# {line}\n" for line in (comment or "").splitlines())
    body = yaml.safe_dump(preset.to_dict(), sort_keys=False, default_flow_style=None)
    atomic_write_text(path, header + body)
