"""The noise study's outputs: noise.json, the Markdown tables and the figure (:mod:`ddsgen.study.noise` measures)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ddsgen.atomic import atomic_path, atomic_write_text
from ddsgen.preset import SensorPreset
from ddsgen.study.lateral import nguyen_lateral_px
from ddsgen.study.noise import NoisePoint, khoshelham_sigma, nguyen_sigma
from ddsgen.study.quantisation import RealQuantisation, local_steps, quantisation_step

#: A point agrees with a published curve when its std is within this fraction of it (+-30 %).
AGREEMENT = 0.3
#: Khoshelham & Oude Elberink measured their random error on a plane facing the sensor: their curve judges the points
#: tilted by at most this much.
KHOSHELHAM_MAX_ANGLE_DEG = 30.0


def verdict(points: list[NoisePoint]) -> dict:
    """How many points lie within +-:data:`AGREEMENT` of each published Kinect V1 curve, and which do not.

    ``{curve: {"within": k, "of": n, "misses": [[z, angle_deg, std / curve or None], ...]}}`` for ``"nguyen"`` (the
    10-60 deg curve, every point), ``"nguyen_with_angle"`` (with Nguyen's angle term, every point) and
    ``"khoshelham"`` (1.425e-3 z^2, the points tilted by at most :data:`KHOSHELHAM_MAX_ANGLE_DEG`). A point without
    valid pixels (std None) is a miss.
    """
    curves = {"nguyen": (lambda p: nguyen_sigma(p.z), lambda p: True),
              "nguyen_with_angle": (lambda p: nguyen_sigma(p.z, p.angle_deg), lambda p: True),
              "khoshelham": (lambda p: khoshelham_sigma(p.z), lambda p: p.angle_deg <= KHOSHELHAM_MAX_ANGLE_DEG)}
    result = {}
    for name, (curve, judged) in curves.items():
        judged_points = [p for p in points if judged(p)]
        misses = []
        for p in judged_points:
            ratio = None if p.std_m is None else p.std_m / float(curve(p))
            if ratio is None or abs(ratio - 1.0) > AGREEMENT:
                misses.append([p.z, p.angle_deg, None if ratio is None else round(ratio, 3)])
        result[name] = {"within": len(judged_points) - len(misses), "of": len(judged_points), "misses": misses}
    return result


VERDICT_LABELS = {"nguyen": "Nguyen 2012", "nguyen_with_angle": "Nguyen 2012 with its angle term",
                  "khoshelham": f"Khoshelham 2012 (α ≤ {KHOSHELHAM_MAX_ANGLE_DEG:g}°)"}


def verdict_line(result: dict) -> str:
    """One line: ``within ±30 %: Nguyen 2012 30 of 39, ...``."""
    parts = [f"{VERDICT_LABELS[name]} {v['within']} of {v['of']}" for name, v in result.items() if v["of"]]
    return f"within ±{100 * AGREEMENT:.0f} %: " + ", ".join(parts)


def verdict_section(result: dict) -> str:
    """Markdown: the verdict line and each curve's misses (z, angle, std / curve)."""
    lines = [verdict_line(result), ""]
    for name, v in result.items():
        if v["misses"]:
            misses = ", ".join(f"{z:g} m / {a:g}° ({'no valid pixels' if r is None else f'{r:.2f}×'})"
                               for z, a, r in v["misses"])  # fmt: skip
            lines.append(f"- misses against {VERDICT_LABELS[name]}: {misses}")
    return "\n".join(lines) + "\n"


def write_noise_json(points: list[NoisePoint], path: Path | str, lateral: list | None = None) -> None:
    """``{"points": [{z, angle_deg, rms_m, std_m, bias_m, valid_fraction, step_m}, ...], "verdict": ...}``
    (:func:`verdict`), atomically; with ``lateral`` (:class:`~ddsgen.study.lateral.LateralPoint` list) also
    ``"lateral": [{z, angle_deg, lateral_px, left_px, right_px, nguyen_px}, ...]``."""
    data = {"points": [p.as_json() for p in points], "verdict": verdict(points)}
    if lateral is not None:
        data["lateral"] = [p.as_json() for p in lateral]
    atomic_write_text(path, json.dumps(data, indent=1) + "\n")


def _mm(value: float | None, digits: int = 2) -> str:
    return "n/a" if value is None else f"{1000 * value:.{digits}f}"


def markdown_table(header: list[str], rows: list[list[str]]) -> str:
    """A Markdown table, every column right-aligned, one line per row, ending in a newline."""
    lines = ["| " + " | ".join(header) + " |", "|" + "---:|" * len(header)]
    lines += ["| " + " | ".join(row) + " |" for row in rows]
    return "\n".join(lines) + "\n"


def noise_table(points: list[NoisePoint]) -> str:
    """A Markdown table of the measurements beside the Nguyen curve (ratios std/Nguyen and rms/Nguyen).

    "Nguyen" is the 10-60 deg curve 0.0012 + 0.0019 (z - 0.4)^2; "Nguyen+angle" adds the angle term.
    """
    header = ["z (m)", "α (°)", "std (mm)", "rms (mm)", "bias (mm)", "valid", "outliers", "inlier std (mm)",
              "Nguyen (mm)", "Nguyen+angle (mm)", "std/Nguyen", "rms/Nguyen", "inlier std/Nguyen", "step (mm)"]
    rows = []
    for p in points:
        base = float(nguyen_sigma(p.z))
        full = float(nguyen_sigma(p.z, p.angle_deg))
        ratio = "n/a" if p.std_m is None else f"{p.std_m / base:.2f}"
        ratio_rms = "n/a" if p.rms_m is None else f"{p.rms_m / base:.2f}"
        ratio_inlier = "n/a" if p.inlier_std_m is None else f"{p.inlier_std_m / base:.2f}"
        outliers = "n/a" if p.outlier_fraction is None else f"{100 * p.outlier_fraction:.2f}%"
        rows.append([f"{p.z:g}", f"{p.angle_deg:g}", _mm(p.std_m), _mm(p.rms_m), _mm(p.bias_m),
                     f"{p.valid_fraction:.3f}", outliers, _mm(p.inlier_std_m), f"{1000 * base:.2f}",
                     f"{1000 * full:.2f}", ratio, ratio_rms, ratio_inlier, _mm(p.step_m)])  # fmt: skip
    return markdown_table(header, rows)


def quantisation_table(points: list[NoisePoint], preset: SensorPreset, real: RealQuantisation,
                       at=(1.0, 2.0)) -> str:  # fmt: skip
    """Markdown: the quantisation step at ``at`` (m): simulated, preset formula, device formula, real data."""
    f, b, n = preset.focal_px, preset.baseline_m, preset.subpixel_level
    header = ["z (m)", "simulated (mm)", f"z²/(2^{n}·f·b) (mm)", "z²/(8·f·b) (mm)", "real LineMOD frame (mm)",
              "real distReal list (mm)", "simulated / LineMOD", "simulated / distReal"]
    rows = []
    for z in at:
        sims = [p.step_m for p in points if abs(p.z - z) < 1e-9 and p.step_m is not None]
        sim = float(np.median(sims)) if sims else None
        real_steps = real.step_at(z)
        ratios = []
        for name in ("linemod", "distreal"):
            r = real_steps[name]
            ratios.append("n/a" if sim is None or r is None else f"{sim / r:.2f}")
        rows.append([f"{z:g}", _mm(sim), f"{1000 * float(quantisation_step(z, f, b, n)):.2f}",
                     f"{1000 * float(quantisation_step(z, f, b, 3)):.2f}", _mm(real_steps["linemod"]),
                     _mm(real_steps["distreal"]), *ratios])  # fmt: skip
    return markdown_table(header, rows)


def lateral_table(points: list, fx: float) -> str:
    """A Markdown table of the lateral noise (:class:`~ddsgen.study.lateral.LateralPoint` list) beside Nguyen's (px;
    mm at the board's distance: px z / fx), and the edges' fattening (px outside the true edge, both edges' mean)."""
    def px(value):
        return "n/a" if value is None else f"{value:.2f}"

    header = ["z (m)", "α (°)", "left (px)", "right (px)", "both (px)", "Nguyen (px)", "both/Nguyen", "both (mm)",
              "fattening (px)"]
    rows = []
    for p in points:
        nguyen = float(nguyen_lateral_px(p.angle_deg))
        both = p.lateral_px
        ratio = "n/a" if both is None else f"{both / nguyen:.2f}"
        mm = "n/a" if both is None else f"{1000 * both * p.z / fx:.2f}"
        rows.append([f"{p.z:g}", f"{p.angle_deg:g}", px(p.left_px), px(p.right_px), px(both), f"{nguyen:.2f}", ratio,
                     mm, px(p.fattening_px)])  # fmt: skip
    return markdown_table(header, rows)


def _label_panel(ax, xlabel: str, ylabel: str, title: str, legend_columns: int = 1, minor_grid: bool = False) -> None:
    """Axis labels, title, legend and grid of one study plot panel."""
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.legend(fontsize=7, ncol=legend_columns)
    ax.grid(True, which="both" if minor_grid else "major", alpha=0.3)


def plot_noise_study(points: list[NoisePoint], preset: SensorPreset, real: RealQuantisation, path: Path | str,
                     lateral: list | None = None) -> None:  # fmt: skip
    """One PNG, six panels: std vs z per alpha with Nguyen / Khoshelham; std / Nguyen; std vs alpha;
    quantisation step vs z with the real device's values; bias vs z; valid fraction vs z. With ``lateral``
    (:class:`~ddsgen.study.lateral.LateralPoint` list) two more: the lateral noise vs z beside Nguyen's, and its
    ratio."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    angles = sorted({p.angle_deg for p in points})
    zs = sorted({p.z for p in points})
    colours = plt.cm.viridis(np.linspace(0.0, 0.9, max(len(angles), 1)))
    z_line = np.linspace(min(zs + [0.4]), max(zs + [4.0]), 200)

    def series(angle, key):
        rows = [(p.z, getattr(p, key)) for p in points if p.angle_deg == angle and getattr(p, key) is not None]
        return (np.array([r[0] for r in rows]), np.array([r[1] for r in rows])) if rows else (np.zeros(0), np.zeros(0))

    fig, axes = plt.subplots(2, 4 if lateral else 3, figsize=(22.5 if lateral else 17, 10))
    ax = axes[0, 0]
    for colour, angle in zip(colours, angles):
        z, s = series(angle, "std_m")
        ax.plot(z, 1000 * s, "o-", color=colour, ms=4, label=f"simulated α={angle:g}°")
        z, s = series(angle, "inlier_std_m")
        ax.plot(z, 1000 * s, "o:", color=colour, ms=4, mfc="none", lw=0.8)
        if angle > 60:
            ax.plot(z_line, 1000 * nguyen_sigma(z_line, angle), "--", color=colour, lw=1,
                    label=f"Nguyen 2012 with angle term, θ={angle:g}°")  # fmt: skip
    ax.plot(z_line, 1000 * nguyen_sigma(z_line), "k--", lw=2, label="Nguyen 2012 (10°–60°)")
    ax.fill_between(z_line, 700 * nguyen_sigma(z_line), 1300 * nguyen_sigma(z_line), color="k", alpha=0.08,
                    label="Nguyen ±30 %")  # fmt: skip
    ax.plot(z_line, 1000 * khoshelham_sigma(z_line), "k:", lw=2, label="Khoshelham 2012 1.425e-3 z²")
    ax.set_yscale("log")
    _label_panel(ax, "plane distance z (m)", "axial noise std (mm, plane removed)\nhollow: without outlier matches",
                 f"{preset.name}: axial noise vs distance", minor_grid=True)

    ax = axes[0, 1]
    for colour, angle in zip(colours, angles):
        z, s = series(angle, "std_m")
        if len(z):
            ax.plot(z, s / nguyen_sigma(z), "o-", color=colour, ms=4, label=f"α={angle:g}°")
    ax.axhspan(0.7, 1.3, color="g", alpha=0.1, label="goal ±30 %")
    ax.axhline(1.0, color="k", lw=1)
    ax.set_yscale("log")
    _label_panel(ax, "plane distance z (m)", "simulated std / Nguyen (10°–60° curve)", "ratio to Nguyen 2012",
                 minor_grid=True)

    ax = axes[0, 2]
    picks = [z for z in (0.5, 1.0, 2.0, 3.0, 3.5) if z in zs] or zs[:: max(len(zs) // 4, 1)]
    theta = np.linspace(0.0, max(angles + [75.0]), 100)
    for colour, z in zip(plt.cm.plasma(np.linspace(0.0, 0.85, len(picks))), picks):
        rows = [(p.angle_deg, p.std_m) for p in points if p.z == z and p.std_m is not None]
        if rows:
            ax.plot([r[0] for r in rows], [1000 * r[1] for r in rows], "o-", color=colour, label=f"simulated z={z:g} m")
        ax.plot(theta, 1000 * nguyen_sigma(z, theta), "--", color=colour, lw=1, label=f"Nguyen+angle z={z:g} m")
    ax.set_yscale("log")
    _label_panel(ax, "tilt α (deg)", "axial noise std (mm)", "axial noise vs tilt", legend_columns=2, minor_grid=True)

    ax = axes[1, 0]
    f, b, n = preset.focal_px, preset.baseline_m, preset.subpixel_level
    steps = [(p.z, p.step_m) for p in points if p.step_m is not None]
    if steps:
        ax.plot([s[0] for s in steps], [1000 * s[1] for s in steps], "bo", ms=5, label="simulated (distinct values)")
    ax.plot(z_line, 1000 * quantisation_step(z_line, f, b, n), "b-", label=f"z²/(2^{n}·f·b) (preset, 1/{2**n} px)")
    ax.plot(z_line, 1000 * quantisation_step(z_line, f, b, 3), "k--", label="z²/(8·f·b) (device, 1/8 px)")
    if real.linemod is not None:
        mids, diffs = local_steps(real.linemod, resolution=1e-3)
        ax.plot(mids, 1000 * diffs, ".", color="tab:red", ms=3, alpha=0.6, label="real LineMOD frame (OpenNI, mm)")
    if real.distreal is not None:
        mids, diffs = local_steps(real.distreal, resolution=1e-3)
        ax.plot(mids, 1000 * diffs, "-", color="tab:orange", lw=1, label="real Kinect for Windows value list")
    for message in real.messages:
        ax.text(0.02, 0.98 - 0.05 * real.messages.index(message), message[-70:], transform=ax.transAxes,
                fontsize=6, va="top")  # fmt: skip
    ax.set_xlim(0.0, max(zs + [4.0]) + 0.25)
    ax.set_ylim(0.3, None)
    ax.set_yscale("log")
    _label_panel(ax, "depth z (m)", "quantisation step (mm)", "depth quantisation step", minor_grid=True)

    ax = axes[1, 1]
    for colour, angle in zip(colours, angles):
        z, s = series(angle, "bias_m")
        ax.plot(z, 1000 * s, "o-", color=colour, ms=4, label=f"α={angle:g}°")
    ax.axhline(0.0, color="k", lw=1)
    ax.set_yscale("symlog", linthresh=1.0)
    _label_panel(ax, "plane distance z (m)", "bias: mean(depth − true) (mm, symlog)", "bias")

    ax = axes[1, 2]
    for colour, angle in zip(colours, angles):
        z, s = series(angle, "valid_fraction")
        ax.plot(z, s, "o-", color=colour, ms=4, label=f"α={angle:g}°")
    ax.set_ylim(-0.02, 1.02)
    _label_panel(ax, "plane distance z (m)", "valid fraction of the region", "valid pixels")

    if lateral:
        _plot_lateral(axes[0, 3], axes[1, 3], lateral, angles, colours)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=90, format="png")
    plt.close(fig)


def _plot_lateral(ax_px, ax_ratio, lateral: list, angles: list[float], colours) -> None:
    """The lateral noise (px) vs z per alpha with Nguyen's value, and its ratio to Nguyen's (goal band +-30 %)."""
    for colour, angle in zip(colours, angles):
        rows = [(p.z, p.lateral_px) for p in lateral if p.angle_deg == angle and p.lateral_px is not None]
        nguyen = float(nguyen_lateral_px(angle))
        ax_px.axhline(nguyen, color=colour, ls="--", lw=1)
        if rows:
            z, px = np.array(rows).T
            ax_px.plot(z, px, "o-", color=colour, ms=4, label=f"simulated α={angle:g}° (dashed: Nguyen {nguyen:.2f})")
            ax_ratio.plot(z, px / nguyen, "o-", color=colour, ms=4, label=f"α={angle:g}°")
    ax_px.set_ylim(0.0, None)
    _label_panel(ax_px, "board distance z (m)", "lateral noise: edge rows' RMS distance from a line (px)",
                 "lateral noise (board's vertical edges before a wall)")  # fmt: skip
    ax_ratio.axhspan(0.7, 1.3, color="g", alpha=0.1, label="±30 %")
    ax_ratio.axhline(1.0, color="k", lw=1)
    _label_panel(ax_ratio, "board distance z (m)", "simulated / Nguyen 2012 (0.8 + 0.035 θ/(π/2 − θ) px)",
                 "lateral noise ratio to Nguyen 2012")  # fmt: skip
