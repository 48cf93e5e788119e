"""Whole-frame benchmark: per-stage time of a 640x480 kinect_v1 frame, and frames/s to disk.

Prints `bench: NAME VALUE UNIT` lines:
  frame_raycast_ms, frame_ir_ms, frame_matching_ms, frame_writing_ms   (one thread, as in a worker)
  frame_matching_vs_stereobm        matching stage / OpenCV StereoBM on the same IR pair, same run
  frame_fps_1worker, frame_fps      frames written to disk per second, steady state (--workers 1, 2)
"""

from __future__ import annotations

import statistics
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np
import torch

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from ddsgen.cache import configure_torch_compile_cache  # noqa: E402
from ddsgen.io.exr import write_exr  # noqa: E402
from ddsgen.io.png import write_depth_png, write_png8, write_png16  # noqa: E402
from ddsgen.preset import load_preset  # noqa: E402
from ddsgen.raycast import cast  # noqa: E402
from ddsgen.runner import render_dataset  # noqa: E402
from ddsgen.scene.sampling import sample_frame  # noqa: E402
from ddsgen.scene.scenelist import load_scene_list  # noqa: E402
from ddsgen.sensor.depth_sensor import DepthSensor, SensorGeometry  # noqa: E402
from ddsgen.sensor.ir import render_ir  # noqa: E402
from ddsgen.sensor.matcher import match  # noqa: E402

REPEATS = 7


def _median_ms(fn, repeats=REPEATS):
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return 1000 * statistics.median(times)


def stage_times() -> None:
    torch.set_num_threads(1)  # as inside a render worker
    preset = load_preset("kinect_v1")
    sensor = DepthSensor(preset).eval()
    scenes = load_scene_list(None)
    scene = sample_frame(scenes, 0, 0)
    intr = preset.intrinsics
    cast(scene, intr, preset.baseline_m, preset.shadow_bias_m)  # warm caches (rest poses, BVHs)
    raycast_ms = _median_ms(lambda: cast(scene, intr, preset.baseline_m, preset.shadow_bias_m))
    hits = cast(scene, intr, preset.baseline_m, preset.shadow_bias_m)
    g = SensorGeometry.from_hits(hits)
    noise = sensor.draw_noise(0)
    field = sensor.pattern_field()
    lit = (g.hit & ~g.shadow).float()

    def ir_stage():
        with torch.no_grad():
            return render_ir(g.points, g.normals, g.albedo, lit, field, intr.fx, intr.fy, intr.cx, intr.cy,
                             preset.baseline_m, preset.emitted_intensity, preset.ambient_counts,
                             preset.speckle_scale, preset.read_noise_mean_counts, preset.read_noise_std_counts,
                             noise, preset.ir_bits)[0]  # fmt: skip

    ir_ms = _median_ms(ir_stage)
    ir = ir_stage()
    ref = sensor.reference_phases()
    fb = intr.fx * preset.baseline_m

    def matching():
        with torch.no_grad():
            return match(ir, ref, sensor.pad, fb / preset.z_max_m, fb / preset.z_min_m, preset.block_size_px,
                         preset.softargmax_beta, preset.subpixel_level, preset.band_rows, preset.min_confidence)

    matching()  # compile / load kernels
    matching_ms = _median_ms(matching)

    # OpenCV StereoBM on the same pair: the IR image against the reference at infinity.
    left = np.clip(ir.numpy() / 4.0, 0, 255).astype(np.uint8)
    right_full = ref[0].numpy()
    right = np.clip(right_full[:, sensor.pad :] * (left.mean() / max(right_full.mean(), 1e-6)), 0, 255)
    right = right.astype(np.uint8)
    num_disp = int(np.ceil(fb / preset.z_min_m / 16.0) * 16)
    bm = cv2.StereoBM_create(numDisparities=num_disp, blockSize=preset.block_size_px)
    cv2.setNumThreads(1)
    bm_ms = _median_ms(lambda: bm.compute(left, right))

    with torch.no_grad():
        out = sensor(g, noise=noise)
    depth = out.depth.numpy()
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)

        def writing():
            write_exr(tmp / "d.exr", depth)
            write_depth_png(tmp / "d.png", depth)
            write_exr(tmp / "c.exr", hits.depth.astype(np.float32))
            write_png8(tmp / "i.png", out.ir.numpy(), max_value=1023.0)
            write_png16(tmp / "m.png", hits.instance.astype(np.uint16))

        writing_ms = _median_ms(writing)

    print(f"bench: frame_raycast_ms {raycast_ms:.1f} ms")
    print(f"bench: frame_ir_ms {ir_ms:.1f} ms")
    print(f"bench: frame_matching_ms {matching_ms:.1f} ms")
    print(f"bench: frame_writing_ms {writing_ms:.1f} ms")
    print(f"bench: frame_stereobm_ms {bm_ms:.1f} ms")
    print(f"bench: frame_matching_vs_stereobm {matching_ms / bm_ms:.2f} ratio")
    total = raycast_ms + ir_ms + matching_ms + writing_ms
    print(f"bench: frame_single_thread_fps {1000.0 / total:.2f} frames/s")


def render_fps(workers: int, short: int = 6, long: int = 30) -> float:
    """Steady-state frames/s of `ddsgen render` (worker start-up and compile excluded by differencing)."""
    configure_torch_compile_cache()
    times = {}
    with tempfile.TemporaryDirectory() as tmp:
        for n in (short, long):
            start = time.perf_counter()
            render_dataset("kinect_v1", None, n, str(Path(tmp) / f"run{n}"), workers=workers, seed=1, progress=False)
            times[n] = time.perf_counter() - start
    return (long - short) / max(times[long] - times[short], 1e-9)


def main() -> None:
    stage_times()
    print(f"bench: frame_fps_1worker {render_fps(1):.2f} frames/s")
    print(f"bench: frame_fps {render_fps(2):.2f} frames/s (--workers 2)")


if __name__ == "__main__":
    main()
