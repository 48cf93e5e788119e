"""Which real frames the unpaired fit learns from and which judge it, and the judgement.

A fitted preset is worth writing only if it is closer to the device on frames the fit did not see. Real frames of one
sequence share the scene, so the frames are held out by **sequence** (the folder a frame lies in: IC-BIN's seq1,
seq2, seq3): with several sequences about a third of them (at least one, at most all but one) are held out, chosen by
a seeded permutation -- ``"sequence"``; with one sequence every other frame is -- ``"frame"`` (the same scene: a weak
test, reported as such); a single frame cannot be split -- ``"none"``.

:func:`judge` compares the input preset and the fitted one on the held-out frames alone: the feature distance
(:func:`~.features.distance_terms`) between those frames and fresh renders of each (a noise seed the fit did not
use), in total and by feature group. Each group's difference has a spread: a bootstrap over the frames, the
held-out real frames and the rendered scenes resampled (the two presets' renders of one scene stay paired), which
is what another draw of frames of these kinds would move it by. The fitted preset is written only if its total
distance is lower and no group is farther by more than :data:`GROUP_SIGMAS` of its spread; otherwise the input's
values are kept and the summary says which group stood against it. The registration reading the fit frames chose,
when it is not the input's, is judged the same way, more strictly: the keys fitted under it against the keys fitted
under the input's reading, kept only if the total is closer by more than :data:`GROUP_SIGMAS` of its spread
(``run.py``).

Why a spread per group: measured on IC-BIN (seq2 held out, three render seeds of one preset), the holes group
moves by up to 40 % between renders, the noise group by under 1 %; a total can fall while one group rises beyond
anything the renders explain, and a user's statistic should not get worse unseen.
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


#: A group is farther (closer) only if its difference exceeds this many bootstrap standard deviations.
GROUP_SIGMAS = 3.0
#: Bootstrap resamples of the per-group differences.
RESAMPLES = 200
#: The feature groups judged (:func:`~.features.distance_terms`).
GROUPS = ("noise", "holes", "radius", "grain")


def judge(held_features: list[dict], stock_features: list[dict], fitted_features: list[dict], *,
          seed: int = 0) -> dict:  # fmt: skip
    """Held-out feature distance of the input preset's renders and the fitted preset's, by group, with spreads.

    Args:
        held_features: :func:`~.features.frame_features` of the held-out real frames (empty: nothing held out).
        stock_features, fitted_features: of each preset's fresh renders; frame i of both is one scene (resampled
            together) when they are as many.
        seed: of the bootstrap.

    Returns: {"stock": distance, "fitted": distance, "fitted_better": bool, "terms": {"stock": {group: distance},
    "fitted": {...}}, "spread": {group: bootstrap std of fitted - stock}, "groups": {group: "closer" | "farther" |
    "within noise"}, "farther": [groups]} (the groups of :func:`~.features.distance_terms`: noise, holes, radius,
    grain, and "total"); distances None and the rest empty without held-out frames.
    """
    if not held_features:
        return {"stock": None, "fitted": None, "fitted_better": False, "terms": {}}
    real = pool(held_features)
    terms = {"stock": distance_terms(pool(stock_features), real), "fitted": distance_terms(pool(fitted_features), real)}
    spread = _difference_spread(held_features, stock_features, fitted_features, seed)
    groups = {}
    for group in (*GROUPS, "total"):
        difference = terms["fitted"][group] - terms["stock"][group]
        beyond = abs(difference) > GROUP_SIGMAS * spread[group]
        groups[group] = ("closer" if difference < 0 else "farther") if beyond else "within noise"
    farther = [group for group in GROUPS if groups[group] == "farther"]
    stock, fitted = terms["stock"]["total"], terms["fitted"]["total"]
    return {"stock": stock, "fitted": fitted, "fitted_better": bool(fitted < stock and not farther), "terms": terms,
            "spread": spread, "groups": groups, "farther": farther}  # fmt: skip


def _difference_spread(held: list[dict], stock: list[dict], fitted: list[dict], seed: int) -> dict[str, float]:
    """{group: standard deviation of (fitted - stock) distance} over :data:`RESAMPLES` bootstrap draws of the
    held-out frames and of the rendered frames (one draw for both presets when their frames pair up)."""
    rng = np.random.default_rng([int(seed), 4242])
    paired = len(stock) == len(fitted)
    draws = {group: [] for group in (*GROUPS, "total")}
    for _ in range(RESAMPLES):
        real = pool(held, rng.integers(0, len(held), len(held)))
        stock_draw = rng.integers(0, len(stock), len(stock))
        fitted_draw = stock_draw if paired else rng.integers(0, len(fitted), len(fitted))
        before, after = distance_terms(pool(stock, stock_draw), real), distance_terms(pool(fitted, fitted_draw), real)
        for group, values in draws.items():
            values.append(after[group] - before[group])
    return {group: float(np.std(values)) for group, values in draws.items()}
