"""The sensor parameters an unpaired fit moves: one table entry each.

Each entry names a preset key, its search bounds and scale. The fit sets values through
``SensorPreset.replace`` and rebuilds the sensor, so any preset key works -- including keys
that only some presets have (an entry whose key the preset lacks is skipped). Adding a
parameter (e.g. a fall-off exponent of a device-faithful preset) is one line in
:data:`UNPAIRED_PARAMETERS`.

What depth alone constrains (see docs/unpaired_fit.md): the IR signal-to-noise ratio
(eta_c against the fixed read noise: only their ratio is identifiable from depth), the
soft-argmax temperature beta (noise texture), the confidence threshold (dropouts), the
sub-pixel level (the disparity lattice). Baseline and focal length are left to the preset:
without calibration, the preset's f b is assumed, and the lattice is fitted as n_sub.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class UnpairedParameter:
    """One fitted preset key: search bounds [low, high], log or linear scale, integer or not,
    grid points of the first coarse search."""

    key: str
    low: float
    high: float
    log: bool = True
    integer: bool = False
    grid: int = 7

    def to_unit(self, value: float) -> float:
        """Value -> search coordinate (log or linear)."""
        return math.log(value) if self.log else float(value)

    def from_unit(self, x: float) -> float:
        value = math.exp(x) if self.log else float(x)
        value = min(max(value, self.low), self.high)
        return int(round(value)) if self.integer else value

    def coarse_grid(self) -> list[float]:
        if self.integer:
            return list(range(int(self.low), int(self.high) + 1))
        return [self.from_unit(x) for x in np.linspace(self.to_unit(self.low), self.to_unit(self.high), self.grid)]

    def step(self) -> float:
        """Spacing of the coarse grid in search coordinates (1 for integers)."""
        if self.integer:
            return 1.0
        return (self.to_unit(self.high) - self.to_unit(self.low)) / (self.grid - 1)


#: Fitted by default, in search order (the lattice first: it shapes the noise histogram).
UNPAIRED_PARAMETERS: dict[str, UnpairedParameter] = {
    "subpixel_level": UnpairedParameter("subpixel_level", 1, 4, log=False, integer=True),
    "emitted_intensity": UnpairedParameter("emitted_intensity", 2.0e5, 5.0e7, grid=8),
    "softargmax_beta": UnpairedParameter("softargmax_beta", 4.0, 60.0),
    "min_confidence": UnpairedParameter("min_confidence", 0.05, 0.35, log=False),
}


def parameters_for(preset) -> list[UnpairedParameter]:
    """The table entries whose key the preset has."""
    return [p for p in UNPAIRED_PARAMETERS.values() if hasattr(preset, p.key)]
