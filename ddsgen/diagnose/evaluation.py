"""Gap and noise floor of one sensor model on prepared frames, measured exactly as ``compare`` does."""

from __future__ import annotations

import dataclasses

import numpy as np
import torch

from ddsgen.diagnose.plane import replaned
from ddsgen.fit.compare import frame_gap
from ddsgen.fit.simulate import simulate


@dataclasses.dataclass
class Evaluation:
    """Gap and noise floor of one model on some frames (per frame and mean, mm)."""

    frame_gaps: list[float]
    frame_floors: list[float]

    @property
    def frame_excess(self) -> np.ndarray:
        return np.asarray(self.frame_gaps) - np.asarray(self.frame_floors)

    @property
    def gap(self) -> float:
        return float(np.mean(self.frame_gaps)) if self.frame_gaps else float("nan")

    @property
    def floor(self) -> float:
        return float(np.mean(self.frame_floors)) if self.frame_floors else float("nan")

    @property
    def excess(self) -> float:
        return self.gap - self.floor


def frame_evaluation(sensor, frame, seed: int) -> tuple[float, float]:
    """(gap, noise floor) of one frame, exactly as ``compare`` measures them: the gap between the
    simulation (noise draw ``seed``) and the real scan, and between that simulation and a second
    draw (``seed + 1000``) of the same sensor."""
    sim = simulate(sensor, frame, seed)
    other = simulate(sensor, frame, seed + 1000)
    g = frame_gap(sim, frame)
    twin = dataclasses.replace(frame, real_depth=other.depth, real_valid=other.valid)
    return float(g["gap"] or 0.0), float(frame_gap(sim, twin)["gap"] or 0.0)


def evaluate(sensor, frames, seed: int, replane_steps: int = 0) -> Evaluation:
    """Per-frame gap and noise floor (:func:`frame_evaluation`) of ``sensor``, planes re-estimated first if asked."""
    if replane_steps:
        frames = replaned(sensor, frames, seed, replane_steps)
    gaps, floors = [], []
    with torch.no_grad():
        for f in frames:
            g, fl = frame_evaluation(sensor, f, seed)
            gaps.append(g)
            floors.append(fl)
    return Evaluation(gaps, floors)
