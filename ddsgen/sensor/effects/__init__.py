"""The effect library: physical effects a real structured-light sensor shows and the base model lacks.

Effects are enabled from a preset's ``effects:`` list, e.g.
``effects: [{name: disparity_offset, offset_px: 0.3}]``; see :mod:`.base` for the
protocol and :data:`REGISTRY` for the names.
"""

from __future__ import annotations

from ddsgen.effect_params import EffectParam, validate_effects
from ddsgen.sensor.effects.base import Effect

REGISTRY: dict[str, type[Effect]] = {}


def register(cls: type[Effect]) -> type[Effect]:
    """Class decorator adding an effect to :data:`REGISTRY` under ``cls.name``."""
    REGISTRY[cls.name] = cls
    return cls


def build_effects(entries) -> list[Effect]:
    """Instantiate validated ``effects:`` entries (in pipeline order of their stages)."""
    return [REGISTRY[e["name"]](**{k: v for k, v in e.items() if k != "name"}) for e in entries]


def library_names() -> list[str]:
    """The named effects (sorted): every registered effect except the generic axis terms."""
    return sorted(name for name, cls in REGISTRY.items() if not cls.generic)


# Import the library modules so that they register themselves.
from ddsgen.sensor.effects import axis_terms, distortion, library  # noqa: E402,F401

__all__ = ["Effect", "EffectParam", "REGISTRY", "register", "validate_effects", "build_effects", "library_names"]
