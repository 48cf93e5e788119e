"""Diagnose's blind suite: hidden effects written by an independent measurement model, diagnosed with the defaults.

The scans are not ddsgen's: ``tests/independent_sensor.py`` turns the ray-cast clean depth of 9 frames of
``tests/diagnose_scenes.yaml`` (320 x 240) into depth with its own Gaussian disparity noise and 1/8-px quantum, and
writes one hidden effect per case in its own terms -- a division-model lens warp (the library's warp is Brown's), a
Brown distortion that also displaces the dots, a disparity offset, a dropout beyond an angle measured at the
projector (the library's is at the camera), an edge dropout with its own edge rule, nothing, and a row bias the
library does not hold. Each case is diagnosed from the stock sensor with the command's default settings
(``ddsgen diagnose`` without options), so the defaults and any second effect are what is measured. Prints per case
the diagnosis' steps and then ``bench:`` lines:

  blind_<case>_named_right     1 when the first named effect is the expected one (null: nothing named; row bias:
                               a disparity term along the row and no library effect claiming > 20 %)
  blind_<case>_shrink_pct      held-out gap beyond the floor removed by the accepted steps (%)
  blind_<case>_shrink_beyond_null_pct  the same, of the part beyond the null case's gap (with null run): the
                               independent model differs from ddsgen's stock sensor without any hidden effect too
                               (no corner fall-off, its own left border), and no candidate may remove that part
  blind_<case>_s               wall time of the diagnosis
  blind_library_right          library cases named right, of 5
  blind_library_median_shrink_pct  median shrink over the library cases (target >= 50 % each)

``--size 640 480 --frames 8`` runs the issue's conditions (each case then takes a few minutes; the lens warp's
strength is the same in pixels at half the lambda).

Usage: python bench/bench_diagnose_blind.py [--cases NAME ...] [--threads N] [--size W H] [--frames N]
"""

from __future__ import annotations

import argparse
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

from ddsgen.diagnose import DiagnoseConfig, diagnose  # noqa: E402
from ddsgen.io.scanfolder import read_scan_folder  # noqa: E402
from ddsgen.preset import save_preset  # noqa: E402
from ddsgen.realscan.simulate import prepare_frames  # noqa: E402
from ddsgen.runner import render_dataset  # noqa: E402
from effects_geometry import small_preset  # noqa: E402
from independent_sensor import remeasure_folder  # noqa: E402
from torch_threads import torch_threads  # noqa: E402

SCENES = ROOT / "tests" / "diagnose_scenes.yaml"
SIZE, FRAMES = (320, 240), 9
#: Scene seed and measurement seed: neither is a seed the tests' blind cases use (41 and 5).
SCENE_SEED, MEASURE_SEED = 97, 13
#: case -> (the hidden effect in the independent model's terms, the library effect that should be named first).
CASES = {
    "lens_warp": ({"name": "lens_warp", "division_lambda": -0.11}, "lens_warp"),
    "lens_distortion": ({"name": "lens_distortion", "k1": -0.025}, "lens_distortion"),
    "disparity_offset": ({"name": "disparity_offset", "offset_px": -0.3}, "disparity_offset"),
    "grazing_dropout_projector": ({"name": "grazing_dropout_projector", "angle_deg": 63.0}, "grazing_dropout"),
    "edge_dropout": ({"name": "edge_dropout", "width_px": 2.5}, "edge_dropout"),
    "null": (None, None),
    "row_bias": ({"name": "row_bias", "amplitude_px": -0.35}, "axis_disparity_term:row"),
}
LIBRARY = ("lens_warp", "lens_distortion", "disparity_offset", "grazing_dropout_projector", "edge_dropout")


def bench(name: str, value: float, unit: str = "") -> None:
    print(f"bench: {name} {value:.4g} {unit}".rstrip(), flush=True)


def stock(size: tuple[int, int] = SIZE):
    """The blind suite's stock sensor: not registered (the independent model measures in the IR camera's image),
    no narrow-gap fill (it leaves every projector-shadow pixel empty)."""
    return small_preset(*size, subpixel_level=3, registration_ir_offset_m=0.0, registration_shift_px=0.0,
                        cleanup_fill_width_px=0)  # fmt: skip


def named_right(case: str, expected: str | None, result) -> bool:
    if expected is None:
        return not result.steps
    if case == "row_bias":
        effects = [s.effect for s in result.steps]
        claims = all(s.gap_after > 0.8 * s.gap_before for s in result.steps if ":" not in s.effect)
        return expected in effects and claims
    return bool(result.steps) and result.steps[0].effect == expected


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", nargs="+", default=list(CASES), choices=list(CASES))
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--size", type=int, nargs=2, default=SIZE, metavar=("W", "H"))
    parser.add_argument("--frames", type=int, default=FRAMES)
    args = parser.parse_args()
    size = tuple(args.size)
    # The warp's displacement in pixels grows with the focal length: the same strength in pixels at any size.
    warp_scale = SIZE[0] / size[0]
    shrinks, right, gaps = {}, {}, {}
    with tempfile.TemporaryDirectory() as tmp, torch_threads(args.threads):
        root = Path(tmp)
        save_preset(stock(size), root / "stock.yaml")
        render_dataset(str(root / "stock.yaml"), str(SCENES), args.frames, str(root / "scenes"), workers=1,
                       seed=SCENE_SEED, progress=False)  # fmt: skip
        geometry = prepare_frames(stock(size), read_scan_folder(root / "scenes"), progress=False)
        for case in args.cases:
            effect, expected = CASES[case]
            if effect and "division_lambda" in effect:
                effect = dict(effect, division_lambda=effect["division_lambda"] * warp_scale)
            folder = root / case
            shutil.copytree(root / "scenes", folder)
            remeasure_folder(folder, geometry, stock(size).baseline_m, effect, seed=MEASURE_SEED)
            (folder / "run.json").unlink()  # another device's scans: only the annotated objects are known
            frames = prepare_frames(stock(size), read_scan_folder(folder), progress=False)
            start = time.perf_counter()
            result = diagnose(stock(size), frames, DiagnoseConfig(), echo=lambda line: print(f"  {case}: {line}"))
            seconds = time.perf_counter() - start
            shrink = 100.0 * (1.0 - result.final_gap / result.baseline_gap) if result.baseline_gap > 0 else 0.0
            right[case] = named_right(case, expected, result)
            shrinks[case] = shrink
            gaps[case] = (result.baseline_gap, result.final_gap)
            bench(f"blind_{case}_named_right", float(right[case]))
            bench(f"blind_{case}_shrink_pct", shrink, "%")
            bench(f"blind_{case}_s", seconds, "s")
    if "null" in gaps:
        floor = gaps["null"][0]  # what remains beyond the floor when nothing is hidden
        for case, (before, after) in gaps.items():
            if case != "null" and before > floor:
                bench(f"blind_{case}_shrink_beyond_null_pct", 100.0 * (before - after) / (before - floor), "%")
    library = [c for c in LIBRARY if c in shrinks]
    if library:
        bench("blind_library_right", sum(right[c] for c in library), f"of {len(library)}")
        bench("blind_library_median_shrink_pct", statistics.median(shrinks[c] for c in library), "%")
    return 0


if __name__ == "__main__":
    sys.exit(main())
