"""The ``compare`` report's figures: bias, spread and validity binned along depth, incidence angle and image radius
(:func:`plot_bins`), and full-resolution residual maps sim - real (:func:`plot_residuals`, also ``fit``'s
before/after figure). Both take :class:`~ddsgen.realscan.gap_report.GapReport` s; matplotlib's Agg backend, no display."""

from __future__ import annotations

from pathlib import Path
import numpy as np

from ddsgen.realscan.gap_report import GapReport


def plot_bins(report: GapReport, path: Path) -> Path:
    """Bias +- spread of real - clean, sim - clean and sim - real (top) and valid rates (bottom) per bin of the
    report's three axes; written to ``path`` (PNG), which is returned."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 3, figsize=(13, 7), constrained_layout=True)
    titles = {"depth_m": "clean depth (m)", "incidence_deg": "incidence angle (deg)",
              "radius": "image radius (fraction of the half-diagonal)"}
    for col, (key, label) in enumerate(titles.items()):
        bins = report.parts["bins"][key]
        x = [0.5 * (b["low"] + min(b["high"], 8.0)) for b in bins]
        ax = axes[0, col]
        for name, style in (("real", "o-"), ("sim", "s--"), ("gap", "^:")):
            y = [np.nan if b[f"{name}_bias_mm"] is None else b[f"{name}_bias_mm"] for b in bins]
            e = [np.nan if b[f"{name}_spread_mm"] is None else b[f"{name}_spread_mm"] for b in bins]
            label_ = {"real": "real - clean", "sim": "sim - clean", "gap": "sim - real"}[name]
            ax.errorbar(x, y, yerr=e, fmt=style, capsize=3, label=label_)
        ax.axhline(0, color="k", lw=0.5)
        ax.set_xlabel(label)
        ax.set_ylabel("bias +- spread (mm)")
        ax.legend(fontsize=8)
        ax = axes[1, col]
        ax.plot(x, [b["real_valid_rate"] for b in bins], "o-", label="real valid rate")
        ax.plot(x, [b["sim_valid_rate"] for b in bins], "s--", label="sim valid rate")
        ax.set_ylim(0, 1.05)
        ax.set_xlabel(label)
        ax.set_ylabel("valid share of the region's pixels")
        ax.legend(fontsize=8)
    fig.suptitle(f"gap {report.gap:.2f} mm (noise floor {report.noise_floor:.2f} mm), {report.region} region")
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_residuals(reports: list[GapReport], path: Path, labels: list[str], max_frames: int = 4,
                   limit_mm: float = 30.0) -> Path:  # fmt: skip
    """Residual maps sim - real (mm) of the first frames, one row per report (e.g. before/after fitting).
    Grey: outside the region; black: valid in only one of sim/real."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = min(max_frames, min(len(r.maps) for r in reports))
    fig, axes = plt.subplots(len(reports), max(n, 1), figsize=(5.0 * max(n, 1), 4.2 * len(reports)), squeeze=False,
                             constrained_layout=True)  # fmt: skip
    for row, (report, label) in enumerate(zip(reports, labels)):
        for col in range(n):
            m = report.maps[col]
            res = (m["sim"] - m["real"]) * 1000.0
            both = m["region"] & m["sim_valid"] & (m["real"] > 0)
            one = m["region"] & (m["sim_valid"] != (m["real"] > 0))
            img = np.full(res.shape + (3,), 0.8)
            cmap = plt.get_cmap("coolwarm")
            rgb = cmap(np.clip(res / limit_mm * 0.5 + 0.5, 0, 1))[..., :3]
            img[both] = rgb[both]
            img[one] = 0.0
            ax = axes[row, col]
            ax.imshow(img, interpolation="nearest")
            ax.set_title(f"{label}\n{m['name']}", fontsize=8)
            ax.axis("off")
    sm = plt.cm.ScalarMappable(cmap="coolwarm", norm=plt.Normalize(-limit_mm, limit_mm))
    fig.colorbar(sm, ax=axes, shrink=0.6, label="sim - real (mm); black: valid in one only; grey: not compared")
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
