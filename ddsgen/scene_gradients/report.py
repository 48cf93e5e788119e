"""The refinement report: per-frame pose changes and gaps (JSON) and real | before | after pictures."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ddsgen.atomic import atomic_path, atomic_write_text
from ddsgen.realscan.gap_report import round_or_none


def frame_summary(refinement) -> dict:
    """JSON-ready summary of a :class:`~ddsgen.scene_gradients.scan.FrameRefinement`."""
    r = refinement.result
    summary = {
        "frame": refinement.name, "crop": list(refinement.crop),
        "gap_before_mm": r.gap_before_mm, "gap_after_mm": r.gap_after_mm, "gap_optimised_mm": r.gap_optimised_mm,
        "kept_start": bool(r.kept_start),
        "heldout_gap_before_mm": round_or_none(r.heldout_gap_before_mm),
        "heldout_gap_after_mm": round_or_none(r.heldout_gap_after_mm),
        "objects": refinement.object_changes(),
        "loss_mm": [round(h["loss_mm"], 4) for h in r.history],
    }  # fmt: skip
    if refinement.plane_fitted:
        k = len(refinement.object_ids)
        n0, n1 = r.initial[k][:3, 2], r.refined[k][:3, 2]
        shift = float(n1 @ r.refined[k][:3, 3] - n0 @ r.initial[k][:3, 3]) * 1000.0
        summary["support_plane"] = {"tilt_deg": round(float(np.degrees(np.arccos(np.clip(n0 @ n1, -1, 1)))), 4),
                                    "offset_mm": round(shift, 4)}  # fmt: skip
    return summary


def save_side_by_side(refinement, path: Path) -> None:
    """PNG: real | simulated at the initial poses | simulated at the refined poses (same depth scale, m)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    r = refinement.result
    images = [refinement.real_depth, r.depth_before, r.depth_after]
    valid = np.concatenate([im[im > 0] for im in images]) if any((im > 0).any() for im in images) else np.ones(1)
    lo, hi = np.percentile(valid, [1, 99])
    fig, axes = plt.subplots(1, 3, figsize=(10, 3.6), constrained_layout=True)
    titles = ["real", f"before (gap {r.gap_before_mm:.1f} mm)", f"after (gap {r.gap_after_mm:.1f} mm)"]
    for ax, image, title in zip(axes, images, titles):
        shown = ax.imshow(np.where(image > 0, image, np.nan), vmin=lo, vmax=hi, cmap="viridis")
        ax.set_title(title, fontsize=9)
        ax.axis("off")
    fig.colorbar(shown, ax=axes, shrink=0.8, label="depth (m)")
    fig.suptitle(refinement.name, fontsize=10)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=80, format="png")
    plt.close(fig)


def write_report(refinements, report_dir: Path, settings: dict) -> Path:
    """``report_dir/refine_report.json`` and one ``<frame>.png`` per frame; returns the JSON's path."""
    report_dir = Path(report_dir)
    frames = []
    for refinement in refinements:
        picture = report_dir / (refinement.name.replace("/", "_") + ".png")
        save_side_by_side(refinement, picture)
        frames.append(dict(frame_summary(refinement), picture=picture.name))
    changes = [o for f in frames for o in f["objects"]]
    summary = {
        "settings": settings,
        "median_rotation_change_deg": float(np.median([o["rotation_deg"] for o in changes])) if changes else 0.0,
        "median_translation_change_mm": float(np.median([o["translation_mm"] for o in changes])) if changes else 0.0,
        "frames": frames,
    }  # fmt: skip
    path = report_dir / "refine_report.json"
    atomic_write_text(path, json.dumps(summary, indent=1, default=float) + "\n")
    return path
