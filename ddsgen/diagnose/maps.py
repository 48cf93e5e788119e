"""Residual maps: where in the image a sensor model and the real scan disagree, pixel by pixel, at full resolution.

The residual analysis (:mod:`ddsgen.diagnose.residuals`) bins the disagreement along physical
axes; these maps show it in place (an edge band, a radial bowl, a tilted plane), for the report.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import torch

from ddsgen.diagnose.plane import replaned
from ddsgen.fit.simulate import simulate

#: Held-out frames whose residual maps go into the report.
MAP_FRAMES = 3


@dataclasses.dataclass
class ResidualMap:
    """One frame's disagreement with one model, all (H, W) at the prepared frame's resolution.

    residual_mm: float32 simulated minus real depth (mm) where both are valid inside the
        compared region, NaN elsewhere;
    real_only: bool, the real scan has depth and the simulation none (inside the region);
    sim_only: bool, the simulation has depth and the real scan none (inside the region);
    region: bool, the pixels the comparison counts (modelled, visible, plausible).
    """

    name: str
    residual_mm: np.ndarray
    real_only: np.ndarray
    sim_only: np.ndarray
    region: np.ndarray


def residual_maps(sensor, frames, seed: int) -> list[ResidualMap]:
    """Residual maps of ``sensor`` on ``frames`` (support planes re-estimated under it first), noise draw ``seed``."""
    frames = replaned(sensor, frames, seed, 1)
    maps = []
    with torch.no_grad():
        for frame in frames:
            sim = simulate(sensor, frame, seed)
            region = frame.region.numpy().astype(bool)
            real_valid = frame.real_valid.numpy().astype(bool) & region
            sim_valid = sim.valid.numpy().astype(bool) & region
            both = real_valid & sim_valid
            diff = 1000.0 * (sim.depth.numpy().astype(np.float64) - frame.real_depth.numpy().astype(np.float64))
            residual = np.where(both, diff, np.nan).astype(np.float32)
            maps.append(ResidualMap(frame.name, residual, real_valid & ~sim_valid, sim_valid & ~real_valid, region))
    return maps
