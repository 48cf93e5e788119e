"""The Effect protocol: a small differentiable module with named physical parameters.

An effect acts on one signal of the sensor (its ``stage``); the sensor runs it in that signal's
:class:`~ddsgen.sensor.effect_stages.EffectStage`, with the frame's
:class:`~ddsgen.sensor.effects.context.EffectContext`:

* ``"ir"``        — (H, W) IR image in counts -> IR image (before matching)
* ``"disparity"`` — (H, W) disparity in px -> disparity (after matching)
* ``"depth"``     — (H, W) depth in m -> depth
* ``"validity"``  — returns an (H, W) keep-probability in [0, 1] that multiplies validity
* ``"image"``     — a tuple of (H, W) maps (depth, disparity, validity, ...) -> the same maps resampled on another
  pixel grid (after validity, before the device's clean-up)

Each parameter has a neutral value (the effect then leaves the sensor unchanged) and a
physical range; it is stored unconstrained and mapped into its range by a sigmoid (or
kept raw when unbounded), so gradient steps can never leave the physical range.

Two optional class tables serve effects with many parameters or a discrete setting:

* ``options`` -- named choices that are not fitted (e.g. ``axis: radius``); the first
  choice is the default;
* ``groups`` -- a preset may give a run of scalar parameters as one list
  (e.g. ``coefficients: [0.1, 0, 0.05]``), expanded by :func:`~ddsgen.effect_params.validate_effects`.

The parameters, options and groups of every library effect are declared in :data:`ddsgen.effect_params.EFFECTS`.
"""

from __future__ import annotations

import math
from typing import ClassVar

import torch
from torch import nn

from ddsgen.effect_params import EffectParam
from ddsgen.sensor.effects.context import EffectContext


class Effect(nn.Module):
    """Base class. Subclasses set the class attributes and implement :meth:`forward`."""

    name: ClassVar[str]
    stage: ClassVar[str]  # "ir" | "disparity" | "depth" | "validity" | "image"
    description: ClassVar[str]  # one sentence a sensor engineer understands
    signature: ClassVar[str]  # the residual pattern it produces
    axis: ClassVar[str]  # the residual axis where its signature shows (e.g. "depth", "radius")
    params: ClassVar[dict[str, EffectParam]]
    options: ClassVar[dict[str, tuple[str, ...]]] = {}  # name -> choices (first = default); not fitted
    groups: ClassVar[dict[str, tuple[str, ...]]] = {}  # list key of a preset entry -> the scalar parameters it fills
    generic: ClassVar[bool] = False  # a shape without a named physical cause (diagnose tries it after the library)
    # False for an effect whose output is a step function of its parameters (a nearest-pixel resampling): searched on
    # a grid by diagnose, never moved by a gradient step.
    differentiable: ClassVar[bool] = True

    def __init__(self, **values):
        super().__init__()
        unknown = set(values) - set(self.params) - set(self.options)
        if unknown:
            raise KeyError(f"unknown parameter(s) {sorted(unknown)} for effect {self.name!r}")
        self.choices: dict[str, str] = {}
        for key, allowed in self.options.items():
            choice = str(values.pop(key, allowed[0]))
            if choice not in allowed:
                raise KeyError(f"{key} {choice!r} of effect {self.name!r} is not one of {allowed}")
            self.choices[key] = choice
        self.raw = nn.ParameterDict()
        for key, spec in self.params.items():
            value = float(values.get(key, spec.neutral))
            self.raw[key] = nn.Parameter(torch.tensor(self._to_raw(spec, value), dtype=torch.float32))

    @staticmethod
    def _bounded(spec: EffectParam) -> bool:
        return math.isfinite(spec.low) and math.isfinite(spec.high)

    @classmethod
    def _to_raw(cls, spec: EffectParam, value: float) -> float:
        if not cls._bounded(spec):
            return value
        eps = 1e-6
        t = min(max((value - spec.low) / (spec.high - spec.low), eps), 1 - eps)
        return math.log(t / (1 - t))

    def value(self, key: str) -> torch.Tensor:
        """The physical value of parameter ``key`` (0-d tensor, differentiable)."""
        spec = self.params[key]
        raw = self.raw[key]
        if not self._bounded(spec):
            return raw
        return spec.low + (spec.high - spec.low) * torch.sigmoid(raw)

    def values(self) -> dict[str, float]:
        """Current physical parameter values (plain floats), e.g. for a written preset."""
        return {key: float(self.value(key).detach()) for key in self.params}

    def set_values(self, **values) -> None:
        """Set physical parameter values in place; an option may be passed only with its current choice."""
        with torch.no_grad():
            for key, value in values.items():
                if key in self.options:
                    if value != self.choices[key]:
                        raise ValueError(f"{key} of {self.name} is {self.choices[key]!r}; build a new effect to change it")
                    continue
                self.raw[key].copy_(torch.tensor(self._to_raw(self.params[key], float(value))))

    def to_entry(self) -> dict:
        """The preset ``effects:`` entry for this effect."""
        return {"name": self.name, **self.choices, **{k: round(v, 9) for k, v in self.values().items()}}

    def forward(self, x: torch.Tensor, ctx: EffectContext) -> torch.Tensor:  # pragma: no cover - abstract
        raise NotImplementedError
