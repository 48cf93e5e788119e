"""Matcher benchmark: speed against OpenCV StereoBM, peak memory, Middlebury bad-2.

Prints `bench: NAME VALUE UNIT` lines:
  stereobm_ms, matcher_fwd_ms, matcher_fwdbwd_ms      640x480, 101 disparities, 9x9, n_sub 2
  matcher_fwd_vs_stereobm, matcher_fwdbwd_vs_stereobm  median of per-repeat ratios, same run,
                                                      one thread for both (a render worker's
                                                      setting); the same with suffix _2threads
                                                      for 2 threads each (on a busy machine the
                                                      2-thread figures suffer from descheduled
                                                      OpenMP threads, torch's more than OpenCV's)
  matcher_first_call_s                                 first match() of a process (C kernel load,
                                                      torch.compile from the on-disk cache)
  matcher_peak_rss_mb_kinect_v1, _matterport_pro2      peak RSS of a fresh process running one
                                                      forward + backward (as in fitting)
  middlebury_bad2_{ddsgen,stereobm,sgbm} (%) and middlebury_density_* (%) on the Middlebury 2014
  Motorcycle pair in ../shared/data (skipped with a message if absent). A pixel with known
  ground truth is bad if its disparity is missing or off by more than 2 px.

The synthetic pair is Kinect-like: a dot pattern (~11 % of pixels lit, dots of 1-2 px,
Gaussian-blurred), shifted by a smooth disparity field (a tilted, gently curved surface),
in 10-bit IR counts with speckle-like multiplicative and additive read noise.
"""

from __future__ import annotations

import math
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import torch

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from ddsgen.sensor.matcher import integer_search_backend, match, stereo_reference_phases  # noqa: E402

REPEATS = 9
THREADS = int(os.environ.get("DDSGEN_BENCH_THREADS", "2"))  # for the peak-RSS children
MIDDLEBURY = ROOT.parent / "shared" / "data" / "middlebury2014_motorcycle_skimage"


def bench(name: str, value: float, unit: str) -> None:
    print(f"bench: {name} {value:.4g} {unit}", flush=True)


# ---------------------------------------------------------------------------------------
# A Kinect-like pair
# ---------------------------------------------------------------------------------------
def dot_pattern(height: int, width: int, rng: np.random.Generator) -> np.ndarray:
    """~11 % of pixels lit: single-pixel and 2x2 dots, blurred by a small PSF, in [0, 1]."""
    small = rng.random((height, width)) < 0.05
    big = cv2.dilate((rng.random((height, width)) < 0.02).astype(np.uint8), np.ones((2, 2), np.uint8)) > 0
    dots = (small | big).astype(np.float32) * rng.uniform(0.6, 1.0, (height, width)).astype(np.float32)
    return cv2.GaussianBlur(dots, (0, 0), 0.6)


def kinect_like_pair(height: int, width: int, d_min: float, d_max: float, n_sub: int, seed: int = 0):
    """(observed (H, W) counts, reference_phases (S, H, W + pad), pad, true disparity (H, W))."""
    rng = np.random.default_rng(seed)
    block = 11
    pad = int(math.ceil(d_max)) + block + 2
    reference = dot_pattern(height, width + pad + 4, rng)
    v, u = np.mgrid[0:height, 0:width].astype(np.float32)
    span = d_max - d_min
    disparity = d_min + span * (0.5 + 0.25 * (u / width - 0.5) + 0.15 * np.sin(v / 97.0) * np.cos(u / 131.0))
    disparity = np.clip(disparity, d_min + 1, d_max - 1).astype(np.float32)
    # observed(u) = R(u - d): reference column x + pad holds R(x)
    observed = cv2.remap(reference, u - disparity + pad, v, cv2.INTER_CUBIC)
    speckle = rng.gamma(4.54, 0.196, observed.shape) / (4.54 * 0.196)
    observed = 40.0 + 700.0 * observed * speckle + rng.normal(0.0, 3.0, observed.shape)
    observed = np.clip(observed, 0, 1023).astype(np.float32)
    steps = 2**n_sub
    vj, j = np.mgrid[0:height, 0 : width + pad].astype(np.float32)
    phases = np.stack([cv2.remap(reference, j - s / steps, vj, cv2.INTER_CUBIC) for s in range(steps)])
    return torch.from_numpy(observed), torch.from_numpy(40.0 + 700.0 * phases), pad, disparity


# ---------------------------------------------------------------------------------------
# Speed
# ---------------------------------------------------------------------------------------
def speed(threads: int, suffix: str) -> None:
    torch.set_num_threads(threads)
    cv2.setNumThreads(threads)
    d_min, d_max, block, n_sub, beta = 8.0, 108.0, 9, 2, 15.0  # 101 integer disparities
    observed, phases, pad, truth = kinect_like_pair(480, 640, d_min, d_max, n_sub)
    to8 = lambda a: np.clip(a / 4.0, 0, 255).astype(np.uint8)  # noqa: E731
    left, right = to8(observed.numpy()), to8(phases[0, :, pad:].numpy())
    bm = cv2.StereoBM_create(numDisparities=112, blockSize=block)

    def run_bm():
        t0 = time.perf_counter()
        bm.compute(left, right)
        return time.perf_counter() - t0

    def run_fwd():
        t0 = time.perf_counter()
        with torch.no_grad():
            result = match(observed, phases, pad, d_min, d_max, block, beta, n_sub, 64, 0.05)
        return time.perf_counter() - t0, result

    obs_grad = observed.clone().requires_grad_(True)
    beta_t = torch.tensor(beta, requires_grad=True)

    def run_fwdbwd():
        obs_grad.grad = None
        t0 = time.perf_counter()
        result = match(obs_grad, phases, pad, d_min, d_max, block, beta_t, n_sub, 64, 0.05)
        result.disparity.sum().backward()
        return time.perf_counter() - t0

    first, result = run_fwd()
    if not suffix:
        bench("matcher_first_call_s", first, "s")
    run_fwdbwd()
    run_bm()
    bm_t, fwd_t, both_t, r_fwd, r_both = [], [], [], [], []
    for _ in range(REPEATS):  # interleaved: load changes hit all three alike
        b = run_bm()
        f, result = run_fwd()
        fb = run_fwdbwd()
        b = min(b, run_bm())
        bm_t.append(b), fwd_t.append(f), both_t.append(fb)
        r_fwd.append(f / b), r_both.append(fb / b)
    bench("stereobm_ms" + suffix, 1e3 * statistics.median(bm_t), "ms")
    bench("matcher_fwd_ms" + suffix, 1e3 * statistics.median(fwd_t), "ms")
    bench("matcher_fwdbwd_ms" + suffix, 1e3 * statistics.median(both_t), "ms")
    bench("matcher_fwd_vs_stereobm" + suffix, statistics.median(r_fwd), "x")
    bench("matcher_fwdbwd_vs_stereobm" + suffix, statistics.median(r_both), "x")
    if not suffix:
        valid = result.valid.numpy()
        error = np.abs(result.disparity.numpy() - truth)[valid]
        bench("matcher_synthetic_valid", 100.0 * valid.mean(), "%")
        bench("matcher_synthetic_within_step", 100.0 * np.mean(error <= 2.0**-n_sub + 1e-6), "%")
    print(f"# integer search backend: {integer_search_backend()}, threads: {threads}", flush=True)


# ---------------------------------------------------------------------------------------
# Peak memory (fresh process per preset)
# ---------------------------------------------------------------------------------------
PRESETS = {  # W, H, f (px), baseline (m), z range (m), block, n_sub, beta
    "kinect_v1": (640, 480, 572.41, 0.075, 0.4, 4.0, 9, 2, 15.0),
    "matterport_pro2": (1280, 1024, 1075.43, 0.075, 0.4, 8.0, 11, 4, 25.0),
}


def peak_rss_child(name: str) -> None:
    import resource

    width, height, f, b, z_min, z_max, block, n_sub, beta = PRESETS[name]
    torch.set_num_threads(THREADS)
    d_min, d_max = f * b / z_max, f * b / z_min
    observed, phases, pad, _ = kinect_like_pair(height, width, d_min, d_max, n_sub)
    observed.requires_grad_(True)
    result = match(observed, phases, pad, d_min, d_max, block, beta, n_sub, 64, 0.05)
    result.disparity.sum().backward()
    assert torch.isfinite(observed.grad).all()
    print(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0)


def peak_rss() -> None:
    for name in PRESETS:
        out = subprocess.run([sys.executable, __file__, "--rss", name], capture_output=True, text=True, cwd=ROOT)
        if out.returncode != 0:
            print(f"# peak RSS {name} failed: {out.stderr.strip().splitlines()[-1:]}", flush=True)
            continue
        bench(f"matcher_peak_rss_mb_{name}", float(out.stdout.strip().splitlines()[-1]), "MB")


# ---------------------------------------------------------------------------------------
# Middlebury 2014 Motorcycle (quarter size, from scikit-image)
# ---------------------------------------------------------------------------------------
def middlebury() -> None:
    if not MIDDLEBURY.is_dir():
        print(f"# middlebury: skipped, {MIDDLEBURY} is absent", flush=True)
        return
    left = cv2.imread(str(MIDDLEBURY / "motorcycle_left.png"), cv2.IMREAD_GRAYSCALE)
    right = cv2.imread(str(MIDDLEBURY / "motorcycle_right.png"), cv2.IMREAD_GRAYSCALE)
    truth = np.load(MIDDLEBURY / "motorcycle_disp.npz")["arr_0"]
    known = np.isfinite(truth)
    max_disp = 64

    def report(name, disparity, valid):
        bad = ~valid[known] | (np.abs(disparity[known] - truth[known]) > 2.0)
        bench(f"middlebury_bad2_{name}", 100.0 * bad.mean(), "%")
        bench(f"middlebury_density_{name}", 100.0 * valid[known].mean(), "%")

    block, n_sub = 9, 2  # the `ddsgen stereo` defaults (and --min-confidence 0)
    pad = max_disp + block
    with torch.no_grad():
        phases = stereo_reference_phases(torch.from_numpy(right.astype(np.float32)), n_sub, pad)
        result = match(torch.from_numpy(left.astype(np.float32)), phases, pad, 0, max_disp, block, 15.0, n_sub, 64, 0.0)
    report("ddsgen", result.disparity.numpy(), result.valid.numpy())

    bm = cv2.StereoBM_create(numDisparities=max_disp, blockSize=block)
    raw = bm.compute(left, right).astype(np.float32) / 16.0
    report("stereobm", raw, raw > 0)
    window = 5
    sgbm = cv2.StereoSGBM_create(
        minDisparity=0, numDisparities=max_disp, blockSize=window, P1=8 * window**2, P2=32 * window**2,
        disp12MaxDiff=1, uniquenessRatio=10, speckleWindowSize=100, speckleRange=2, mode=cv2.STEREO_SGBM_MODE_SGBM,
    )  # fmt: skip
    raw = sgbm.compute(left, right).astype(np.float32) / 16.0
    report("sgbm", raw, raw > 0)


def main() -> int:
    if len(sys.argv) == 3 and sys.argv[1] == "--rss":
        peak_rss_child(sys.argv[2])
        return 0
    speed(1, "")  # one thread each, as in a render worker
    speed(2, "_2threads")
    peak_rss()
    middlebury()
    return 0


if __name__ == "__main__":
    sys.exit(main())
