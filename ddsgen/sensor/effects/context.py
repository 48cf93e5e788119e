"""What an effect reads of the frame it acts on, besides its input signal."""

from __future__ import annotations

import dataclasses
from typing import Callable

import torch


@dataclasses.dataclass
class EffectContext:
    """One frame's camera and scene as the effects see them (built by the sensor once per frame).

    fx, fy: focal lengths (px; 0-d tensors or floats, differentiable where the sensor fits them); cx, cy: the IR
    camera's principal point (px); baseline: m (0-d tensor or float); geometry: the frame's
    :class:`~ddsgen.sensor.geometry.SensorGeometry` (H, W) (None where an effect is applied to measured data, e.g.
    :func:`ddsgen.realscan.plane_depth.plane_depth_for`); signal: (H, W) projected pattern signal (counts);
    ir_max: the ADC's full scale (counts); noise: the frame's :class:`~ddsgen.sensor.ir.IRNoise`;
    raw_depth: (H, W) depth (m) before the depth effects, set once disparity is turned into depth.
    """

    fx: torch.Tensor | float
    fy: torch.Tensor | float
    cx: float
    cy: float
    baseline: torch.Tensor | float
    geometry: object = None
    signal: torch.Tensor | None = None
    ir_max: float | None = None
    noise: object = None
    raw_depth: torch.Tensor | None = None
    _features: dict = dataclasses.field(default_factory=dict, init=False, repr=False, compare=False)

    def feature(self, name: str, compute: Callable[[], torch.Tensor]) -> torch.Tensor:
        """A per-pixel feature several effects read (edge distance, incidence angle, local signal), computed once
        per frame."""
        if name not in self._features:
            self._features[name] = compute()
        return self._features[name]

    def on_grid(self, geometry, signal: torch.Tensor, noise) -> None:
        """The depth image's grid after matching (the IR margin's columns dropped): features computed on the
        wider IR image are dropped with it."""
        self.geometry, self.signal, self.noise = geometry, signal, noise
        self._features.clear()
