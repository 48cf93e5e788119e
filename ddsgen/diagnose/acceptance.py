"""The acceptance rule of diagnosis: how much of the held-out gap a candidate effect must remove, credited fairly.

A candidate is credited, per frame and with the same noise draws for every model, with the fall
of its gap minus any fall of its own noise floor (:func:`frame_falls`): a model can lower the
``compare`` gap by *hiding* noise (a dropout that removes the noisiest pixels lowers gap and floor
alike), while a genuinely missing effect lowers the gap and leaves the floor. It is accepted when
the credited fall clears :data:`MIN_RELATIVE_GAIN` and a bootstrap over the held-out frames
(:func:`bootstrap_fall`) confirms it is not carried by a few frames (:data:`RULE`).
"""

from __future__ import annotations

import numpy as np

from ddsgen.diagnose.evaluation import Evaluation

#: A candidate's credited fall (frame_falls) must be at least this fraction of the held-out gap ...
MIN_RELATIVE_GAIN = 0.05
#: ... and the BOOTSTRAP_QUANTILE-quantile of that gain over resamples of the held-out frames must stay above zero.
BOOTSTRAP_RESAMPLES = 2000
BOOTSTRAP_QUANTILE = 0.05
#: Residual structure below this (mm, beyond noise) is not reported as unexplained.
UNEXPLAINED_MIN_MM = 1.0

RULE = (
    f"Each round, the candidate with the largest credited fall of the held-out gap -- per frame, the fall of the "
    f"gap minus any fall of the model's own noise floor (noise it hides rather than explains; the floor averaged "
    f"over the same several units as the reported one), same noise draws for every model -- is accepted only if "
    f"(a) the fall is at least {100 * MIN_RELATIVE_GAIN:.0f} % of the held-out gap "
    f"and (b) it is not carried by a few frames: over {BOOTSTRAP_RESAMPLES} bootstrap resamples of the held-out "
    f"frames (with replacement), the {100 * BOOTSTRAP_QUANTILE:.0f}th percentile of that relative fall stays above "
    f"zero; a validity effect (one that only removes pixels) must moreover not lower the held-out likelihood of the "
    f"real valid/invalid map, each pixel a Bernoulli draw with the simulation's local valid rate. Named library "
    f"effects are tried first; only when none is accepted are generic smooth terms (disparity or dropout along "
    f"one axis with residual structure beyond noise) tried, and one accepted is reported as an unnamed effect "
    f"along that axis. Residual structure along an axis counts as unexplained when it exceeds twice its bootstrap noise and "
    f"is at least {UNEXPLAINED_MIN_MM:.1f} mm beyond it."
)


def judged_floors(before: Evaluation, after: Evaluation) -> tuple[np.ndarray, np.ndarray]:
    """Per-frame floors of ``before`` and ``after`` as the rule compares them: averaged over the units both were
    measured against (``reported_floors``, the same draws for every model) when they were measured with the same
    number, else the one unit both have (``frame_floors``)."""
    if before.reported_floors is not None and after.reported_floors is not None \
            and before.floor_draws == after.floor_draws:
        return np.asarray(before.reported_floors), np.asarray(after.reported_floors)
    return np.asarray(before.frame_floors), np.asarray(after.frame_floors)


def frame_falls(before: Evaluation, after: Evaluation) -> np.ndarray:
    """Per-frame credited fall of the gap: ``(gap_before - gap_after) - max(0, floor_before - floor_after)``.

    A candidate gets no credit for the part of its gap fall that its own noise floor falls too (noise it
    hides, e.g. by dropping the noisiest pixels), and no credit either for making its own draws noisier. The
    floors are :func:`judged_floors`: one unit's floor scatters by tens of percent on one frame, and the rule is
    one-sided, so a model whose draws differ (any depth change) would be charged that scatter.
    """
    gb, ga = np.asarray(before.frame_gaps), np.asarray(after.frame_gaps)
    fb, fa = judged_floors(before, after)
    return (gb - ga) - np.maximum(0.0, fb - fa)


def relative_fall(before: Evaluation, after: Evaluation) -> float:
    """Credited fall (:func:`frame_falls`) summed over frames, as a fraction of the gap before."""
    return float(frame_falls(before, after).sum() / max(float(np.sum(before.frame_gaps)), 1e-12))


def bootstrap_fall(before: Evaluation, after: Evaluation, rng: np.random.Generator,
                   resamples: int = BOOTSTRAP_RESAMPLES) -> float:  # fmt: skip
    """The BOOTSTRAP_QUANTILE-quantile of :func:`relative_fall` over resamples of the frames."""
    gb = np.asarray(before.frame_gaps)
    d = frame_falls(before, after)
    n = len(d)
    if n == 0:
        return 0.0
    idx = rng.integers(0, n, size=(resamples, n))
    falls = d[idx].sum(1) / np.maximum(gb[idx].sum(1), 1e-12)
    return float(np.quantile(falls, BOOTSTRAP_QUANTILE))


def unexplained_axes(analysis: dict) -> list[dict]:
    out = []
    for axis, (_, s) in analysis.items():
        if s.significant and s.excess_mm >= UNEXPLAINED_MIN_MM:
            out.append({"axis": axis, "strength": s.excess_mm})
    return sorted(out, key=lambda u: -u["strength"])
