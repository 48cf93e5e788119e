"""The settings of a diagnosis (:class:`DiagnoseConfig`), apart from the loop that reads them, so that the candidate
searches can take them without importing the loop."""

from __future__ import annotations

import dataclasses

from ddsgen.diagnose.acceptance import MIN_RELATIVE_GAIN
from ddsgen.fit import DEFAULT_TILE_PX
from ddsgen.fit.parameters import DEFAULT_PARAMS

#: Base parameters fitted first. Not the baseline: fit_sensor estimates it from the disparity quantisation
#: lattice of the real depth, which a depth scale error rescales just like a baseline error would, so a
#: fitted baseline would hide that effect (b itself cancels from z = f b / d).
BASE_PARAMS = tuple(p for p in DEFAULT_PARAMS if p != "baseline")


@dataclasses.dataclass
class DiagnoseConfig:
    """Settings of :func:`diagnose` (defaults sized for a dozen 640x480 frames on 2 cores)."""

    holdout: float = 1.0 / 3.0
    base_params: tuple = BASE_PARAMS
    base_steps: int = 15  # Adam steps of the base fit (after its 1-D searches)
    refit_steps: int = 10  # Adam steps of the refit after accepting an effect
    tile_px: int | None = DEFAULT_TILE_PX  # each Adam step on a random tile of each frame, as ddsgen fit (None: whole)
    refine_rounds: int = 2  # halving rounds of the local search around a candidate's best grid point
    lr: float = 1e-3
    batch_frames: int | None = 2
    candidates: tuple | None = None  # effect names; default: the whole library
    max_steps: int = 4
    seed: int = 0
    grid_frames: int = 4  # fit frames used by the candidates' searches
    min_relative_gain: float = MIN_RELATIVE_GAIN
    axis_terms: bool = True  # try generic axis terms when no named effect clears the rule
    screen_frames: int = 1  # each candidate is searched on this many fit frames first (0: no screening)
