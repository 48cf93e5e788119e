"""Which real frames the unpaired fit learns from and which judge it, and the judgement.

A fitted preset is worth writing only if it is closer to the device on frames the fit did not see. Real frames of one
sequence share the scene, so the frames are held out by **sequence** (the folder a frame lies in: IC-BIN's seq1,
seq2, seq3): with several sequences about a third of them (at least one, at most all but one) are held out, chosen by
a seeded permutation -- ``"sequence"``; with one sequence every other frame is -- ``"frame"`` (the same scene: a weak
test, reported as such); a single frame cannot be split -- ``"none"``.

:func:`judge` compares the input preset and the fitted one on the held-out frames alone: the feature distance
(:func:`~.features.distance_terms`) between those frames and fresh renders of each (a noise seed the fit did not
use). The fitted preset is written only if its distance is lower; otherwise the input's values are kept and the
summary says so. The fit's structural choices (registration, output window) are judged the same way: each reading
the fit considered, with the fitted values, against the input's own reading with the same values (``run.py``).
"""

from __future__ import annotations

import numpy as np

from ddsgen.fit.unpaired.features import distance_terms, pool

#: What each split kind means, for the terminal and the report.
HOLDOUT_MEANING = {
    "sequence": "held-out frames are of other sequences (another scene: a real test of transfer)",
    "frame": "one sequence: every other frame held out (the same scene: optimistic)",
    "none": "one frame: nothing held out, so nothing can show the fit transfers; the input preset is kept",
}
#: Share of the sequences held out when there are several.
HOLDOUT_SHARE = 1.0 / 3.0


def sequence_of(name: str) -> str:
    """The sequence of a frame named by its path below the real folder: its first folder ('' at the top)."""
    parts = name.replace("\\", "/").split("/")
    return parts[0] if len(parts) > 1 else ""


def split_frames(names: list[str], seed: int) -> tuple[list[int], list[int], str]:
    """(fit indices, held-out indices, kind) of frames named ``names`` (see the module docstring)."""
    sequences = sorted({sequence_of(n) for n in names})
    if len(sequences) > 1:
        count = min(max(1, round(HOLDOUT_SHARE * len(sequences))), len(sequences) - 1)
        order = np.random.default_rng([int(seed), 7331]).permutation(len(sequences))
        held_sequences = {sequences[i] for i in order[:count]}
        held = [i for i, n in enumerate(names) if sequence_of(n) in held_sequences]
        return [i for i in range(len(names)) if i not in held], held, "sequence"
    if len(names) > 1:
        return list(range(0, len(names), 2)), list(range(1, len(names), 2)), "frame"
    return list(range(len(names))), [], "none"


def judge(held_features: list[dict], stock_features: list[dict], fitted_features: list[dict]) -> dict:
    """Held-out feature distance of the input preset's renders and the fitted preset's.

    Args:
        held_features: :func:`~.features.frame_features` of the held-out real frames (empty: nothing held out).
        stock_features, fitted_features: of each preset's fresh renders.

    Returns: {"stock": distance, "fitted": distance, "fitted_better": bool, "terms": {"stock": {group: distance},
    "fitted": {...}}} (the groups of :func:`~.features.distance_terms`: noise, holes, radius, grain); distances None
    and terms empty without held-out frames.
    """
    if not held_features:
        return {"stock": None, "fitted": None, "fitted_better": False, "terms": {}}
    real = pool(held_features)
    terms = {"stock": distance_terms(pool(stock_features), real), "fitted": distance_terms(pool(fitted_features), real)}
    stock, fitted = terms["stock"]["total"], terms["fitted"]["total"]
    return {"stock": stock, "fitted": fitted, "fitted_better": bool(fitted < stock), "terms": terms}
