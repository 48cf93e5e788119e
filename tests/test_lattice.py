"""The disparity quantum is measured from the real depth's levels (ddsgen.fit.lattice), confirmed on held-out pixels,
and a paired fit from a preset on another lattice writes the measured one."""

from __future__ import annotations

import json
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from ddsgen.fit.lattice import coarsest_coherent, level_coherences, measure_quantum

FX, BASELINE = 572.41, 0.075
CAT = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "linemod_bop"


def frame_on_lattice(level: int | None, seed: int, baseline: float = BASELINE, pixels: int = 4000):
    """A stand-in real frame: depth 0.6-2.5 m on the lattice z = f b / (k 2^-level) (None: continuous depth),
    rounded to the millimetre as a 16-bit PNG stores it."""
    rng = np.random.default_rng(seed)
    disparity = FX * baseline / rng.uniform(0.6, 2.5, pixels)
    if level is not None:
        disparity = np.round(disparity * 2**level) / 2**level
    depth = np.round(FX * baseline / disparity * 1000.0) / 1000.0
    ones = torch.ones(pixels, dtype=torch.bool)
    return SimpleNamespace(real_depth=torch.tensor(depth, dtype=torch.float32), region=ones, real_valid=ones,
                           full_intrinsics=None, intrinsics=SimpleNamespace(fx=FX))  # fmt: skip


def test_the_coarsest_coherent_level_is_the_devices_quantum_whatever_the_baseline_within_its_bounds():
    """Depth on a 1/8 px lattice is coherent at 1/8 (and any finer step, which holds its levels), not at 1/4: the
    measured level is 3. The search over b finds the lattice when the device's b is 2 % off the start value."""
    for true_level in (2, 3):
        coherences = level_coherences([frame_on_lattice(true_level, seed=1, baseline=0.0735)], BASELINE)
        assert coarsest_coherent(coherences) == true_level, coherences
        assert coherences[true_level - 1] < 0.2 and coherences[true_level] > 0.7, coherences


def test_continuous_depth_shows_no_lattice():
    assert coarsest_coherent(level_coherences([frame_on_lattice(None, seed=2)], BASELINE)) is None


def test_the_measured_level_is_used_only_when_the_held_out_frames_agree():
    fit = [frame_on_lattice(3, seed=3)]
    agreed = measure_quantum(fit, [frame_on_lattice(3, seed=4)], preset_level=2, baseline_m=BASELINE)
    assert agreed["changed"] and agreed["level"] == 3 and "1/8 px" in agreed["reason"]
    disagreed = measure_quantum(fit, [frame_on_lattice(2, seed=4)], preset_level=2, baseline_m=BASELINE)
    assert not disagreed["changed"] and disagreed["level"] == 2 and "do not agree" in disagreed["reason"]
    same = measure_quantum(fit, [frame_on_lattice(3, seed=4)], preset_level=3, baseline_m=BASELINE)
    assert not same["changed"] and same["level"] == 3
    alone = measure_quantum(fit, [], preset_level=2, baseline_m=BASELINE)
    assert not alone["changed"] and "no held-out frame" in alone["reason"]


@pytest.mark.skipif(not (CAT / "test" / "000006" / "scene_gt.json").is_file(), reason="real LineMOD data absent")
def test_a_fit_from_the_paper_preset_writes_the_real_cats_1_8_px_quantum(tmp_path):
    """The real cat's depth levels lie 2.92 mm apart at 1 m: Kinect V1's 1/8 px, where kinect_v1_paper renders 1/4.
    The fit measures it on its half of the frame, the other half confirms it, and the written preset has it."""
    from ddsgen.cli import main
    from ddsgen.preset import load_preset

    out = tmp_path / "fitted.yaml"
    assert main(["fit", "kinect_v1_paper", str(CAT), "--steps", "2", "--out", str(out), "--quiet",
                 "--threads", "1"]) == 0  # fmt: skip
    quantum = json.loads((tmp_path / "fitted_report" / "fit_report.json").read_text())["disparity_quantum"]
    assert quantum["measured_fit"] == quantum["measured_held_out"] == 3
    assert quantum["changed"], quantum["reason"]
    assert load_preset(str(out)).subpixel_level == 3
    assert "disparity quantum: measured from the depth levels: 1/8 px" in out.read_text()
