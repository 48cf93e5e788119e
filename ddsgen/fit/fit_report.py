"""The ``fit --report`` folder: what the fit changed, how sure it is, and whether it transfers.

Writes into the report folder:

* ``parameters.txt`` and the table in ``index.html``: every fitted parameter before, after
  (what the output preset holds), its uncertainty (:mod:`ddsgen.fit.uncertainty`), its bounds
  and whether its group was kept or reverted (:mod:`ddsgen.fit.revert`);
* ``gaps.txt``: the gaps (mm) on the fit and the held-out frames, region ``all`` and
  ``objects``, before and after, the pixels each is measured on, the split kind and what it means;
* ``loss_curve.png``: the loss terms per Adam step (mm);
* ``frames/``: real | simulated | difference pictures of the held-out frames before and after
  (:func:`ddsgen.realscan.pictures.side_by_side`), and ``index.html`` showing all of it.
"""

from __future__ import annotations

import math
from pathlib import Path

from ddsgen.realscan.pictures import side_by_side, write_index
from ddsgen.atomic import atomic_path, atomic_write_text


def format_value(value: float, sigma: float | None = None) -> str:
    text = f"{value:.6g}"
    if sigma is None or (isinstance(sigma, float) and math.isnan(sigma)):
        return text
    return text + (" +- inf" if math.isinf(sigma) else f" +- {sigma:.2g}")


def not_identified(row: dict) -> bool:
    """Whether the frames leave a :func:`parameter_rows` row's parameter undetermined: an infinite 1 s.d., or, for a
    positive parameter fitted by its logarithm (a ``factor`` bound), a 1 s.d. at least as large as the value (the
    loss is flat over a factor of e and more; "+- 5.6e+07" on 1.2e+06 would read as if negative values fitted)."""
    sigma, bound = row["sigma"], row.get("bound")
    if not isinstance(sigma, (int, float)) or math.isnan(sigma):
        return False
    return math.isinf(sigma) or (bool(bound) and bound[0] == "factor" and sigma >= abs(row["fitted"]))


def fitted_line(row: dict) -> str:
    """A :func:`parameter_rows` row's fitted value with its 1 s.d., or, where the parameter has none (held or
    switched off: ``sigma`` is NaN), with the reason; says so when the frames do not determine it."""
    text = format_value(row["fitted"], row["sigma"])
    held = isinstance(row["sigma"], float) and math.isnan(row["sigma"])
    if held:
        return text + f" ({row['method']})"
    return text + (" (not identified by these frames)" if not_identified(row) else "")


def parameter_rows(before: dict, fitted: dict, after: dict, uncertainty: dict, kept: dict[str, bool],
                   bounds: list[dict]) -> list[dict]:  # fmt: skip
    """One row per fitted scalar parameter: name, key, before (input), fitted (the fit's value, whose
    uncertainty ``sigma`` is), after (what the output preset holds: the input's when reverted), bound, kept."""
    bound_of = {b["param"]: b["bound"] for b in bounds}
    rows = []
    for name, info in uncertainty.items():
        key = info["key"]
        rows.append({"param": name, "key": key, "before": before.get(key), "fitted": fitted.get(key),
                     "after": after.get(key),
                     "sigma": info["sigma"], "method": info["method"], "bound": bound_of.get(name),
                     "kept": kept.get(name, True),
                     "at_bound": at_bound(bound_of.get(name), before.get(key), fitted.get(key))})  # fmt: skip
    return rows


def at_bound(bound, before, fitted, tolerance: float = 1e-3) -> bool:
    """Whether ``fitted`` sits on a bound (``("factor"|"range", lo, hi)``; factors of ``before``)."""
    if not bound or before is None or fitted is None:
        return False
    kind, lo, hi = bound
    if kind == "factor":
        lo, hi = lo * before, hi * before
    span = max(abs(hi - lo), 1e-12)
    return abs(fitted - lo) <= tolerance * span or abs(fitted - hi) <= tolerance * span


def parameter_table(rows: list[dict]) -> str:
    """Plain-text table of :func:`parameter_rows`."""
    lines = [f"{'parameter':26s} {'input':>12s} {'fitted +- 1 s.d.':>24s} {'output':>12s}  {'bounds':14s} kept  "
             "uncertainty from"]
    for r in rows:
        bound = r["bound"]
        bound_text = "" if not bound else (f"x{bound[1]:g}..x{bound[2]:g}" if bound[0] == "factor"
                                           else f"{bound[1]:g}..{bound[2]:g}")  # fmt: skip
        before = "" if r["before"] is None else f"{r['before']:.6g}"
        lines.append(f"{r['key']:26s} {before:>12s} {format_value(r['fitted'], r['sigma']):>24s} {r['after']:12.6g}  "
                     f"{bound_text:14s} "
                     f"{'yes ' if r['kept'] else 'no  '}  {r['method']}" + ("; AT A BOUND" if r["at_bound"] else "")
                     + ("; NOT IDENTIFIED" if not_identified(r) else ""))  # fmt: skip
    return "\n".join(lines)


def gap_table(gaps: dict, split_kind: str, split_meaning: str, pixels: dict | None = None) -> str:
    """Plain-text table of gaps[(set, region)] = (before, after) in mm, with the pixels each gap is measured on
    (``pixels[(set, region)]``) when given."""
    lines = [f"split: {split_kind} -- {split_meaning}", f"{'frames':10s} {'region':8s} {'input':>9s} {'fitted':>9s} "
             f"{'ratio':>6s}" + (f" {'pixels':>9s}" if pixels else "")]  # fmt: skip
    for (which, region), (before, after) in gaps.items():
        ratio = after / before if before else math.nan
        lines.append(f"{which:10s} {region:8s} {before:9.2f} {after:9.2f} {ratio:6.2f}"
                     + (f" {pixels[(which, region)]:9d}" if pixels else ""))  # fmt: skip
    return "\n".join(lines)


def plot_loss(history: list[dict], path: Path) -> None:
    """Loss terms (mm) per Adam step."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4), constrained_layout=True)
    if history:
        steps = [h["step"] for h in history]
        for key in ("total", "depth", "gradient", "validity", "prior"):
            if key in history[0]:
                ax.plot(steps, [h[key] for h in history], label=key)
        ax.legend()
    else:
        ax.text(0.5, 0.5, "no Adam steps (searches only)", ha="center", transform=ax.transAxes)
    ax.set_xlabel("Adam step")
    ax.set_ylabel("loss on the fit frames (mm)")
    ax.set_title("fit loss")
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=80, format="png")
    plt.close(fig)


def held_out_pictures(folder: Path, before, after, max_frames: int = 4) -> list[tuple[str, str]]:
    """real | sim | difference of the held-out frames before and after (GapReports with maps)."""
    frames_dir = folder / "frames"
    frames_dir.mkdir(parents=True, exist_ok=True)
    pictures = []
    for i, (b, a) in enumerate(zip(before.maps[:max_frames], after.maps[:max_frames])):
        for label, tag, m in (("input preset", "before", b), ("fitted preset", "after", a)):
            stem = f"{i:03d}_{tag}.png"
            side_by_side(frames_dir / stem, f"{m['name']} (held out): {label}", m["real"], m["sim"], m["sim_valid"],
                         m["region"])  # fmt: skip
            pictures.append((f"{m['name']} -- {label}", f"frames/{stem}"))
    return pictures


def write_fit_report(folder: Path, *, title: str, rows: list[dict], gaps: dict, split_kind: str, split_meaning: str,
                     revert_lines: list[str], history: list[dict], before_maps, after_maps,
                     gap_pixels: dict | None = None) -> Path:  # fmt: skip
    """Write parameters.txt, gaps.txt, loss_curve.png, frames/ and index.html into ``folder``; returns index.html.
    ``gap_pixels[(set, region)]``: the pixels each gap is measured on (a column of gaps.txt)."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    params_text = parameter_table(rows)
    gaps_text = gap_table(gaps, split_kind, split_meaning, gap_pixels)
    atomic_write_text(folder / "parameters.txt", params_text + "\n")
    atomic_write_text(folder / "gaps.txt", gaps_text + "\n")
    plot_loss(history, folder / "loss_curve.png")
    pictures = held_out_pictures(folder, before_maps, after_maps)
    summary = "\n\n".join([gaps_text, "\n".join(revert_lines) or "every fitted group lowered the held-out gap: kept",
                           params_text])  # fmt: skip
    return write_index(folder, title, summary, pictures, ["loss_curve.png", "residuals.png"])
