"""Bounds and priors that keep fitted sensor parameters physical.

Every sensor parameter ``fit`` can move has a :class:`SensorParam` (the parameter registry's
:class:`~ddsgen.parameters.FitRule`: the ``fit`` record of its key in :data:`ddsgen.parameters.PARAMETERS`) in
:data:`ddsgen.fit.parameters.SENSOR_PARAMS`: the tensor that stores it, its bounds (``stored_bounds``), the width of
its prior, its group and its finite-difference step. :class:`Priors` enforces the bounds by projecting the stored
value back after every Adam step, and adds the regulariser ``prior_mm * sum ((stored - start) / width)^2`` (mm, like
the loss) that pulls a parameter the data constrain only weakly back to the input preset instead of letting one
view's noise drive it to a bound (one frame drove beta from 15 to 3).

Effect parameters are bounded by their own specs (a sigmoid of an unbounded raw value, see
:mod:`ddsgen.sensor.effects.base`), so they need no projection; the prior does not apply to them.
"""

from __future__ import annotations

import torch

from ddsgen.parameters import FitRule as SensorParam

#: Weight of the regulariser toward the input preset (mm of loss at one prior width).
DEFAULT_PRIOR_MM = 0.1


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
