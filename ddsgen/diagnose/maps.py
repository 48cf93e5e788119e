"""Residual maps: where in the image a sensor model and the real scan disagree, pixel by pixel, at full resolution.

The residual analysis (:mod:`ddsgen.diagnose.residuals`) bins the disagreement along physical
axes; these maps show it in place (an edge band, a radial bowl, a tilted plane), for the report.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import torch

from ddsgen.diagnose.plane import replaned
from ddsgen.realscan.local_patches import residual_mm
from ddsgen.realscan.simulate import simulate

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
    origin: tuple[int, int] = (0, 0)  # (column, row) of the map's first pixel in the frame (a crop's offset)

    def cropped(self, box: tuple[int, int, int, int]) -> ResidualMap:
        """The map inside ``box`` = (x0, y0, x1, y1), pixels of this map (x1, y1 exclusive)."""
        x0, y0, x1, y1 = box
        cut = (slice(y0, y1), slice(x0, x1))
        return ResidualMap(self.name, self.residual_mm[cut], self.real_only[cut], self.sim_only[cut],
                           self.region[cut], (self.origin[0] + x0, self.origin[1] + y0))  # fmt: skip


#: A map is cropped to its compared region (plus this margin, px) when the region's box is less than
#: CROP_BELOW of the frame: with ``--region objects`` one object is otherwise a small patch of a 640 x 480 map.
CROP_MARGIN_PX = 16
CROP_BELOW = 0.5
#: A crop is drawn enlarged by a whole factor (nearest neighbour) to at least this width, at most 4x.
MIN_PANEL_WIDTH_PX = 320


def crop_zoom(width: int) -> int:
    """Whole enlargement factor (1-4) that draws a crop ``width`` px wide at least MIN_PANEL_WIDTH_PX wide."""
    return int(min(4, max(1, -(-MIN_PANEL_WIDTH_PX // max(int(width), 1)))))


def region_box(maps: list[ResidualMap], margin: int = CROP_MARGIN_PX) -> tuple[int, int, int, int] | None:
    """The box (x0, y0, x1, y1) around the compared region of every map in ``maps`` (one frame under several
    models), widened by ``margin`` and clipped to the frame; None when the box covers CROP_BELOW of the frame
    or more (the whole map is shown) or the region is empty."""
    region = np.logical_or.reduce([m.region for m in maps])
    rows, cols = np.nonzero(region.any(1))[0], np.nonzero(region.any(0))[0]
    if rows.size == 0:
        return None
    height, width = region.shape
    x0, x1 = max(int(cols[0]) - margin, 0), min(int(cols[-1]) + 1 + margin, width)
    y0, y1 = max(int(rows[0]) - margin, 0), min(int(rows[-1]) + 1 + margin, height)
    return None if (x1 - x0) * (y1 - y0) >= CROP_BELOW * width * height else (x0, y0, x1, y1)


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
            residual = residual_mm(sim, frame.region, frame.real_depth, frame.real_valid).astype(np.float32)
            maps.append(ResidualMap(frame.name, residual, real_valid & ~sim_valid, sim_valid & ~real_valid, region))
    return maps
