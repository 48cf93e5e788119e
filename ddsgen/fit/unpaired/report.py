"""The unpaired fit's report: feature distributions before/after, patches side by side, JSON.

Files written into the report folder (each atomically):

* ``distributions.png``: per depth bin, the |second difference| histograms of the disparity
  proxy (real, stock preset, fitted preset); the isolated-dropout rate by depth; the valid
  share by image radius.
* ``patches.png``: depth patches of real frames next to patches of the stock and fitted
  renders (not the same scenes: unpaired), each in its own colour range, invalid black.
* ``frames.png``: whole frames, real next to stock and fitted renders (the same fit scene in
  both sim columns), invalid black: hole structure, corners and left border at a glance.
* ``profiles.png``: per fitted key, its search objective over the key's range with the other
  keys at their fitted values; the fitted value, and shaded the scene-content interval
  (:mod:`.spread`: values the frames cannot tell from it). A flat panel is a key the frames
  do not determine.
* ``unpaired_report.json``: fitted values with bootstrap uncertainties, distances before and
  after, feature summaries, the hole/validity/quantisation statistics of
  :mod:`ddsgen.depth_statistics` (median over frames) for real, stock and fitted renders, and (with f b) their
  flat roughness by depth, pooled over the frames (:func:`ddsgen.surface_roughness.flat_roughness_by_depth`).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ddsgen.atomic import atomic_path, atomic_write_text
from ddsgen.depth_statistics import STATISTIC_LABELS, realism_statistics
from ddsgen.fit.unpaired.features import (
    DEPTH_EDGES,
    ISOLATED_CLASSES,
    NOISE_BIN_PX,
    RADIUS_EDGES,
    summary,
)
from ddsgen.fit.unpaired.parameters import UNPAIRED_PARAMETERS
from ddsgen.surface_roughness import (
    flat_residuals_by_depth,
    pooled_flat_roughness,
    surface_residuals,
)

COLOURS = {"real": "black", "stock": "tab:orange", "fitted": "tab:blue"}
PATCH_PX = 64
STATISTIC_KEYS = tuple(STATISTIC_LABELS)


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(fig, path: Path) -> None:
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=80, format="png")
    _plt().close(fig)


def median_statistics(depths: list[np.ndarray], resolution_m: float, disparity_fb: float | None = None) -> dict:
    """Median over frames of :func:`~ddsgen.depth_statistics.realism_statistics` (None-safe; ``disparity_fb``:
    f b (px m) for the roughness statistics, then also ``"flat_roughness_by_depth"``: the rows of
    :func:`~ddsgen.surface_roughness.flat_roughness_by_depth` pooled over the frames)."""
    residuals = [surface_residuals(d, disparity_fb, d > 0) for d in depths] if disparity_fb else [None] * len(depths)
    rows = [realism_statistics(d, resolution_m=resolution_m, disparity_fb=disparity_fb, residuals=r)
            for d, r in zip(depths, residuals)]  # fmt: skip
    out = {}
    for key in STATISTIC_KEYS:
        values = [r[key] for r in rows if r[key] is not None]
        out[key] = float(np.median(values)) if values else None
    if disparity_fb:
        out["flat_roughness_by_depth"] = pooled_flat_roughness(flat_residuals_by_depth(r) for r in residuals)
    return out


def plot_distributions(pooled: dict[str, dict], path: Path) -> None:
    """``pooled``: label ("real", "stock", "fitted") -> pooled features (:func:`.features.pool`)."""
    plt = _plt()
    n_depth = len(DEPTH_EDGES) - 1
    fig, axes = plt.subplots(1, n_depth + 2, figsize=(3.2 * (n_depth + 2), 3.2), constrained_layout=True)
    centres = np.arange(pooled["real"]["noise"].shape[-1] - 1) * NOISE_BIN_PX
    for d in range(n_depth):
        ax = axes[d]
        for label, f in pooled.items():
            hist = f["noise"][0, d, :-1].astype(float)
            if hist.sum():
                ax.step(centres, hist / hist.sum(), where="mid", color=COLOURS[label], label=label)
        ax.set_yscale("log")
        ax.set_title(f"|2nd diff.| {DEPTH_EDGES[d]:.1f}-{DEPTH_EDGES[d + 1]:.1f} m", fontsize=9)
        ax.set_xlabel("px of disparity")
    axes[0].legend(fontsize=8)
    mids = (DEPTH_EDGES[:-1] + DEPTH_EDGES[1:]) / 2
    for label, f in pooled.items():
        isolated = f["holes"][:, :, :ISOLATED_CLASSES].sum(axis=(0, 2))
        rate = np.where(f["valid"] > 0, 1e4 * isolated / np.maximum(f["valid"], 1), np.nan)
        axes[n_depth].plot(mids, rate, "o-", color=COLOURS[label], label=label)
        share = f["radius_valid"] / np.maximum(f["radius_all"], 1)
        axes[n_depth + 1].plot((RADIUS_EDGES[:-1] + RADIUS_EDGES[1:]) / 2, share, "o-", color=COLOURS[label])
    axes[n_depth].set(title="isolated dropouts by depth", xlabel="depth (m)", ylabel="px per 1e4 valid px")
    axes[n_depth + 1].set(title="valid share by image radius", xlabel="radius / half-diagonal", ylim=(0, 1))
    _save(fig, path)


def plot_profiles(content: dict, path: Path) -> None:
    """One panel per fitted key: objective against value (``content``: :class:`.search.UnpairedResult` as a dict)."""
    from matplotlib import ticker

    plt = _plt()
    keys = list(content["profiles"])
    fig, axes = plt.subplots(1, len(keys), figsize=(3.0 * len(keys), 3.0), constrained_layout=True, squeeze=False)
    for ax, key in zip(axes[0], keys):
        profile, scene = content["profiles"][key], content["bootstrap"][key]["scene_content"]
        ax.plot(profile["points"], profile["distance"], "o-", color="black", ms=3)
        ax.axvspan(scene["low"], scene["high"], color=COLOURS["fitted"], alpha=0.15, label="fits as well")
        ax.axvline(content["after"][key], color=COLOURS["fitted"], label="fitted")
        ax.axvline(content["before"][key], color=COLOURS["stock"], ls="--", label="stock")
        if UNPAIRED_PARAMETERS.get(key) is not None and UNPAIRED_PARAMETERS[key].log:
            ax.set_xscale("log")
            ax.xaxis.set_minor_formatter(ticker.NullFormatter())  # decades only: minor labels overlap
        ax.set_title(key, fontsize=9)
        ax.set_xlabel("value")
    axes[0][0].set_ylabel("search objective")
    axes[0][0].legend(fontsize=7)
    _save(fig, path)


def _patch_origins(depth: np.ndarray, count: int, rng: np.random.Generator) -> list[tuple[int, int]]:
    """Patch corners on mostly valid surface with some holes (where the sensor's texture shows)."""
    h, w = depth.shape
    candidates = []
    for _ in range(200):
        y, x = int(rng.integers(0, h - PATCH_PX)), int(rng.integers(0, w - PATCH_PX))
        share = (depth[y:y + PATCH_PX, x:x + PATCH_PX] > 0).mean()
        if 0.8 <= share < 1.0:
            candidates.append((y, x))
    return candidates[:count] or [((h - PATCH_PX) // 2, (w - PATCH_PX) // 2)]


def plot_patches(columns: dict[str, list[np.ndarray]], path: Path, rows: int = 4, seed: int = 0) -> None:
    """``columns``: label -> depth frames; ``rows`` patches per column, from different frames."""
    plt = _plt()
    rng = np.random.default_rng(seed)
    cmap = plt.get_cmap("viridis").with_extremes(bad="black")  # invalid pixels black
    fig, axes = plt.subplots(rows, len(columns), figsize=(2.2 * len(columns), 2.2 * rows), squeeze=False)
    for c, (label, frames) in enumerate(columns.items()):
        for r in range(rows):
            depth = frames[r % len(frames)]
            y, x = _patch_origins(depth, 1, rng)[0] if min(depth.shape) > PATCH_PX else (0, 0)
            patch = depth[y:y + PATCH_PX, x:x + PATCH_PX].astype(float)
            valid = patch > 0
            lo, hi = np.percentile(patch[valid], [2, 98]) if valid.any() else (0.0, 1.0)
            shown = np.ma.masked_where(~valid, patch)
            axes[r, c].imshow(shown, cmap=cmap, vmin=lo, vmax=max(hi, lo + 1e-3), interpolation="nearest")
            axes[r, c].set_xticks([]), axes[r, c].set_yticks([])
            if r == 0:
                axes[r, c].set_title(label, fontsize=10)
    fig.tight_layout()
    _save(fig, path)


def plot_frames(columns: dict[str, list[np.ndarray]], path: Path, rows: int = 3) -> None:
    """``columns``: label -> depth frames; the first ``rows`` frames of each, whole, invalid black,
    each frame in its own 2-98 % depth range."""
    plt = _plt()
    cmap = plt.get_cmap("viridis").with_extremes(bad="black")
    fig, axes = plt.subplots(rows, len(columns), figsize=(3.6 * len(columns), 2.8 * rows), squeeze=False)
    for c, (label, frames) in enumerate(columns.items()):
        for r in range(rows):
            ax = axes[r, c]
            ax.set_xticks([]), ax.set_yticks([])
            if r >= len(frames):
                ax.axis("off")
                continue
            depth = frames[r].astype(float)
            valid = depth > 0
            lo, hi = np.percentile(depth[valid], [2, 98]) if valid.any() else (0.0, 1.0)
            ax.imshow(np.ma.masked_where(~valid, depth), cmap=cmap, vmin=lo, vmax=max(hi, lo + 1e-3),
                      interpolation="nearest")  # fmt: skip
            ax.set_title(f"{label}: {valid.mean():.0%} valid", fontsize=9)
    fig.tight_layout()
    _save(fig, path)


def write_report(folder: str | Path, content: dict, pooled: dict[str, dict], depths: dict[str, list[np.ndarray]],
                 resolution_m: float, seed: int = 0, disparity_fb: float | None = None) -> dict:  # fmt: skip
    """Write the report files; returns the JSON content (with the statistics added; ``disparity_fb``: f b in px m,
    for the roughness statistics)."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    content = dict(content)
    content["feature_summary"] = {label: summary(f) for label, f in pooled.items()}
    content["realism_statistics"] = {label: median_statistics(d, resolution_m, disparity_fb)
                                     for label, d in depths.items()}  # fmt: skip
    plot_distributions(pooled, folder / "distributions.png")
    plot_patches(depths, folder / "patches.png", seed=seed)
    plot_frames(depths, folder / "frames.png")
    plot_profiles(content, folder / "profiles.png")
    atomic_write_text(folder / "unpaired_report.json", json.dumps(content, indent=1, default=float) + "\n")
    return content
