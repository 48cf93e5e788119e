"""The diagnosis report: ``diagnosis.json`` (fixed shape) and ``report.html`` (plots embedded as PNG)."""

from __future__ import annotations

import base64
import html
import io
import json
from pathlib import Path

import numpy as np

from ddsgen.diagnose.acceptance import RULE
from ddsgen.diagnose.residuals import AXES, AXIS_WORDS, AxisStats


def _png(fig) -> str:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=80)
    return base64.b64encode(buf.getvalue()).decode("ascii")


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def profile_figure(curves: list[tuple[str, AxisStats]], axis: str, title: str = "") -> str:
    """Bias and validity-disagreement profiles of several models along one axis -> base64 PNG."""
    plt = _plt()
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(9.5, 3.2), constrained_layout=True)
    styles = ["o-", "s--", "^:", "d-."]
    for i, (label, stats) in enumerate(curves):
        p = stats.profile()
        x = stats.centres()
        ok = p["n_err"] >= 30
        a1.plot(x[ok], p["bias_mm"][ok], styles[i % 4], label=label)
        ok = p["n_px"] >= 30
        a2.plot(x[ok], 100.0 * p["valid_diff"][ok], styles[i % 4], label=label)
    for ax, ylabel in ((a1, "mean depth error sim - real (mm)"), (a2, "valid rate sim - real (%)")):
        ax.axhline(0.0, color="k", lw=0.5)
        ax.set_xlabel(AXES[axis])
        ax.set_ylabel(ylabel)
        ax.legend(fontsize=8)
    if title:
        fig.suptitle(title, fontsize=10)
    out = _png(fig)
    plt.close(fig)
    return out


def strengths_figure(before: dict, after: dict) -> str:
    """Bar chart of the excess structure per axis, baseline vs final -> base64 PNG."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(8, 3), constrained_layout=True)
    names = list(AXES)
    x = np.arange(len(names))
    ax.bar(x - 0.2, [before[a].excess_mm for a in names], 0.4, label="baseline")
    ax.bar(x + 0.2, [after[a].excess_mm for a in names], 0.4, label="final")
    ax.set_xticks(x, names, rotation=20)
    ax.set_ylabel("structure beyond noise (mm)")
    ax.legend(fontsize=8)
    out = _png(fig)
    plt.close(fig)
    return out


def write_json(path: Path, result: dict) -> None:
    from ddsgen.io.atomic import atomic_write_text

    atomic_write_text(path, json.dumps(result, indent=1) + "\n")


def _fmt_params(params: dict) -> str:
    return ", ".join(f"{k} = {v:.4g}" for k, v in params.items())


def write_html(path: Path, title: str, summary: list[str], steps: list[dict], overview: list[tuple[str, str]],
               unexplained_text: list[str], rule: str, rejected: list[dict]) -> None:  # fmt: skip
    """``steps``: dicts with effect, sentence, params, gap_before, gap_after, figure (base64)."""
    from ddsgen.io.atomic import atomic_write_text

    e = html.escape
    parts = [
        "<!doctype html><html><head><meta charset='utf-8'>",
        f"<title>{e(title)}</title>",
        "<style>body{font-family:sans-serif;max-width:1000px;margin:2em auto;line-height:1.4}"
        "table{border-collapse:collapse}td,th{border:1px solid #ccc;padding:3px 8px;text-align:right}"
        "th{background:#eee}td:first-child{text-align:left}img{max-width:100%}.note{color:#555}</style>",
        "</head><body>",
        f"<h1>{e(title)}</h1>",
    ]
    parts += [f"<p>{e(line)}</p>" for line in summary]
    parts.append("<h2>Steps</h2>")
    if not steps:
        parts.append("<p>No effect of the library explains the disagreement clearly beyond noise: nothing was added.</p>")
    for i, step in enumerate(steps, 1):
        parts.append(f"<h3>Step {i}: {e(step['effect'])}</h3>")
        parts.append(f"<p>{e(step['sentence'])}</p>")
        parts.append(
            f"<p class='note'>parameters: {e(_fmt_params(step['params']))}; held-out gap beyond the noise floor "
            f"{step['gap_before']:.2f} mm &rarr; {step['gap_after']:.2f} mm</p>"
        )
        parts.append(f"<img alt='residual along {e(step['axis'])}' src='data:image/png;base64,{step['figure']}'>")
    if rejected:
        parts.append("<h2>Candidates tried in the last round</h2><table><tr><th>effect</th><th>fitted parameters</th>"
                     "<th>held-out gap beyond the floor (mm)</th><th>credited fall / gap</th><th>bootstrap 5 %</th></tr>")  # fmt: skip
        for c in rejected:
            parts.append(
                f"<tr><td>{e(c['effect'])}</td><td>{e(_fmt_params(c['params']))}</td><td>{c['gap']:.2f}</td>"
                f"<td>{100 * c['gain']:.1f} %</td><td>{100 * c['gain_low']:.1f} %</td></tr>"
            )
        parts.append("</table>")
    parts.append("<h2>What remains</h2>")
    parts += [f"<p>{e(line)}</p>" for line in unexplained_text]
    for caption, figure in overview:
        parts.append(f"<h3>{e(caption)}</h3><img alt='{e(caption)}' src='data:image/png;base64,{figure}'>")
    parts.append(f"<h2>Acceptance rule</h2><p class='note'>{e(rule)}</p>")
    parts.append("</body></html>")
    atomic_write_text(path, "\n".join(parts) + "\n")


def axis_sentence(axis: str, strength: float) -> str:
    return (f"Unexplained: the disagreement still varies {AXIS_WORDS.get(axis, 'along ' + axis)} by about "
            f"{strength:.1f} mm beyond noise, and no effect of the library removes it.")  # fmt: skip


def write_diagnosis(diagnosis, folder: str | Path, title: str, notes: list[str] | None = None) -> list[Path]:
    """Write ``diagnosis.json`` and ``report.html`` of a :class:`~ddsgen.diagnose.Diagnosis` into ``folder``."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    d = diagnosis
    summary = list(notes or [])
    summary.append(
        f"{len(d.fit_frames)} frame(s) fitted, {len(d.held_frames)} held out. Held-out gap of the fitted base sensor: "
        f"{d.baseline.gap:.2f} mm, of which {d.baseline.floor:.2f} mm is its noise floor (two noise draws of the same "
        f"simulated sensor differ by this much, so no model can remove it): {d.baseline_gap:.2f} mm beyond it. "
        f"The gaps below (and in diagnosis.json) are gaps beyond the noise floor."
    )
    if d.steps:
        names = ", ".join(s.effect for s in d.steps)
        pct = 100.0 * (1.0 - d.final_gap / d.baseline_gap) if d.baseline_gap > 0 else 0.0
        summary.append(f"Effects added, in order: {names}. Final held-out gap beyond the noise floor "
                       f"{d.final_gap:.2f} mm ({pct:.0f} % less; compare gap {d.final.gap:.2f} mm, noise floor "
                       f"{d.final.floor:.2f} mm).")  # fmt: skip
    else:
        summary.append("No effect was added: the base sensor explains the scans as well as any library effect would.")
    steps = []
    for step in d.steps:
        before = step.analysis_before[step.axis][0]
        after = step.analysis_after[step.axis][0]
        fig = profile_figure([("before", before), (f"with {step.effect}", after)], step.axis,
                             f"{step.effect}: residual along {step.axis}")  # fmt: skip
        steps.append({"effect": step.effect, "sentence": step.sentence, "params": step.params,
                      "gap_before": step.gap_before, "gap_after": step.gap_after, "axis": step.axis,
                      "figure": fig})  # fmt: skip
    rejected = []
    if d.rounds:
        for c in d.rounds[-1]:
            rejected.append({"effect": c.effect, "params": c.params, "gap": c.held.excess, "gain": c.gain,
                             "gain_low": c.gain_low})  # fmt: skip
    unexplained_text = [axis_sentence(u["axis"], u["strength"]) for u in d.unexplained]
    if not unexplained_text:
        unexplained_text = ["No residual structure beyond noise remains along any axis."]
    overview = [("Residual structure beyond noise per axis", strengths_figure(
        {a: s for a, (_, s) in d.analysis_baseline.items()}, {a: s for a, (_, s) in d.analysis_final.items()}))]
    for u in d.unexplained:
        axis = u["axis"]
        overview.append((f"Residual along {axis}: baseline and final model", profile_figure(
            [("baseline", d.analysis_baseline[axis][0]), ("final", d.analysis_final[axis][0])], axis)))
    json_path, html_path = folder / "diagnosis.json", folder / "report.html"
    write_json(json_path, d.to_dict())
    write_html(html_path, title, summary, steps, overview, unexplained_text, RULE, rejected)
    return [json_path, html_path]
