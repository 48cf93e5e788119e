"""The sensor parameters an unpaired fit moves: one table entry each.

Each entry names a preset key, its search bounds and scale: the ``unpaired`` records of the parameter
registry (:mod:`ddsgen.parameters`). The fit sets values through ``SensorPreset.replace`` and rebuilds
the sensor, so any preset key works. Adding a parameter (e.g. a fall-off exponent of a device-faithful
preset) is an ``unpaired`` record on its key in :data:`ddsgen.parameters.PARAMETERS`.

What depth alone constrains (see docs/validation.md): the IR signal-to-noise ratio
(eta_c against the fixed read noise: only their ratio is identifiable from depth), the
soft-argmax temperature beta (noise texture), the device's smoothing along its rows (the noise's
correlation with the next pixel in the row), the confidence threshold (dropouts), the
sub-pixel level (the disparity lattice); the device keys: the projector's fall-off exponent
(validity by image radius), the clean-up's hole and speck sizes (hole-size histogram).
Baseline and focal length are left to the preset: without calibration, the preset's f b is
assumed, and the lattice is fitted as n_sub. The lens vignetting exponent is not fitted: it
multiplies the same signal by cos^n of nearly the same angle as the projector's cos^m, so
depth only sees m + n; the fit moves m with n held at the preset's value.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ddsgen.fit.unpaired.features import WEIGHTS
from ddsgen.parameters import unpaired_searches


@dataclass(frozen=True)
class UnpairedParameter:
    """One fitted preset key: search bounds [low, high], log or linear scale, integer or not,
    grid points of the first coarse search. ``choices``: an integer key searched over these
    values only (sizes in px spanning decades, where every integer would be a wasted render).
    ``terms``: the distance terms (:func:`.features.distance_terms`) whose weighted sum this
    key's search minimises -- the features that identify it; "total" = all of them."""

    key: str
    low: float
    high: float
    log: bool = True
    integer: bool = False
    grid: int = 7
    choices: tuple = ()
    terms: tuple = ("total",)

    def objective(self, terms: dict) -> float:
        """This key's search objective from a :func:`.features.distance_terms` dict."""
        return float(sum(terms[t] if t == "total" else WEIGHTS[t] * terms[t] for t in self.terms))

    def to_unit(self, value: float) -> float:
        """Value -> search coordinate (log or linear)."""
        return math.log(value) if self.log else float(value)

    def from_unit(self, x: float) -> float:
        value = math.exp(x) if self.log else float(x)
        value = min(max(value, self.low), self.high)
        return int(round(value)) if self.integer else value

    def coarse_grid(self) -> list[float]:
        if self.choices:
            return list(self.choices)
        if self.integer:
            return list(range(int(self.low), int(self.high) + 1))
        return [self.from_unit(x) for x in np.linspace(self.to_unit(self.low), self.to_unit(self.high), self.grid)]

    def neighbours(self, value) -> list:
        """The choices next to ``value`` and itself (``choices`` keys), sorted."""
        index = int(np.argmin([abs(c - value) for c in self.choices]))
        return list(self.choices[max(index - 1, 0):index + 2])

    def step(self) -> float:
        """Spacing of the coarse grid in search coordinates (1 for integers)."""
        if self.integer:
            return 1.0
        return (self.to_unit(self.high) - self.to_unit(self.low)) / (self.grid - 1)


#: Fitted by default, in search order (:class:`~ddsgen.parameters.UnpairedSearch`).
UNPAIRED_PARAMETERS: dict[str, UnpairedParameter] = {
    key.name: UnpairedParameter(key.name, search.low, search.high, search.log, key.kind is int, search.grid,
                                search.choices, search.terms)
    for key, search in unpaired_searches()
}


def parameters_for(preset, keys=None) -> list[UnpairedParameter]:
    """The table entries whose key the preset has (only ``keys``, in table order, when given)."""
    if keys is not None:
        unknown = sorted(set(keys) - set(UNPAIRED_PARAMETERS))
        if unknown:
            raise ValueError(f"not in UNPAIRED_PARAMETERS: {unknown}")
    return [p for p in UNPAIRED_PARAMETERS.values() if hasattr(preset, p.key) and (keys is None or p.key in keys)]
