"""The pictures of a compare report: full-resolution real | simulated | difference, and index.html.

Each side-by-side picture shows three panels at the image's own resolution (one image pixel
= one picture pixel):

* real and simulated depth in one shared colour range (metres, labelled colour bar), invalid
  pixels black;
* the difference sim - real in mm with a diverging map and a symmetric range (colour bar),
  on the pixels of the compare region valid in both; black where only one of them (or
  neither) has depth in the region, grey outside the region (not compared).
"""

from __future__ import annotations

import html
from pathlib import Path

import numpy as np

from ddsgen.atomic import atomic_path, atomic_write_text

DEPTH_CMAP = "viridis"
DIFF_CMAP = "RdBu_r"
OUTSIDE_GREY = 0.55
GAP_PX, TOP_PX, BAR_PX = 12, 44, 70
DPI = 100


def depth_range(*depths: np.ndarray) -> tuple[float, float]:
    """Shared colour range (m): the 1st-99th percentile of the valid depth of all images, rounded to cm."""
    values = np.concatenate([np.asarray(d)[np.asarray(d) > 0].ravel() for d in depths])
    if values.size == 0:
        return 0.0, 1.0
    low, high = np.percentile(values, [1, 99])
    low, high = np.floor(low * 100) / 100, np.ceil(high * 100) / 100
    return float(low), float(max(high, low + 0.01))


def difference_limit(difference_mm: np.ndarray) -> float:
    """Symmetric range of the difference map (mm): the 95th percentile of |diff|, within 5-100 mm, rounded."""
    if difference_mm.size == 0:
        return 10.0
    return float(np.clip(np.ceil(np.percentile(np.abs(difference_mm), 95) / 5.0) * 5.0, 5.0, 100.0))


def side_by_side(path: str | Path, title: str, real_m: np.ndarray, sim_m: np.ndarray, sim_valid: np.ndarray,
                 region: np.ndarray, patches: np.ndarray | None = None) -> dict:  # fmt: skip
    """Write the real | simulated | difference picture of one frame (PNG, atomic).

    Args:
        real_m, sim_m: float32 (H, W) depth in metres, 0 = invalid (full frames).
        sim_valid: bool (H, W); region: bool (H, W) the compare region.
        patches: bool (H, W) local patches (:mod:`ddsgen.realscan.local_patches`), outlined on the difference, or None.

    Returns:
        ``{"path", "depth_range_m", "difference_limit_mm"}``.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    real = np.asarray(real_m, dtype=np.float64)
    sim = np.where(np.asarray(sim_valid, bool), np.asarray(sim_m, dtype=np.float64), 0.0)
    region = np.asarray(region, bool)
    height, width = real.shape
    low, high = depth_range(real, sim)
    depth_norm = plt.Normalize(low, high)
    depth_cmap = plt.get_cmap(DEPTH_CMAP)

    def colour_depth(depth):
        rgb = depth_cmap(depth_norm(depth))[..., :3]
        rgb[depth <= 0] = 0.0
        return rgb

    both = region & (real > 0) & (sim > 0)
    diff_mm = (sim - real) * 1000.0
    limit = difference_limit(diff_mm[both])
    diff_norm = plt.Normalize(-limit, limit)
    diff_rgb = np.full((height, width, 3), OUTSIDE_GREY)
    diff_rgb[region] = 0.0
    diff_rgb[both] = plt.get_cmap(DIFF_CMAP)(diff_norm(diff_mm[both]))[:, :3]

    fig_w, fig_h = 3 * width + 4 * GAP_PX, height + TOP_PX + BAR_PX
    fig = plt.figure(figsize=(fig_w / DPI, fig_h / DPI), dpi=DPI)
    fig.suptitle(title, fontsize=10, y=1 - 4 / fig_h, va="top")
    panels = (("real", colour_depth(real)), ("simulated", colour_depth(sim)),
              (f"difference sim - real ({int(both.sum())} px of the compare region valid in both)", diff_rgb))  # fmt: skip
    for i, (label, image) in enumerate(panels):
        left = GAP_PX + i * (width + GAP_PX)
        ax = fig.add_axes([left / fig_w, BAR_PX / fig_h, width / fig_w, height / fig_h])
        ax.imshow(image, interpolation="nearest")
        if i == 2 and patches is not None and np.any(patches):
            ax.contour(np.asarray(patches, float), levels=[0.5], colors="k", linewidths=0.8)
        ax.set_title(label, fontsize=9, pad=3)
        ax.set_xticks([])
        ax.set_yticks([])
    bar_y, bar_h = 36 / fig_h, 10 / fig_h
    cax = fig.add_axes([GAP_PX / fig_w, bar_y, (2 * width + GAP_PX) / fig_w, bar_h])
    bar = fig.colorbar(plt.cm.ScalarMappable(norm=depth_norm, cmap=depth_cmap), cax=cax, orientation="horizontal")
    bar.set_label("depth (m); black = no depth", fontsize=8)
    bar.ax.tick_params(labelsize=7)
    cax = fig.add_axes([(GAP_PX + 2 * (width + GAP_PX)) / fig_w, bar_y, width / fig_w, bar_h])
    bar = fig.colorbar(plt.cm.ScalarMappable(norm=diff_norm, cmap=DIFF_CMAP), cax=cax, orientation="horizontal")
    bar.set_label("sim - real (mm); black = depth in one only; grey = not compared"
                  + ("; black lines: local patches" if patches is not None and np.any(patches) else ""), fontsize=8)
    bar.ax.tick_params(labelsize=7)
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=DPI)
    plt.close(fig)
    return {"path": path, "depth_range_m": [low, high], "difference_limit_mm": limit}


def write_index(folder: str | Path, title: str, summary_text: str, pictures: list[tuple[str, str]],
                plots: list[str],
                plots_heading: str = "Binned errors and valid rates; residual maps") -> Path:  # fmt: skip
    """``folder/index.html``: the summary table, the plots and every side-by-side picture.

    Args:
        summary_text: the plain-text table (shown preformatted).
        pictures: (frame name, picture path relative to ``folder``) per frame (none: no frames section).
        plots: plot paths relative to ``folder``, under ``plots_heading``.
    """
    esc = html.escape
    parts = [f"<!doctype html>\n<html><head><meta charset='utf-8'><title>{esc(title)}</title>",
             "<style>body{font-family:sans-serif;margin:1em} img{max-width:none;display:block;margin:.3em 0 1.5em}"
             " pre{background:#f4f4f4;padding:.6em;overflow-x:auto}</style></head><body>",
             f"<h1>{esc(title)}</h1>", f"<pre>{esc(summary_text)}</pre>",
             f"<h2>{esc(plots_heading)}</h2>"]  # fmt: skip
    parts += [f"<img src='{esc(p)}' alt='{esc(p)}'>" for p in plots]
    if pictures:
        parts.append("<h2>Frames: real | simulated | difference (full resolution)</h2>")
    for name, picture in pictures:
        parts.append(f"<h3>{esc(name)}</h3><img src='{esc(picture)}' alt='{esc(name)}'>")
    parts.append("</body></html>\n")
    path = Path(folder) / "index.html"
    atomic_write_text(path, "\n".join(parts))
    return path
