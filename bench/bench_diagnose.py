"""Diagnosis speed benchmark (issue 15: "a 640 x 480 case of 8 frames in at most 2 minutes on 2 cores").

Renders 8 frames of tests/diagnose_scenes.yaml at 640 x 480 with a hidden effect (``--effect``, default a
0.3 px disparity offset), then times :func:`ddsgen.diagnose.diagnose` from the stock preset with the
command's default settings (``ddsgen diagnose`` without options) on 2 torch threads. Prints the diagnosis' own
lines, each prefixed with the wall time (s) at which it was reached, then `bench: NAME VALUE UNIT` lines:

  diagnose_640x480_8frames_s          wall time of the whole diagnosis (target 120 s on 2 cores)
  diagnose_640x480_8frames_cpu_s      its process CPU time
  diagnose_simulations_equivalent     that wall time in units of one simulation of the 8 frames measured in
                                      the same run (median of 3 passes; still follows the load of the moment)
  diagnose_front_ends                 sensor front ends computed (IR image + matching; cache hits not counted)
  diagnose_validity_stages            validity stages computed (one per simulation, front end cached or not);
                                      both counts are machine-independent: what the loop costs in work
  diagnose_named_first                1 when the hidden effect is named first (the answer must stay right)
  diagnose_load_average               the 1-minute load average at the end (timings on a loaded machine lie)

Usage: python bench/bench_diagnose.py [--effect NAME KEY=VALUE ...] [--threads N] [--screen-frames N] [--tile-px N]
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import tempfile
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

from ddsgen.diagnose import DiagnoseConfig, diagnose  # noqa: E402
from ddsgen.realscan.simulate import prepare_frames, simulate  # noqa: E402
from ddsgen.io.scanfolder import read_scan_folder  # noqa: E402
from ddsgen.preset import save_preset  # noqa: E402
from ddsgen.runner import render_dataset  # noqa: E402
from effects_geometry import small_preset  # noqa: E402

SCENES = ROOT / "tests" / "diagnose_scenes.yaml"
FRAMES = 8
TARGET_S = 120.0


def bench(name: str, value: float, unit: str = "") -> None:
    print(f"bench: {name} {value:.4g} {unit}".rstrip(), flush=True)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--effect", nargs="+", default=["disparity_offset", "offset_px=0.3"])
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--screen-frames", type=int, default=None,
                        help="DiagnoseConfig.screen_frames (0: no screening; default: the command's)")
    parser.add_argument("--tile-px", type=int, default=None,
                        help="DiagnoseConfig.tile_px (Adam steps of the base fit and refits on tiles; 0: whole frames)")
    args = parser.parse_args()
    effect = {"name": args.effect[0], **{k: float(v) for k, v in (a.split("=") for a in args.effect[1:])}}

    stock = small_preset(640, 480, subpixel_level=3)
    with tempfile.TemporaryDirectory() as tmp:
        truth = stock.replace(effects=[effect], emitted_intensity=stock.emitted_intensity * 1.15)
        save_preset(truth, Path(tmp) / "truth.yaml")
        render_dataset(str(Path(tmp) / "truth.yaml"), str(SCENES), FRAMES, str(Path(tmp) / "scans"), workers=1,
                       seed=11, progress=False)  # fmt: skip
        torch.set_num_threads(args.threads)
        frames = prepare_frames(stock, read_scan_folder(Path(tmp) / "scans"), progress=False)

    from ddsgen.diagnose.stage_cache import StageCache
    from ddsgen.sensor.depth_sensor import DepthSensor

    sensor = DepthSensor(stock)
    with torch.no_grad():
        simulate(sensor, frames[0], 0)  # warm-up: pattern and reference caches
        passes = []
        for _ in range(3):
            start = time.perf_counter()
            for f in frames:
                simulate(sensor, f, 0)
            passes.append(time.perf_counter() - start)
        one_pass = sorted(passes)[1]

    config = DiagnoseConfig()
    if args.tile_px is not None:
        config = dataclasses.replace(config, tile_px=args.tile_px or None)
    if args.screen_frames is not None:
        config = dataclasses.replace(config, screen_frames=args.screen_frames)
    log: list[str] = []
    wall, cpu = time.perf_counter(), time.process_time()

    def timed(line: str) -> None:  # each stage line with the wall time it was reached at: where the time goes
        log.append(f"{time.perf_counter() - wall:6.1f} s  {line}")

    cache = StageCache()  # counts the stages computed (what it serves is not counted)
    result = diagnose(stock, frames, config, echo=timed, stage_cache=cache)
    counts = cache.computed
    wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
    print("\n".join("# " + line for line in log), flush=True)
    bench("diagnose_640x480_8frames_s", wall, "s")
    bench("diagnose_640x480_8frames_vs_target", wall / TARGET_S, "x")
    bench("diagnose_640x480_8frames_cpu_s", cpu, "s")
    bench("diagnose_simulations_equivalent", wall / one_pass, "passes")
    bench("diagnose_front_ends", counts["front_end"])
    bench("diagnose_validity_stages", counts["validity_stage"])
    bench("diagnose_named_first", float(bool(result.steps) and result.steps[0].effect == effect["name"]))
    bench("diagnose_load_average", os.getloadavg()[0])
    return 0


if __name__ == "__main__":
    sys.exit(main())
