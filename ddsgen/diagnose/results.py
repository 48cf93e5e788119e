"""What a diagnosis found: the accepted steps, the candidates of every round, ``diagnosis.json``'s document."""

from __future__ import annotations

import dataclasses
import math

from ddsgen.diagnose.evaluation import Evaluation


@dataclasses.dataclass
class Candidate:
    effect: str
    params: dict
    fit_score: float
    held: Evaluation
    gain: float = 0.0
    gain_low: float = 0.0
    validity_ll_gain: float = 0.0  # change of the held-out validity log-likelihood (nats per pixel)
    sensor: object = None
    screened: bool = False  # judged at the values of its one-frame screening search (loop.SCREEN_FRACTION)


@dataclasses.dataclass
class Step:
    """One accepted effect. ``gap_before``/``gap_after``: held-out gap beyond the noise floor (mm);
    ``before``/``after``: the evaluations (compare gap and floor per frame)."""

    effect: str
    params: dict
    before: Evaluation
    after: Evaluation
    axis: str
    sentence: str
    analysis_before: dict
    analysis_after: dict

    @property
    def gap_before(self) -> float:
        return self.before.excess

    @property
    def gap_after(self) -> float:
        return self.after.excess


@dataclasses.dataclass
class Diagnosis:
    """The outcome of :func:`ddsgen.diagnose.diagnose`. ``maps_baseline`` / ``maps_final``: residual maps
    (:class:`ddsgen.diagnose.maps.ResidualMap`) of the fitted base sensor and of the final model on the
    first held-out frames."""

    baseline: Evaluation
    steps: list[Step]
    final: Evaluation
    unexplained: list[dict]
    sensor: object
    fit_frames: list
    held_frames: list
    analysis_baseline: dict
    analysis_final: dict
    rounds: list[list[Candidate]]
    maps_baseline: list = dataclasses.field(default_factory=list)
    maps_final: list = dataclasses.field(default_factory=list)
    notes: list = dataclasses.field(default_factory=list)  # sentences for the report (e.g. a spatial split)
    output_window: object = None  # the OutputWindow measured on the real frames and used, when it differs from the preset's
    local: object = None  # LocalReading (local_patches.py) when a gap beyond the floor remains along no axis

    @property
    def baseline_gap(self) -> float:
        """Held-out gap of the fitted base sensor beyond the noise floor (mm)."""
        return self.baseline.excess

    @property
    def final_gap(self) -> float:
        """Held-out gap of the final model beyond the noise floor (mm)."""
        return self.final.excess

    def to_dict(self) -> dict:
        """The ``diagnosis.json`` document (exactly this shape; gaps beyond the noise floor, mm)."""
        return {
            "baseline_gap": _f(self.baseline_gap),
            "steps": [{"effect": s.effect, "params": {k: _f(v) for k, v in s.params.items()},
                       "gap_before": _f(s.gap_before), "gap_after": _f(s.gap_after)} for s in self.steps],  # fmt: skip
            "final_gap": _f(self.final_gap),
            "unexplained": [{"axis": u["axis"], "strength": _f(u["strength"])} for u in self.unexplained],
            "local_patches": self.local.to_dict() if self.local is not None else None,
        }


def _f(x) -> float:
    x = float(x)
    return round(x, 6) if math.isfinite(x) else 0.0
