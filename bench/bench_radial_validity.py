"""Real and rendered kinect_v1 frames side by side with their validity by image radius: docs/radial_validity.png.

    python bench/bench_radial_validity.py [--seed 11] [--frames 16] [--out docs/radial_validity.png]

Top row: real frames held out of tuning (IC-BIN seq3, the LineMOD cat, the raw NYU frame) and two renders of the
built-in scene list (kinect_v1), invalid pixels white. Bottom: the valid share by ring of the half-diagonal, every real
frame (grey band: their range) against the mean of the renders, over the whole image and inside each frame's output
window (ddsgen.depth_statistics.radial_valid_profile's ``in_window``: the empty border bands of a device, which cut
through the corners, are its window and are measured apart).
"""

import argparse
import sys
import tempfile
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from ddsgen.depth_statistics import RADIAL_RING_EDGES, corner_valid_share, radial_valid_profile  # noqa: E402
from ddsgen.runner import render_dataset  # noqa: E402
from tests.realframes import SHARED, real_frames  # noqa: E402


def render(preset_path: Path, frames: int, seed: int) -> list[np.ndarray]:
    """(480, 640) depth in metres of the first ``frames`` frames of the built-in list."""
    out = Path(tempfile.mkdtemp(prefix="radial_"))
    render_dataset(str(preset_path), None, frames, out, workers=1, seed=seed, progress=False)
    return [cv2.imread(str(p), cv2.IMREAD_UNCHANGED) / 1000.0 for p in sorted((out / "depth").glob("*.png"))]


def main() -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    parser = argparse.ArgumentParser()
    parser.add_argument("--seed", type=int, default=11)
    parser.add_argument("--frames", type=int, default=16)
    parser.add_argument("--out", type=Path, default=ROOT / "docs" / "radial_validity.png")
    args = parser.parse_args()

    if not (SHARED / "linemod_bop").is_dir():
        print(f"# skipped: the real frames ({SHARED}) are absent")
        return
    real = real_frames()
    renders = {"kinect_v1": render(ROOT / "presets" / "kinect_v1.yaml", args.frames, args.seed)}

    shown = [("real: IC-BIN seq3 0002", real["icbin_seq3_0002"][0]), ("real: LineMOD cat", real["linemod_cat"][0]),
             ("real: NYU raw", real["nyu_raw"][0]), (f"kinect_v1, seed {args.seed} frame 0", renders["kinect_v1"][0]),
             (f"kinect_v1, seed {args.seed} frame 1", renders["kinect_v1"][1])]  # fmt: skip
    figure = plt.figure(figsize=(17, 7.5))
    for i, (title, depth) in enumerate(shown):
        axis = figure.add_subplot(2, len(shown), i + 1)
        shown_depth = np.where(depth > 0, depth, np.nan)
        axis.imshow(shown_depth, cmap="viridis", vmin=np.nanpercentile(shown_depth, 2),
                    vmax=np.nanpercentile(shown_depth, 98))  # fmt: skip
        axis.set_title(title, fontsize=9)
        axis.axis("off")
    centres = [0.15, 0.4, 0.6, 0.775, 0.925]
    rendered = renders["kinect_v1"]
    for panel, in_window in ((3, False), (4, True)):  # bottom row: the whole image, then each frame's output window
        axis = figure.add_subplot(2, 2, panel)
        profiles = np.array([radial_valid_profile(depth > 0, in_window=in_window) for depth, _ in real.values()])
        axis.fill_between(centres, profiles.min(0), profiles.max(0), color="0.85", label="real frames: range")
        for profile in profiles:
            axis.plot(centres, profile, color="0.6", lw=0.8, marker=".")
        mean = np.mean([radial_valid_profile(depth > 0, in_window=in_window) for depth in rendered], axis=0)
        axis.plot(centres, mean, color="tab:red", lw=2.2, marker="o",
                  label=f"kinect_v1: mean of {args.frames} renders, seed {args.seed}")  # fmt: skip
        axis.set_xticks(centres, [f"{a:g}-{b:g}" if np.isfinite(b) else f">= {a:g}"
                                  for a, b in zip(RADIAL_RING_EDGES, RADIAL_RING_EDGES[1:])])  # fmt: skip
        axis.set_xlabel("distance from the image centre / half-diagonal")
        axis.set_ylabel("valid share")
        axis.set_title("inside each frame's output window (its empty border bands left out)" if in_window else
                       "whole image (device border bands included)", fontsize=9)  # fmt: skip
        axis.set_ylim(0, 1.02)
        axis.legend(loc="lower left", fontsize=9)
    figure.tight_layout()
    figure.savefig(args.out, dpi=80)
    print(f"wrote {args.out}")

    def corner_losses(depths, in_window):
        return [whole - corner for corner, whole in (corner_valid_share(d > 0, in_window=in_window) for d in depths)]

    for name, depths in (*((f"real {key}", [frame[0]]) for key, frame in real.items()), *renders.items()):
        for in_window in (False, True):
            rings = np.mean([radial_valid_profile(depth > 0, in_window=in_window) for depth in depths], axis=0)
            losses = corner_losses(depths, in_window)
            print(f"{name:28s} {'window' if in_window else 'whole '} rings {' / '.join(f'{r:.3f}' for r in rings)}"
                  f"   minus corner {min(losses):.2f}-{max(losses):.2f} (median {np.median(losses):.2f})")
    # Against issue #67's targets, inside each frame's output window (the border bands are the device's window,
    # measured apart): the renders' outer ring within the real frames' range, each render's corner loss within it.
    real_depths = [frame[0] for frame in real.values()]
    real_outer = [radial_valid_profile(d > 0, in_window=True)[-1] for d in real_depths]
    real_loss = corner_losses(real_depths, True)
    outer = float(np.mean([radial_valid_profile(depth > 0, in_window=True)[-1] for depth in rendered]))
    outside = sum(not min(real_loss) <= loss <= max(real_loss) for loss in corner_losses(rendered, True))
    print(f"bench: window_outer_ring_valid_share {outer:.3f} share (real {min(real_outer):.2f}-{max(real_outer):.2f})")
    print(f"bench: frames_window_corner_loss_outside_real_range {outside} frames (of {len(rendered)}; real "
          f"{min(real_loss):.2f}-{max(real_loss):.2f}; target 0)")

if __name__ == "__main__":
    main()
