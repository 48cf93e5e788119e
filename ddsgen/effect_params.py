"""The effect library's declarations, and the check of a preset's ``effects:`` list against them.

Each effect is declared once here: its preset name, the sensor stage it acts at, its parameters (neutral value,
physical range, unit, meaning), its options (named choices that are not fitted, the first the default) and its
groups (a list key of a preset entry that fills a run of scalar parameters). Plain data, no torch: a preset is
checked when it is loaded (:mod:`ddsgen.preset`), below the sensor; the effect classes
(:mod:`ddsgen.sensor.effects`) take their parameters, options and groups from here, so a range is written once
(the preset keys' own ranges are in :mod:`ddsgen.parameters`).
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass, field

from ddsgen.errors import InputError, did_you_mean, where


@dataclass(frozen=True)
class EffectParam:
    """One physical parameter of an effect."""

    neutral: float  # value that makes the effect a no-op
    low: float  # physical range (inclusive)
    high: float
    unit: str
    help: str
    typical: float | None = None  # a realistic strength, used as a fitting start


@dataclass(frozen=True)
class EffectSpec:
    """One effect of the library: name, stage (``"ir"``, ``"disparity"``, ``"depth"``, ``"validity"`` or ``"image"``),
    parameters, options, groups; ``generic``: a smooth term along an axis rather than a named physical cause."""

    name: str
    stage: str
    params: dict[str, EffectParam]
    options: dict[str, tuple[str, ...]] = field(default_factory=dict)
    groups: dict[str, tuple[str, ...]] = field(default_factory=dict)
    generic: bool = False


#: The disparity distortion field's control grid (rows x columns) and its parameter names.
GRID_ROWS, GRID_COLS = 3, 5
GRID_KEYS = tuple(f"d_r{r}c{c}" for r in range(GRID_ROWS) for c in range(GRID_COLS))

#: Number of Legendre coefficients of a generic axis term (degrees 0 .. N_COEFFICIENTS - 1), and their names.
N_COEFFICIENTS = 5
COEFFICIENTS = tuple(f"c{k}" for k in range(N_COEFFICIENTS))
#: Axis -> (low, high) of the range an axis term's basis spans, in the axis' units (see
#: ``ddsgen.sensor.effects.features.PIXEL_AXES``); ``signal`` is spanned in log10(counts). Image coordinates cover a
#: Kinect-like field of view (57 x 43 deg: |x| <= 0.56, |y| <= 0.42, r <= 0.70); values beyond a range get the
#: term's value at its end.
AXIS_DOMAINS: dict[str, tuple[float, float]] = {
    "radius": (0.0, 0.75),
    "row": (-0.48, 0.48),
    "column": (-0.6, 0.6),
    "edge_distance": (0.0, 30.0),
    "incidence": (0.0, 90.0),
    "depth": (0.3, 5.0),
    "signal": (-1.0, 3.0),  # log10 of the local signal in counts: 0.1 .. 1000
}


def _axis_term(name: str, stage: str, low: float, high: float, unit: str, what: str, typical: float) -> EffectSpec:
    params = {k: EffectParam(0.0, low, high, unit, f"coefficient of the Legendre polynomial P{k[1:]} of {what}",
                             typical=typical) for k in COEFFICIENTS}  # fmt: skip
    return EffectSpec(name, stage, params, options={"axis": tuple(AXIS_DOMAINS)},
                      groups={"coefficients": COEFFICIENTS}, generic=True)  # fmt: skip


EFFECTS: dict[str, EffectSpec] = {spec.name: spec for spec in (
    EffectSpec("lens_distortion", "ir", {
        "k1": EffectParam(0.0, -0.1, 0.1, "1", "radial distortion coefficient of r^2", typical=-0.006),
        "k2": EffectParam(0.0, -0.1, 0.1, "1", "radial distortion coefficient of r^4", typical=0.0),
    }),
    EffectSpec("lens_warp", "image", {
        "k1": EffectParam(0.0, -0.3, 0.3, "1", "radial distortion coefficient of r^2 of the pixel grid", typical=0.05),
        "k2": EffectParam(0.0, -0.3, 0.3, "1", "radial distortion coefficient of r^4 of the pixel grid", typical=0.0),
    }),
    EffectSpec("disparity_offset", "disparity", {
        "offset_px": EffectParam(0.0, -3.0, 3.0, "px", "disparity added to every match", typical=0.3),
    }),
    EffectSpec("depth_scale", "depth", {
        "scale_error": EffectParam(0.0, -0.1, 0.1, "1", "relative depth error epsilon: z' = (1 + epsilon) z",
                                   typical=0.01),
    }),
    EffectSpec("grazing_dropout", "validity", {
        "angle_deg": EffectParam(90.0, 30.0, 95.0, "deg",
                                 "incidence angle (normal vs. viewing ray) where returns start to fail", typical=72.0),
    }),
    EffectSpec("edge_dropout", "validity", {
        "width_px": EffectParam(0.0, 0.0, 20.0, "px", "width of the failed band on each side of a depth edge",
                                typical=3.0),
    }),
    EffectSpec("low_signal_dropout", "validity", {
        "threshold_counts": EffectParam(0.0, 0.0, 20.0, "IR counts",
                                        "local mean dot signal (9x9 window) below which depth is dropped", typical=1.5),
    }),
    EffectSpec("disparity_distortion", "disparity", {
        **{k: EffectParam(0.0, -2.0, 2.0, "px", f"distortion at zero disparity, control point row {k[3]} column "
                          f"{k[5]} of the {GRID_ROWS}x{GRID_COLS} grid", typical=0.2) for k in GRID_KEYS},
        "alpha0": EffectParam(0.0, -3.0, 3.0, "1", "log gain of the pattern: d' = d + D exp(alpha0 - alpha1 d)",
                              typical=0.0),
        "alpha1": EffectParam(0.0, -0.1, 0.1, "1/px", "decay rate of the pattern with disparity (< 0: grows)",
                              typical=0.02),
    }, groups={"grid": GRID_KEYS}),
    _axis_term("axis_disparity_term", "disparity", -2.0, 2.0, "px", "the disparity bias", typical=0.1),
    _axis_term("axis_validity_term", "validity", -20.0, 20.0, "logit", "the keep logit", typical=2.0),
)}  # fmt: skip


def _expand_groups(spec: EffectSpec, entry: dict, source: str, key: str) -> dict:
    """``entry`` with each list-valued group (``spec.groups``) spread over its scalar parameters."""
    out = {}
    for param, value in entry.items():
        if param not in spec.groups:
            out[param] = value
            continue
        names = spec.groups[param]
        if not isinstance(value, (list, tuple)) or len(value) != len(names):
            got = f"{len(value)} values" if isinstance(value, (list, tuple)) else repr(value)
            raise InputError(f"{where(source, key + '.' + param)}{entry['name']} takes a list of {len(names)} values "
                             f"({', '.join(names)}), got {got}")  # fmt: skip
        for name, item in zip(names, value):
            if name in entry:
                raise InputError(f"{where(source, key + '.' + name)}given both alone and in {param!r}")
            out[name] = item
    return out


def validate_effects(entries: list[dict], source: str = "") -> list[dict]:
    """Check effect names, options, parameter names and ranges; fill in defaults and neutral values.

    Raises:
        InputError: one line naming the file, the entry and the problem.
    """
    out = []
    for index, entry in enumerate(entries):
        key = f"effects[{index}]"
        name = entry["name"]
        if name not in EFFECTS:
            hint = did_you_mean(name, EFFECTS, f"known: {', '.join(sorted(EFFECTS))}")
            raise InputError(f"{where(source, key)}unknown effect {name!r}{hint}")
        spec = EFFECTS[name]
        resolved = {"name": name}
        entry = _expand_groups(spec, entry, source, key)
        for option, allowed in spec.options.items():
            choice = entry.get(option, allowed[0])
            if choice not in allowed:
                raise InputError(f"{where(source, key + '.' + option)}unknown {option} {choice!r} of {name} "
                                 f"(choices: {', '.join(allowed)})")  # fmt: skip
            resolved[option] = choice
        for param, value in entry.items():
            if param == "name" or param in spec.options:
                continue
            if param not in spec.params:
                known = [*spec.options, *spec.groups, *spec.params]
                hint = did_you_mean(param, known, f"parameters: {', '.join(known)}")
                raise InputError(f"{where(source, key + '.' + param)}unknown parameter of {name}{hint}")
            param_spec = spec.params[param]
            if isinstance(value, bool) or not isinstance(value, numbers.Real) or not math.isfinite(value):
                raise InputError(f"{where(source, key + '.' + param)}expected a finite number ({param_spec.unit}), "
                                 f"got {value!r}")  # fmt: skip
            if not param_spec.low <= float(value) <= param_spec.high:
                raise InputError(f"{where(source, key + '.' + param)}must be in [{param_spec.low:g}, "
                                 f"{param_spec.high:g}] {param_spec.unit}, got {value!r}")  # fmt: skip
        for param, param_spec in spec.params.items():
            resolved[param] = float(entry.get(param, param_spec.neutral))
        if any(e["name"] == name for e in out):
            raise InputError(f"{where(source, key)}effect {name!r} is listed twice")
        out.append(resolved)
    return out
