"""The unpaired fit against hidden devices it does not model: depth written by an independent measurement model.

``tests/independent_sensor.py`` turns the ray-cast clean depth into depth with Gaussian disparity noise, a disparity
quantum and an optional effect, and nothing else: no dots, no matcher, no clean-up, no corner fall-off. Each hidden
device here is that model with its own noise, quantum and effect. Per device:

1. 12 target frames of the device on the tests' scene list (``tests/diagnose_scenes.yaml``), depth only, are given to
   ``run_unpaired_fit`` of the stock sensor, which renders the built-in default scene list: other scenes than the
   targets';
2. 6 check frames of the device (other views of the tests' list, with their poses) judge the stock and the fitted
   preset by the paired gap (:func:`ddsgen.realscan.gap.gap`), which the unpaired fit never sees.

Prints per device ``bench: unpaired_blind_<device>_gap_ratio`` (fitted / stock paired gap on the check frames: the
fit must never make a preset worse, <= 1.05 where nothing identifiable differs, e.g. ``offset``, a global disparity
offset that unpaired depth cannot see), ``..._stock_gap_mm``, ``..._fitted_gap_mm``, ``..._written`` (1 when the
fitted values were written, 0 when the held-out judgement kept the input's) and ``..._s``; then the median and worst
ratio over the devices.

``--draws N`` adds N devices drawn at random (seeded): noise 0.02-0.15 px, 2, 4 or 8 steps per px, and nothing, an
edge dropout of 1-4 px or a disparity offset of -0.4..0.4 px.

Usage: python bench/bench_unpaired_blind.py [--devices NAME ...] [--draws N] [--size W H]
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

from ddsgen.fit.unpaired.run import run_unpaired_fit  # noqa: E402
from ddsgen.io.scanfolder import read_scan_folder  # noqa: E402
from ddsgen.preset import load_preset, save_preset  # noqa: E402
from ddsgen.realscan.gap import gap  # noqa: E402
from ddsgen.realscan.simulate import prepare_frames  # noqa: E402
from ddsgen.runner import render_dataset  # noqa: E402
from ddsgen.sensor.depth_sensor import DepthSensor  # noqa: E402
from effects_geometry import small_preset  # noqa: E402
from independent_sensor import remeasure_folder  # noqa: E402

SCENES = ROOT / "tests" / "diagnose_scenes.yaml"
TARGETS, CHECKS = 12, 6
#: device -> (disparity noise px, steps per px, hidden effect or None), in the independent model's terms.
DEVICES = {
    "noisy_coarse": (0.12, 4, {"name": "edge_dropout", "width_px": 2.0}),
    "quiet_fine": (0.03, 8, None),
    "offset": (0.05, 8, {"name": "disparity_offset", "offset_px": 0.3}),
}


def drawn_device(draw: int) -> tuple:
    """A hidden device drawn at random (seeded by ``draw``), in the independent model's terms (see :data:`DEVICES`)."""
    import numpy as np

    rng = np.random.default_rng([2026, draw])
    kind = rng.integers(3)
    effect = (None, {"name": "edge_dropout", "width_px": float(rng.uniform(1.0, 4.0))},
              {"name": "disparity_offset", "offset_px": float(rng.uniform(-0.4, 0.4))})[kind]  # fmt: skip
    return float(rng.uniform(0.02, 0.15)), int(rng.choice([2, 4, 8])), effect


def bench(name: str, value: float, unit: str = "") -> None:
    print(f"bench: {name} {value:.4g} {unit}".rstrip(), flush=True)


def device_folder(root: Path, stock_path: Path, name: str, frames: int, seed: int, device) -> Path:
    """``frames`` frames of the tests' scene list measured by the hidden ``device`` (a scan folder with poses)."""
    noise_px, subpixel, effect = device
    folder = root / f"{name}_{seed}"
    render_dataset(str(stock_path), str(SCENES), frames, str(folder), workers=1, seed=seed, progress=False)
    stock = load_preset(stock_path)
    prepared = prepare_frames(stock, read_scan_folder(folder), progress=False)
    remeasure_folder(folder, prepared, stock.baseline_m, effect, seed=seed, noise_px=noise_px, subpixel=subpixel)
    return folder


def paired_gap(preset_path: Path, folder: Path) -> float:
    preset = load_preset(preset_path)
    frames = prepare_frames(preset, read_scan_folder(folder), progress=False)
    return gap(DepthSensor(preset), frames, seed=5, noise_floor=False).gap


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--devices", nargs="*", default=list(DEVICES), choices=list(DEVICES))
    parser.add_argument("--draws", type=int, default=0)
    parser.add_argument("--size", type=int, nargs=2, default=(320, 240), metavar=("W", "H"))
    args = parser.parse_args()
    devices = {name: DEVICES[name] for name in args.devices}
    devices.update({f"draw{k}": drawn_device(k) for k in range(args.draws)})
    ratios = {}
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        stock_path = root / "stock.yaml"
        # Not registered: the independent model measures in the IR camera's own image.
        save_preset(small_preset(*args.size, registration_ir_offset_m=0.0, registration_shift_px=0.0), stock_path)
        for i, (name, device) in enumerate(devices.items()):
            print(f"# {name}: noise {device[0]:.3f} px, 1/{device[1]} px, effect {device[2]}", flush=True)
            targets = device_folder(root, stock_path, name, TARGETS, 31 + 2 * i, device)
            checks = device_folder(root, stock_path, name, CHECKS, 32 + 2 * i, device)
            depth_only = root / f"{name}_depth"
            shutil.copytree(targets / "depth", depth_only, ignore=shutil.ignore_patterns("*.exr"))
            start = time.perf_counter()
            fitted = root / f"{name}_fitted.yaml"
            report = run_unpaired_fit(str(stock_path), depth_only, out=fitted, report_dir=root / f"{name}_report",
                                      progress=False)  # fmt: skip
            seconds = time.perf_counter() - start
            stock_gap, fitted_gap = paired_gap(stock_path, checks), paired_gap(fitted, checks)
            ratios[name] = fitted_gap / stock_gap
            bench(f"unpaired_blind_{name}_stock_gap_mm", stock_gap, "mm")
            bench(f"unpaired_blind_{name}_fitted_gap_mm", fitted_gap, "mm")
            bench(f"unpaired_blind_{name}_gap_ratio", ratios[name])
            bench(f"unpaired_blind_{name}_written", float(report.get("written") == "fitted"))
            bench(f"unpaired_blind_{name}_s", seconds, "s")
    bench("unpaired_blind_median_gap_ratio", statistics.median(ratios.values()))
    bench("unpaired_blind_worst_gap_ratio", max(ratios.values()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
