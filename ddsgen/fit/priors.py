"""Bounds and priors that keep fitted sensor parameters physical.

Every sensor parameter ``fit`` can move is one :class:`SensorParam` entry of
:data:`ddsgen.fit.parameters.SENSOR_PARAMS` (adding a parameter to the fit is adding one entry):

* ``attr`` -- the :class:`~ddsgen.sensor.depth_sensor.DepthSensor` tensor that stores it
  (``None``: a device key of the preset, fitted by a 1-D search, :mod:`ddsgen.fit.device_keys`),
  ``log`` -- whether that tensor is the logarithm of the physical value;
* ``bound`` -- where the fitted value must stay: ``("factor", lo, hi)`` = within [lo, hi] x the
  start (input preset's) value, ``("range", lo, hi)`` = within [lo, hi] in the preset key's units;
  enforced by projecting the stored value back after every Adam step (and bounding the 1-D searches);
* ``width`` -- the prior's standard deviation in stored units (log units for ``log``): the
  regulariser ``prior_mm * sum ((stored - start) / width)^2`` (mm, like the loss) pulls a
  parameter the data constrain only weakly back to the input preset instead of letting one
  view's noise drive it to a bound (issue 14: one frame drove beta from 15 to 3);
* ``group`` -- parameters that are kept or reverted together (eta_c and the read-noise std only
  act through their ratio, so they are one group);
* ``key`` -- the preset key reported (``physical_parameters``); ``step`` -- the finite-difference
  step (stored units) of the uncertainty estimate (:mod:`ddsgen.fit.uncertainty`).

Effect parameters are bounded by their own specs (a sigmoid of an unbounded raw value, see
:mod:`ddsgen.sensor.effects.base`), so they need no projection; the prior does not apply to them.
"""

from __future__ import annotations

import dataclasses
import math

import torch

#: Weight of the regulariser toward the input preset (mm of loss at one prior width).
DEFAULT_PRIOR_MM = 0.1


@dataclasses.dataclass(frozen=True)
class SensorParam:
    """One fittable sensor parameter (see the module docstring)."""

    attr: str | None
    key: str
    log: bool
    bound: tuple[str, float, float]
    width: float
    group: str
    step: float = 0.05

    def stored_bounds(self, start_stored: float) -> tuple[float, float]:
        """(low, high) of the stored value given the stored start value."""
        kind, lo, hi = self.bound
        if kind == "factor":
            if self.log:
                return start_stored + math.log(lo), start_stored + math.log(hi)
            a, b = start_stored * lo, start_stored * hi
            return min(a, b), max(a, b)
        if kind == "range":
            if self.log:
                return math.log(max(lo, 1e-9)), math.log(hi)
            return lo, hi
        raise ValueError(f"unknown bound kind {kind!r}")

    def describe(self) -> str:
        kind, lo, hi = self.bound
        where = f"x{lo:g}..x{hi:g} of the input" if kind == "factor" else f"{lo:g}..{hi:g}"
        prior = f"{self.width:g} in log" if self.log else f"{self.width:g}"
        return f"{self.key}: {where}; prior width {prior}; group {self.group}"


class Priors:
    """Bounds and the regulariser for the fitted entries of a sensor (start values captured at construction).

    Args:
        sensor: the DepthSensor being fitted (its current values are the start).
        table: name -> :class:`SensorParam` of the parameters being fitted (only these are bounded/regularised).
        prior_mm: regulariser weight (0: bounds only).
    """

    def __init__(self, sensor, table: dict[str, SensorParam], prior_mm: float = DEFAULT_PRIOR_MM):
        self.entries = []
        for name, spec in table.items():
            if spec.attr is None:  # device keys: bounded by their search grid (ddsgen.fit.device_keys)
                continue
            tensor = getattr(sensor, spec.attr)
            start = float(tensor.detach())
            self.entries.append((name, spec, tensor, start, spec.stored_bounds(start)))
        self.prior_mm = float(prior_mm)

    def penalty(self) -> torch.Tensor:
        """The regulariser (0-d tensor, mm), differentiable in the fitted tensors."""
        total = torch.zeros(())
        if self.prior_mm <= 0:
            return total
        for _, spec, tensor, start, _ in self.entries:
            if tensor.requires_grad:
                total = total + self.prior_mm * ((tensor - start) / spec.width) ** 2
        return total

    def curvature(self, name: str) -> float:
        """Second derivative of the regulariser in ``name``'s stored value (0 if not regularised)."""
        for n, spec, *_ in self.entries:
            if n == name:
                return 2.0 * self.prior_mm / spec.width**2
        return 0.0

    @torch.no_grad()
    def project(self) -> list[str]:
        """Clamp every fitted value into its bounds; returns the names that were at a bound."""
        hit = []
        for name, _, tensor, _, (low, high) in self.entries:
            value = float(tensor)
            if value < low or value > high:
                tensor.clamp_(low, high)
                hit.append(name)
        return hit

    def at_bound(self) -> list[str]:
        """Names whose value sits on a bound (within 1e-6 of the stored range)."""
        out = []
        for name, _, tensor, _, (low, high) in self.entries:
            value = float(tensor.detach())
            if value <= low + 1e-6 or value >= high - 1e-6:
                out.append(name)
        return out

    def bounds_of(self, name: str) -> tuple[float, float] | None:
        for n, _, _, _, bounds in self.entries:
            if n == name:
                return bounds
        return None

    def table(self) -> list[dict]:
        """Documented bounds of the fitted parameters, for reports."""
        return [{"param": name, "key": spec.key, "bound": list(spec.bound), "prior_width": spec.width,
                 "log": spec.log, "group": spec.group} for name, spec, *_ in self.entries]  # fmt: skip
