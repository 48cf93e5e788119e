"""The effect library: physical effects a real structured-light sensor shows and the base model lacks.

Effects are enabled from a preset's ``effects:`` list, e.g.
``effects: [{name: disparity_offset, offset_px: 0.3}]``; see :mod:`.base` for the
protocol and :data:`REGISTRY` for the names.
"""

from __future__ import annotations

import difflib

from ddsgen.errors import InputError, where
from ddsgen.sensor.effects.base import Effect, EffectParam

REGISTRY: dict[str, type[Effect]] = {}


def register(cls: type[Effect]) -> type[Effect]:
    """Class decorator adding an effect to :data:`REGISTRY` under ``cls.name``."""
    REGISTRY[cls.name] = cls
    return cls


def validate_effects(entries: list[dict], source: str = "") -> list[dict]:
    """Check effect names, parameter names and ranges; fill in neutral defaults.

    Raises:
        InputError: one line naming the file, the entry and the problem.
    """
    out = []
    for index, entry in enumerate(entries):
        key = f"effects[{index}]"
        name = entry["name"]
        if name not in REGISTRY:
            near = difflib.get_close_matches(name, REGISTRY, n=1)
            hint = f" (did you mean {near[0]!r}?)" if near else f" (known: {', '.join(sorted(REGISTRY))})"
            raise InputError(f"{where(source, key)}unknown effect {name!r}{hint}")
        cls = REGISTRY[name]
        resolved = {"name": name}
        for param, value in entry.items():
            if param == "name":
                continue
            if param not in cls.params:
                near = difflib.get_close_matches(param, cls.params, n=1)
                hint = f" (did you mean {near[0]!r}?)" if near else f" (parameters: {', '.join(cls.params)})"
                raise InputError(f"{where(source, key + '.' + param)}unknown parameter of {name}{hint}")
            spec = cls.params[param]
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


# Import the library modules so that they register themselves.
from ddsgen.sensor.effects import library  # noqa: E402,F401

__all__ = ["Effect", "EffectParam", "REGISTRY", "register", "validate_effects", "build_effects"]
