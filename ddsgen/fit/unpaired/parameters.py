"""The sensor parameters an unpaired fit moves: one table entry each.

Each entry names a preset key, its search bounds and scale. The fit sets values through
``SensorPreset.replace`` and rebuilds the sensor, so any preset key works -- including keys
that only some presets have (an entry whose key the preset lacks is skipped). Adding a
parameter (e.g. a fall-off exponent of a device-faithful preset) is one line in
:data:`UNPAIRED_PARAMETERS`.

What depth alone constrains (see docs/unpaired_fit.md): the IR signal-to-noise ratio
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
        from ddsgen.fit.unpaired.features import WEIGHTS

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


#: Fitted by default, in search order (the lattice first: it shapes the noise histogram; the clean-up
#: before the fall-off: filled holes change the validity by radius).
UNPAIRED_PARAMETERS: dict[str, UnpairedParameter] = {
    "subpixel_level": UnpairedParameter("subpixel_level", 1, 4, log=False, integer=True),
    "emitted_intensity": UnpairedParameter("emitted_intensity", 2.0e5, 5.0e7, grid=8),
    "softargmax_beta": UnpairedParameter("softargmax_beta", 4.0, 60.0),
    # The device's smoothing along its rows: it raises the flat-surface noise's correlation with the next pixel in
    # the row (and lowers the column's a little), which beta and the SNR hardly move -> searched on the grain alone.
    # Up to 0.3: beyond ~0.3 the side taps outweigh the centre, and the correlation falls again (no longer a
    # one-valued function of w).
    "row_smoothing_weight": UnpairedParameter("row_smoothing_weight", 0.0, 0.3, log=False, grid=7,
                                              terms=("grain",)),
    "min_confidence": UnpairedParameter("min_confidence", 0.05, 0.35, log=False),
    # Device keys (kinect_v1): the beam's fall-off darkens the corners -> searched on validity by
    # radius alone (it also changes the hole rates, but those are scene-dominated: measured, they
    # swung by 0.6 between fall-off values 4 apart while the radius term pointed at the hidden
    # value); the clean-up removes holes below cleanup_hole_px and valid specks below
    # cleanup_speckle_px -> searched on the hole-size histogram. A preset without them has them at
    # 0 (off), so the fit can switch them on.
    "cleanup_hole_px": UnpairedParameter("cleanup_hole_px", 0, 32, log=False, integer=True,
                                         choices=(0, 2, 4, 8, 16, 32), terms=("holes",)),
    "cleanup_speckle_px": UnpairedParameter("cleanup_speckle_px", 0, 400, log=False, integer=True,
                                            choices=(0, 25, 50, 100, 200, 400), terms=("holes",)),
    "projector_falloff_exponent": UnpairedParameter("projector_falloff_exponent", 0.0, 16.0, log=False, grid=5,
                                                    terms=("radius",)),
}


def parameters_for(preset, keys=None) -> list[UnpairedParameter]:
    """The table entries whose key the preset has (only ``keys``, in table order, when given)."""
    if keys is not None:
        unknown = sorted(set(keys) - set(UNPAIRED_PARAMETERS))
        if unknown:
            raise ValueError(f"not in UNPAIRED_PARAMETERS: {unknown}")
    return [p for p in UNPAIRED_PARAMETERS.values() if hasattr(preset, p.key) and (keys is None or p.key in keys)]
