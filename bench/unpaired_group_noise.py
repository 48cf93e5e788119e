"""How far each feature group of the unpaired fit's held-out judgement moves between renders of one preset.

The held-out judgement of ``ddsgen fit --unpaired`` (:mod:`ddsgen.fit.unpaired.holdout`) compares feature distances
to the held-out real frames. This renders the preset's values through each registration reading the fit considers,
on the fit's own scene casts, with several noise seeds, and prints each group's distance per seed: a difference
between two presets smaller than the spread over seeds is not a difference.

Usage: python bench/unpaired_group_noise.py [REAL_DIR] [PRESET] [SEEDS]
(defaults: ../shared/data/icbin_primesense_unpaired, kinect_v1, 3; IC-BIN: about 4 min)
"""

from __future__ import annotations

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from ddsgen.fit.unpaired.device_window import choose_window_model  # noqa: E402
from ddsgen.fit.unpaired.features import frame_features  # noqa: E402
from ddsgen.fit.unpaired.holdout import judge, split_frames  # noqa: E402
from ddsgen.fit.unpaired.run import DEFAULT_SIM_FRAMES  # noqa: E402
from ddsgen.fit.unpaired.search import camera_for, render_depths  # noqa: E402
from ddsgen.preset import load_preset  # noqa: E402
from ddsgen.realscan.realfolder import read_depth_folder, round_like  # noqa: E402
from ddsgen.scene.scenelist import load_scene_list  # noqa: E402

GROUPS = ("noise", "holes", "radius", "grain", "total")


def main(real_dir: str, preset_ref: str, seeds: int) -> None:
    real = read_depth_folder(real_dir, 0.001)
    height, width = real[0].depth.shape
    stock = camera_for(load_preset(preset_ref), width, height)
    fb = stock.focal_px * stock.baseline_m
    features = [frame_features(f.depth, fb) for f in real]
    fit_indices, held_indices, kind = split_frames([f.name for f in real], 0)  # the fit's split at its default seed
    _, candidates = choose_window_model(stock, [real[i] for i in fit_indices], load_scene_list(None),
                                        DEFAULT_SIM_FRAMES, 0, False, reading="auto",
                                        real_features=[features[i] for i in fit_indices])  # fmt: skip
    resolution = max(f.resolution_m for f in real)
    held = [features[i] for i in held_indices]
    print(f"held out ({kind}): {[real[i].name for i in held_indices]}")
    for model in candidates:
        per_seed = []
        for seed in range(1, seeds + 1):
            rendered = [frame_features(round_like(d, resolution), fb)
                        for d in render_depths(model.camera, model.geometries, seed)]
            per_seed.append(judge(held, rendered, rendered)["terms"]["stock"])
        for group in GROUPS:
            values = [t[group] for t in per_seed]
            print(f"bench: unpaired_group_noise {model.name} {group} " + " ".join(f"{v:.4f}" for v in values)
                  + f" spread {max(values) - min(values):.4f}")


if __name__ == "__main__":
    arguments = sys.argv[1:]
    main(arguments[0] if arguments else str(ROOT.parent / "shared" / "data" / "icbin_primesense_unpaired"),
         arguments[1] if len(arguments) > 1 else "kinect_v1", int(arguments[2]) if len(arguments) > 2 else 3)
