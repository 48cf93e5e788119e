"""The loop's sentences: what :func:`~ddsgen.diagnose.loop.diagnose` prints and puts in the report when it
names an effect (or an unnamed one along an axis), and its short summaries of residual structure and values."""

from __future__ import annotations

from ddsgen.diagnose.axis_candidates import DISPARITY_TERM, split_label
from ddsgen.diagnose.candidates import spec
from ddsgen.diagnose.evaluation import Evaluation
from ddsgen.diagnose.residuals import AXIS_WORDS
from ddsgen.sensor.effects.axis_terms import PHYSICAL_CAUSES


def structure_summary(analysis: dict, top: int = 3) -> str:
    """The ``top`` axes with the most residual structure beyond noise, as 'AXIS X mm (noise Y)'."""
    items = sorted(analysis.items(), key=lambda kv: -kv[1][1].excess_mm)[:top]
    return ", ".join(f"{axis} {s.excess_mm:.1f} mm (noise {s.noise_mm:.1f})" for axis, (_, s) in items)


def step_sentence(label: str, params: dict, before: Evaluation, after: Evaluation) -> str:
    """The report's sentence for an accepted candidate ``label`` (a named effect or ``TERM:AXIS``) with its fitted
    ``params``: what it is, and how far the held-out gap beyond the noise floor fell (``before`` -> ``after``)."""
    name, options = split_label(label)
    cls = spec(name)
    pct = 100.0 * (1.0 - after.excess / before.excess) if before.excess > 0 else 0.0
    if cls.generic:
        axis = options["axis"]
        what = "disparity bias" if name == DISPARITY_TERM else "dropout"
        return (
            f"Unnamed effect along {axis.replace('_', ' ')}: no library effect explains the disagreement, but a "
            f"smooth {what} that varies {AXIS_WORDS.get(axis, axis)} (a degree-{len(params) - 1} Legendre profile, "
            f"plotted below) lowers the held-out gap beyond the noise floor from {before.excess:.2f} mm to "
            f"{after.excess:.2f} mm ({pct:.0f} % less; compare gap {before.gap:.2f} -> {after.gap:.2f} mm, noise "
            f"floor {after.floor:.2f} mm). Physical effects that produce such a shape: {'; '.join(PHYSICAL_CAUSES[axis])}."
        )  # fmt: skip
    values = ", ".join(f"{k} = {v:.3g} {cls.params[k].unit}".rstrip() for k, v in params.items())
    return (
        f"Missing effect: {name}. {cls.description} With it ({values}) the held-out gap beyond the noise floor "
        f"falls from {before.excess:.2f} mm to {after.excess:.2f} mm ({pct:.0f} % less; compare gap {before.gap:.2f} "
        f"-> {after.gap:.2f} mm, noise floor {after.floor:.2f} mm); the disagreement it removes varied "
        f"{AXIS_WORDS.get(cls.axis, cls.axis)} ({cls.signature})."
    )

def format_values(values: dict) -> str:
    """'k=v, ...' with 4 significant digits (the loop's log lines)."""
    return ", ".join(f"{k}={v:.4g}" for k, v in values.items())
