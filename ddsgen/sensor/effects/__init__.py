"""The effect library: physical effects a real structured-light sensor shows and the base model lacks.

Effects are enabled from a preset's ``effects:`` list, e.g.
``effects: [{name: disparity_offset, offset_px: 0.3}]``; see :mod:`.base` for the
protocol and :data:`REGISTRY` for the names.
"""

from __future__ import annotations

import math
import numbers

from ddsgen.errors import InputError, did_you_mean, where
from ddsgen.sensor.effects.base import Effect, EffectParam

REGISTRY: dict[str, type[Effect]] = {}


def register(cls: type[Effect]) -> type[Effect]:
    """Class decorator adding an effect to :data:`REGISTRY` under ``cls.name``."""
    REGISTRY[cls.name] = cls
    return cls


def _expand_groups(cls: type[Effect], entry: dict, source: str, key: str) -> dict:
    """``entry`` with each list-valued group (``cls.groups``) spread over its scalar parameters."""
    out = {}
    for param, value in entry.items():
        if param not in cls.groups:
            out[param] = value
            continue
        names = cls.groups[param]
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
        if name not in REGISTRY:
            hint = did_you_mean(name, REGISTRY, f"known: {', '.join(sorted(REGISTRY))}")
            raise InputError(f"{where(source, key)}unknown effect {name!r}{hint}")
        cls = REGISTRY[name]
        resolved = {"name": name}
        entry = _expand_groups(cls, entry, source, key)
        for option, allowed in cls.options.items():
            choice = entry.get(option, allowed[0])
            if choice not in allowed:
                raise InputError(f"{where(source, key + '.' + option)}unknown {option} {choice!r} of {name} "
                                 f"(choices: {', '.join(allowed)})")  # fmt: skip
            resolved[option] = choice
        for param, value in entry.items():
            if param == "name" or param in cls.options:
                continue
            if param not in cls.params:
                known = [*cls.options, *cls.groups, *cls.params]
                hint = did_you_mean(param, known, f"parameters: {', '.join(known)}")
                raise InputError(f"{where(source, key + '.' + param)}unknown parameter of {name}{hint}")
            spec = cls.params[param]
            if isinstance(value, bool) or not isinstance(value, numbers.Real) or not math.isfinite(value):
                raise InputError(f"{where(source, key + '.' + param)}expected a finite number ({spec.unit}), got {value!r}")
            if not spec.low <= float(value) <= spec.high:
                raise InputError(
                    f"{where(source, key + '.' + param)}must be in [{spec.low:g}, {spec.high:g}] {spec.unit}, got {value!r}"
                )
        for param, spec in cls.params.items():
            resolved[param] = float(entry.get(param, spec.neutral))
        if any(e["name"] == name for e in out):
            raise InputError(f"{where(source, key)}effect {name!r} is listed twice")
        out.append(resolved)
    return out


def build_effects(entries) -> list[Effect]:
    """Instantiate validated ``effects:`` entries (in pipeline order of their stages)."""
    return [REGISTRY[e["name"]](**{k: v for k, v in e.items() if k != "name"}) for e in entries]


def library_names() -> list[str]:
    """The named effects (sorted): every registered effect except the generic axis terms."""
    return sorted(name for name, cls in REGISTRY.items() if not cls.generic)


# Import the library modules so that they register themselves.
from ddsgen.sensor.effects import axis_terms, distortion, library  # noqa: E402,F401

__all__ = ["Effect", "EffectParam", "REGISTRY", "register", "validate_effects", "build_effects", "library_names"]
