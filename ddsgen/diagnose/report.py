"""The diagnosis report: ``diagnosis.json`` (fixed shape), ``report.html`` and its figures as PNG files in ``plots/``."""

from __future__ import annotations

import html
import json
from pathlib import Path

import numpy as np

from ddsgen.atomic import atomic_folder, atomic_path, atomic_write_text
from ddsgen.diagnose.acceptance import RULE
from ddsgen.diagnose.maps import ResidualMap, crop_zoom, region_box
from ddsgen.diagnose.residuals import AXES, AXIS_WORDS, AxisStats
from ddsgen.realscan.gap_report import BELOW_FLOOR
from ddsgen.sensor.effects.axis_terms import axis_shape
from ddsgen.sensor.effects.features import PIXEL_AXES

#: Where the report's figures go, relative to the report folder (report.html references them).
PLOTS = "plots"
DPI = 100


def _figure(width_px: int, height_px: int):
    """A matplotlib Figure of exactly ``width_px`` x ``height_px`` at :data:`DPI` (object API: no pyplot state)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width_px / DPI, height_px / DPI), dpi=DPI)
    FigureCanvasAgg(fig)
    return fig


def _save(fig, path: Path) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=DPI, format="png", metadata={"Software": None})


def profile_figure(curves: list[tuple[str, AxisStats]], axis: str, path: Path, title: str = "") -> None:
    """Bias and validity-disagreement profiles of several models along one axis -> PNG ``path`` (1200 x 450 px)."""
    fig = _figure(1200, 450)
    a1, a2 = fig.subplots(1, 2)
    styles = ["o-", "s--", "^:", "d-."]
    for i, (label, stats) in enumerate(curves):
        p = stats.profile()
        x = stats.centres()
        ok = p["n_err"] >= 30
        a1.plot(x[ok], p["bias_mm"][ok], styles[i % 4], label=label)
        ok = p["n_px"] >= 30
        a2.plot(x[ok], 100.0 * p["valid_diff"][ok], styles[i % 4], label=label)
    for ax, ylabel in ((a1, "mean depth error sim - real (mm)"), (a2, "valid rate sim - real (percentage points)")):
        ax.axhline(0.0, color="k", lw=0.5)
        ax.set_xlabel(AXES[axis])
        ax.set_ylabel(ylabel)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=9)
    if title:
        fig.suptitle(title, fontsize=12)
    fig.set_layout_engine("constrained")
    _save(fig, path)


def shape_figure(effect, path: Path) -> None:
    """The fitted shape of a generic axis term along its axis -> PNG ``path`` (700 x 400 px)."""
    x, y = axis_shape(effect)
    fig = _figure(700, 400)
    ax = fig.subplots()
    ax.plot(x, y, "-", lw=2)
    if effect.axis == "signal":
        ax.set_xscale("log")
    ax.axhline(1.0 if effect.stage == "validity" else 0.0, color="k", lw=0.5)
    ax.set_xlabel(PIXEL_AXES[effect.axis], fontsize=8)
    ax.set_ylabel("keep probability" if effect.stage == "validity" else "disparity bias added (px)")
    ax.set_title(f"fitted {effect.name} along {effect.axis}", fontsize=11)
    ax.grid(alpha=0.3)
    fig.set_layout_engine("constrained")
    _save(fig, path)


def strengths_figure(before: dict, after: dict, path: Path) -> None:
    """Bar chart of the excess structure per axis, baseline vs final -> PNG ``path`` (1000 x 400 px)."""
    fig = _figure(1000, 400)
    ax = fig.subplots()
    names = list(AXES)
    x = np.arange(len(names))
    ax.bar(x - 0.2, [before[a].excess_mm for a in names], 0.4, label="baseline")
    ax.bar(x + 0.2, [after[a].excess_mm for a in names], 0.4, label="final")
    ax.set_xticks(x, names, rotation=20)
    ax.set_xlabel("residual axis")
    ax.set_ylabel("structure beyond noise (mm)")
    ax.grid(axis="y", alpha=0.3)
    ax.legend(fontsize=9)
    fig.set_layout_engine("constrained")
    _save(fig, path)


#: Colours of the pixels a residual map cannot show as a number (RGB in [0, 1]).
REAL_ONLY_RGB, SIM_ONLY_RGB, NOT_COMPARED_RGB = (0.0, 0.0, 0.0), (0.1, 0.75, 0.2), (0.82, 0.82, 0.82)


def residual_map_figure(panels: list[tuple[str, ResidualMap]], path: Path, title: str, zoom: int = 1,
                        outline: np.ndarray | None = None) -> list[tuple[int, ...]]:  # fmt: skip
    """Residual maps side by side, each at the frame's full resolution (one figure pixel per image pixel) -> PNG.

    Colour: simulated minus real depth (mm) on a diverging scale shared by the panels (symmetric,
    the 99th percentile of |residual|); black: real depth but no simulated depth; green: simulated
    depth but no real depth; grey: not compared. Axes in the frame's pixels (a crop keeps its place: the
    axes start at its ``origin``), colour bar in millimetres. ``zoom``: each image pixel is drawn as a
    square of that many figure pixels (for a crop: :func:`~ddsgen.diagnose.maps.crop_zoom`). ``outline``: a
    (H, W) bool mask of the whole frame (local patches) drawn as black contours on every panel.
    Returns each panel's pixel box (x0, y0, x1, y1) in the PNG (x right, y down).
    """
    from matplotlib import colormaps
    from matplotlib.cm import ScalarMappable
    from matplotlib.colors import Normalize

    rows, cols = panels[0][1].residual_mm.shape
    height, width = rows * zoom, cols * zoom
    left, gap, right, top, bottom = 70, 70, 120, 60, 80
    fig_w, fig_h = left + len(panels) * width + (len(panels) - 1) * gap + right, top + height + bottom
    fig = _figure(fig_w, fig_h)
    values = np.concatenate([np.abs(m.residual_mm[np.isfinite(m.residual_mm)]) for _, m in panels])
    limit = float(np.ceil(max(np.percentile(values, 99.0), 1.0))) if values.size else 1.0
    norm, cmap = Normalize(-limit, limit), colormaps["RdBu_r"]
    boxes = []
    for i, (label, m) in enumerate(panels):
        x0 = left + i * (width + gap)
        boxes.append((x0, top, x0 + width, top + height))
        ax = fig.add_axes((x0 / fig_w, bottom / fig_h, width / fig_w, height / fig_h))
        rgb = np.empty((rows, cols, 3))
        rgb[:] = NOT_COMPARED_RGB
        finite = np.isfinite(m.residual_mm)
        rgb[finite] = cmap(norm(m.residual_mm[finite]))[:, :3]
        rgb[m.real_only] = REAL_ONLY_RGB
        rgb[m.sim_only] = SIM_ONLY_RGB
        rgb = np.repeat(np.repeat(rgb, zoom, 0), zoom, 1)  # whole pixels: the PNG stays pixel-sharp
        (ox, oy) = m.origin
        ax.imshow(rgb, interpolation="nearest", extent=(ox, ox + cols, oy + rows, oy), aspect="auto")
        if outline is not None and outline[oy : oy + rows, ox : ox + cols].any():
            ax.contour(ox + 0.5 + np.arange(cols), oy + 0.5 + np.arange(rows),
                       outline[oy : oy + rows, ox : ox + cols].astype(float), levels=[0.5], colors="k",
                       linewidths=1.0)  # fmt: skip
        ax.set_title(label, fontsize=11)
        ax.set_xlabel("column (px)")
        if i == 0:
            ax.set_ylabel("row (px)")
    bar = fig.add_axes(((fig_w - right + 25) / fig_w, bottom / fig_h, 18 / fig_w, height / fig_h))
    fig.colorbar(ScalarMappable(norm=norm, cmap=cmap), cax=bar, extend="both").set_label("sim - real depth (mm)")
    fig.suptitle(title, fontsize=11)
    fig.text(0.5, 4 / fig_h, "black: real depth, no simulated depth; green: simulated depth, no real depth; "
             "grey: not compared" + ("; black lines: local patches" if outline is not None else ""),
             ha="center", va="bottom", fontsize=9, color="0.3", wrap=True)  # fmt: skip
    _save(fig, path)
    return boxes


def write_json(path: Path, result: dict) -> None:
    atomic_write_text(path, json.dumps(result, indent=1) + "\n")


def _fmt_params(params: dict) -> str:
    return ", ".join(f"{k} = {v:.4g}" for k, v in params.items())


def _img(src: str, alt: str) -> str:
    """An image linked to itself (a click opens it at full resolution)."""
    e = html.escape
    return f"<a href='{e(src)}'><img alt='{e(alt)}' src='{e(src)}'></a>"


def write_html(path: Path, title: str, summary: list[str], steps: list[dict], overview: list[tuple[str, str]],
               unexplained_text: list[str], rule: str, rejected: list[dict],
               maps: list[tuple[str, str]] = ()) -> None:  # fmt: skip
    """``steps``: dicts with effect, sentence, params, gap_before, gap_after, axis, figure (PNG path relative to
    the report); ``overview`` and ``maps``: (caption, PNG path relative to the report)."""
    e = html.escape
    parts = [
        "<!doctype html><html><head><meta charset='utf-8'>",
        f"<title>{e(title)}</title>",
        "<style>body{font-family:sans-serif;max-width:1400px;margin:2em auto;line-height:1.4}"
        "table{border-collapse:collapse}td,th{border:1px solid #ccc;padding:3px 8px;text-align:right}"
        "th{background:#eee}td:first-child{text-align:left}img{max-width:100%}.note{color:#555}</style>",
        "</head><body>",
        f"<h1>{e(title)}</h1>",
    ]
    parts += [f"<p>{e(line)}</p>" for line in summary]
    parts.append("<h2>Steps</h2>")
    if not steps:
        parts.append("<p>No effect of the library, and no generic term along an axis, explains the disagreement "
                     "clearly beyond noise: nothing was added.</p>")
    for i, step in enumerate(steps, 1):
        parts.append(f"<h3>Step {i}: {e(step['effect'])}</h3>")
        parts.append(f"<p>{e(step['sentence'])}</p>")
        parts.append(
            f"<p class='note'>parameters: {e(_fmt_params(step['params']))}; held-out gap beyond the noise floor "
            f"{step['gap_before']:.2f} mm &rarr; {step['gap_after']:.2f} mm</p>"
        )
        parts.append(_img(step["figure"], f"residual along {step['axis']}"))
        if step.get("shape"):
            parts.append(_img(step["shape"], f"fitted shape along {step['axis']}"))
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
        parts.append(f"<h3>{e(caption)}</h3>{_img(figure, caption)}")
    if maps:
        parts.append("<h2>Residual maps (held-out frames, full resolution)</h2>")
    for caption, figure in maps:
        parts.append(f"<h3>{e(caption)}</h3>{_img(figure, caption)}")
    parts.append(f"<h2>Acceptance rule</h2><p class='note'>{e(rule)}</p>")
    parts.append("</body></html>")
    atomic_write_text(path, "\n".join(parts) + "\n")


def axis_sentence(axis: str, strength: float) -> str:
    return (f"Unexplained: the disagreement still varies {AXIS_WORDS.get(axis, 'along ' + axis)} by about "
            f"{strength:.1f} mm beyond noise, and no effect of the library removes it.")  # fmt: skip


def generic_term(sensor, label: str):
    """The generic axis term of ``sensor`` that a step label ``NAME:AXIS`` names, or None."""
    name, _, axis = label.partition(":")
    if not axis:
        return None
    return next((e for e in sensor.effects if e.name == name and getattr(e, "axis", None) == axis), None)


def write_diagnosis(diagnosis, folder: str | Path, title: str, notes: list[str] | None = None) -> list[Path]:
    """Write ``diagnosis.json``, ``report.html`` and ``plots/`` of a :class:`~ddsgen.diagnose.Diagnosis` into
    ``folder``; returns the first two. The report is built under a temporary name and put in place whole
    (:func:`ddsgen.atomic.atomic_folder`): an interrupted run leaves no half-written report."""
    with atomic_folder(folder, "the report", last="report.html") as building:
        _write_diagnosis(diagnosis, building, title, notes)
    return [Path(folder) / "diagnosis.json", Path(folder) / "report.html"]


def _write_diagnosis(diagnosis, folder: Path, title: str, notes: list[str] | None) -> None:
    plots = folder / PLOTS
    d = diagnosis
    summary = list(notes or []) + list(getattr(d, "notes", []))
    summary.append(
        f"{len(d.fit_frames)} frame(s) fitted, {len(d.held_frames)} held out. Held-out gap of the fitted base sensor: "
        f"{d.baseline.gap:.2f} mm, of which {d.baseline.floor:.2f} mm is its noise floor (two units of the same "
        f"simulated sensor, each with its own noise, speckle and dot positions, differ by this much, so no model can "
        f"remove it; averaged over {d.baseline.floor_draws} unit(s) per held-out frame): {d.baseline_gap:.2f} mm "
        f"beyond it. "
        f"The gaps below (and in diagnosis.json) are gaps beyond the noise floor."
    )
    if d.steps:
        names = ", ".join(s.effect for s in d.steps)
        pct = 100.0 * (1.0 - d.final_gap / d.baseline_gap) if d.baseline_gap > 0 else 0.0
        summary.append(f"Effects added, in order: {names}. Final held-out gap beyond the noise floor "
                       f"{d.final_gap:.2f} mm ({pct:.0f} % less; compare gap {d.final.gap:.2f} mm, noise floor "
                       f"{d.final.floor:.2f} mm)." + (f" That is {BELOW_FLOOR}." if d.final_gap < 0 else ""))  # fmt: skip
    else:
        summary.append("No effect was added: the base sensor explains the scans as well as any library effect or "
                       "generic axis term would." + (" What remains is local, in patches of the scene (below)."
                                                     if d.local is not None and d.local.count else ""))  # fmt: skip
    steps = []
    for i, step in enumerate(d.steps, 1):
        before = step.analysis_before[step.axis][0]
        after = step.analysis_after[step.axis][0]
        name = f"step{i}_{step.effect.replace(':', '_')}_{step.axis}.png"
        profile_figure([("before", before), (f"with {step.effect}", after)], step.axis, plots / name,
                       f"{step.effect}: residual along {step.axis}")  # fmt: skip
        entry = {"effect": step.effect, "sentence": step.sentence, "params": step.params,
                 "gap_before": step.gap_before, "gap_after": step.gap_after, "axis": step.axis,
                 "figure": f"{PLOTS}/{name}"}  # fmt: skip
        term = generic_term(d.sensor, step.effect)
        if term is not None:
            shape = f"step{i}_{step.effect.replace(':', '_')}_shape.png"
            shape_figure(term, plots / shape)
            entry["shape"] = f"{PLOTS}/{shape}"
        steps.append(entry)
    rejected = []
    if d.rounds:
        for c in d.rounds[-1]:
            rejected.append({"effect": c.effect, "params": c.params, "gap": c.held.excess, "gain": c.gain,
                             "gain_low": c.gain_low})  # fmt: skip
    unexplained_text = [axis_sentence(u["axis"], u["strength"]) for u in d.unexplained]
    if not unexplained_text:
        unexplained_text = ["No residual structure beyond noise remains along any axis."]
    if d.local is not None:
        unexplained_text.append(d.local.sentence())
    outlines = {p.name: p.mask for p in d.local.patches if p.sizes_px} if d.local is not None else {}
    strengths_figure({a: s for a, (_, s) in d.analysis_baseline.items()},
                     {a: s for a, (_, s) in d.analysis_final.items()}, plots / "structure_per_axis.png")  # fmt: skip
    overview = [("Residual structure beyond noise per axis", f"{PLOTS}/structure_per_axis.png")]
    for u in d.unexplained:
        axis = u["axis"]
        profile_figure([("baseline", d.analysis_baseline[axis][0]), ("final", d.analysis_final[axis][0])], axis,
                       plots / f"unexplained_{axis}.png")  # fmt: skip
        overview.append((f"Residual along {axis}: baseline and final model", f"{PLOTS}/unexplained_{axis}.png"))
    maps = []
    final_label = f"final model (with {', '.join(s.effect for s in d.steps)})" if d.steps else "no effect added"
    for i, (before, after) in enumerate(zip(d.maps_baseline, d.maps_final)):
        panels = [("fitted base sensor", before)] + ([(final_label, after)] if d.steps else [])
        box = region_box([m for _, m in panels])  # a small region (--region objects) is shown, not the frame
        panels = [(label, m.cropped(box)) for label, m in panels] if box else panels
        where = (f", cropped to the compared region (columns {box[0]}-{box[2] - 1}, rows {box[1]}-{box[3] - 1})"
                 if box else "")  # fmt: skip
        name = f"residual_map_{i}.png"
        residual_map_figure(panels, plots / name, f"held-out frame {before.name}{where}",
                            crop_zoom(box[2] - box[0]) if box else 1, outlines.get(before.name))  # fmt: skip
        maps.append((f"Held-out frame {before.name}: simulated minus real depth{where}", f"{PLOTS}/{name}"))
    json_path, html_path = folder / "diagnosis.json", folder / "report.html"
    write_json(json_path, d.to_dict())
    write_html(html_path, title, summary, steps, overview, unexplained_text, RULE, rejected, maps)
