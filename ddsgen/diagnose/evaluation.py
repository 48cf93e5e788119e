"""Gap and noise floor of one sensor model on prepared frames, measured exactly as ``compare`` does, and the
likelihood of the real valid/invalid map under the model.

The ``compare`` gap judges validity by a difference of local valid rates. A rate difference does not say
whether the model puts its holes *where* the real ones are; a likelihood does: every real pixel's
valid/invalid state is a Bernoulli draw with the simulation's local valid rate
(:func:`validity_log_likelihood`), and a model that predicts the real hole map better scores higher.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import torch

from ddsgen.diagnose.plane import replaned
from ddsgen.realscan.losses import frame_gap_mm
from ddsgen.realscan.losses import local_window, masked_local_mean
from ddsgen.realscan.simulate import simulate, simulate_twin


@dataclasses.dataclass
class Evaluation:
    """Gap and noise floor of one model on some frames (per frame and mean, mm).

    ``frame_floors`` is the floor against one other unit (unit 1, the same draw for every model).
    ``reported_floors``, when measured, is the floor averaged over several units per frame, as ``compare``
    reports it: one unit's floor on few frames scatters by tens of percent, so the gaps *beyond the floor* that a
    diagnosis reports and the acceptance rule's floors (:func:`~ddsgen.diagnose.acceptance.judged_floors`) use
    it."""

    frame_gaps: list[float]
    frame_floors: list[float]
    frame_validity_ll: list[float] = dataclasses.field(default_factory=list)  # nats per region pixel
    reported_floors: list[float] | None = None
    floor_draws: int = 1  # units per frame behind ``floor``

    @property
    def validity_ll(self) -> float:
        """Mean over frames of the real valid map's log-likelihood per pixel (nats; higher is better)."""
        return float(np.mean(self.frame_validity_ll)) if self.frame_validity_ll else float("nan")

    @property
    def frame_excess(self) -> np.ndarray:
        return np.asarray(self.frame_gaps) - np.asarray(self.frame_floors)

    @property
    def gap(self) -> float:
        return float(np.mean(self.frame_gaps)) if self.frame_gaps else float("nan")

    @property
    def floor(self) -> float:
        """Mean floor over frames: the several-unit floor where measured, else the one-unit floor."""
        floors = self.reported_floors if self.reported_floors is not None else self.frame_floors
        return float(np.mean(floors)) if floors else float("nan")

    @property
    def excess(self) -> float:
        return self.gap - self.floor


#: The simulation's local valid rate is clipped to [RATE_FLOOR, 1 - RATE_FLOOR]: one pixel against a certain
#: prediction costs at most -ln(RATE_FLOOR) ~ 4.6 nats instead of infinity.
RATE_FLOOR = 0.01


def validity_log_likelihood(sim, frame) -> float:
    """Mean Bernoulli log-likelihood (nats per region pixel) of the real valid map under the simulation.

    The probability that a pixel is valid is the simulation's local valid rate: the mean of its
    keep-probability ``valid_soft`` (H, W) over the comparison region in the ``compare`` window (15 px at
    the Kinect's focal length), clipped to [RATE_FLOOR, 1 - RATE_FLOOR]. Real valid pixels add ln p, real
    holes ln(1 - p). Noise-free models score 0; a model whose holes fall where the real ones are scores
    higher than one with the same hole rate elsewhere.
    """
    region = frame.region
    if not bool(region.any()):
        return 0.0
    rate, _ = masked_local_mean(sim.valid_soft.detach().double(), region, local_window(frame.intrinsics.fx))
    p = rate.clamp(RATE_FLOOR, 1.0 - RATE_FLOOR)
    real = frame.real_valid
    ll = torch.where(real, torch.log(p), torch.log1p(-p))
    return float(ll[region].mean())


def frame_evaluation(sensor, frame, seed: int, floor_draws: int = 1) -> tuple[float, list[float], float]:
    """(gap, noise floors, validity log-likelihood) of one frame: the gap between the simulation (noise draw
    ``seed``) and the real scan and between that simulation and ``floor_draws`` twins (other units of the
    same sensor: :func:`~ddsgen.realscan.simulate.simulate_twin`, draws 0, 1, ...), as ``compare`` measures
    them, and :func:`validity_log_likelihood` of the real scan. A diagnosis evaluates hundreds of models
    and judges them by the gap itself against one twin each; only the gaps it reports beyond the floor
    average several."""
    sim = simulate(sensor, frame, seed)
    floors = []
    for draw in range(max(1, int(floor_draws))):
        other = simulate_twin(sensor, frame, seed, draw)
        floors.append(frame_gap_mm(sim, dataclasses.replace(frame, real_depth=other.depth, real_valid=other.valid)))
    return frame_gap_mm(sim, frame), floors, validity_log_likelihood(sim, frame)


def evaluate(sensor, frames, seed: int, replane_steps: int = 0, floor_draws: int = 1) -> Evaluation:
    """Per-frame gap and noise floor (:func:`frame_evaluation`) of ``sensor``, planes re-estimated first if asked.

    ``floor_draws`` > 1 also measures ``reported_floors``: per frame the mean floor over that many units
    (the first of them is ``frame_floors``' unit)."""
    if replane_steps:
        frames = replaned(sensor, frames, seed, replane_steps)
    gaps, floors, lls, averaged = [], [], [], []
    with torch.no_grad():
        for f in frames:
            g, fl, ll = frame_evaluation(sensor, f, seed, floor_draws)
            gaps.append(g)
            floors.append(fl[0])
            averaged.append(float(np.mean(fl)))
            lls.append(ll)
    return Evaluation(gaps, floors, lls, averaged, floor_draws) if floor_draws > 1 else Evaluation(gaps, floors, lls)
