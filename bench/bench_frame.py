"""Whole-frame benchmark: per-stage time of a 640x480 kinect_v1 frame, and frames/s to disk.

Prints `bench: NAME VALUE UNIT` lines:
  frame_raycast_ms, frame_ir_ms, frame_matching_ms, frame_sensor_ms, frame_writing_ms   (one thread, as in a
                                    worker; frame_raycast_ms is every cast render makes for a frame
                                    (cast_for_sensor: output view, IR view with shadow rays, margin strip,
                                    registration index); frame_sensor_ms the whole DepthSensor.forward)
  frame_sensor_paper_ms             the same for kinect_v1_paper (1/4 px, no device effects), same run
  frame_matching_vs_stereobm        matching stage / OpenCV StereoBM on the same IR pair, same run
  frame_fps_1worker, frame_fps      frames written to disk per second, steady state (--workers 1, 2)
  frame_fps_paper, frame_fps_vs_paper   the same (--workers 2) for kinect_v1_paper, and the ratio (same run)
  frame_cpu_<stage>_ms              CPU time (process time, one thread) per frame of each stage of `render`'s worker
                                    (scene, raycast, sensor, write; median over steady-state frames): far less
                                    sensitive to the load than wall time
  frame_cpu_fps_estimate            cores x 1000 / the summed CPU ms: frames/s on an idle machine if the workers
                                    keep every core busy (and the stages do not slow each other down)
  frame_cpu_fps_estimate_vs_paper   its ratio to the same estimate for kinect_v1_paper, same run
  frame_load_average                the 1-minute load average before and after (the machine is shared:
                                    every time above is pessimistic by roughly load / cores when load > cores)
"""

from __future__ import annotations

import os
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
from ddsgen.runner import render_dataset  # noqa: E402
from ddsgen.scene.sampling import sample_frame  # noqa: E402
from ddsgen.scene.scenelist import load_scene_list  # noqa: E402
from ddsgen.sensor.depth_sensor import DepthSensor  # noqa: E402
from ddsgen.sensor.ir import render_ir  # noqa: E402
from ddsgen.sensor.matcher import match  # noqa: E402
from ddsgen.sensor.sensor_cast import cast_for_sensor  # noqa: E402

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
    # The casts `render` makes (registered device: the output view, the IR view, the IR margin strip, the index).
    hits, g = cast_for_sensor(scene, intr, preset, output_shadows=False)  # also warms caches (rest poses, BVHs)
    raycast_ms = _median_ms(lambda: cast_for_sensor(scene, intr, preset, output_shadows=False))
    noise = sensor.draw_noise(0, g)
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

    def sensor_ms(name):
        model_preset = load_preset(name)
        model = DepthSensor(model_preset).eval()
        _, geometry = cast_for_sensor(scene, intr, model_preset, output_shadows=False)  # its own (un)registered view
        model_noise = model.draw_noise(0, geometry)
        with torch.no_grad():
            model(geometry, noise=model_noise)  # caches: pattern field, reference phases
            return _median_ms(lambda: model(geometry, noise=model_noise))

    forward_ms, forward_paper_ms = sensor_ms("kinect_v1"), sensor_ms("kinect_v1_paper")

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
    print(f"bench: frame_sensor_ms {forward_ms:.1f} ms")
    print(f"bench: frame_sensor_paper_ms {forward_paper_ms:.1f} ms")
    print(f"bench: frame_writing_ms {writing_ms:.1f} ms")
    print(f"bench: frame_stereobm_ms {bm_ms:.1f} ms")
    print(f"bench: frame_matching_vs_stereobm {matching_ms / bm_ms:.2f} ratio")
    total = raycast_ms + forward_ms + writing_ms
    print(f"bench: frame_single_thread_fps {1000.0 / total:.2f} frames/s")


def render_fps(workers: int, short: int = 6, long: int = 30, preset: str = "kinect_v1") -> float:
    """Steady-state frames/s of `ddsgen render`: from the write times of its depth files, frames ``short``..``long``
    (worker start-up and compile excluded). (Differencing two runs' wall times, as before, gave nonsense under
    load: 2.4e10 frames/s when the longer run happened to finish as fast as the shorter.)"""
    configure_torch_compile_cache()
    with tempfile.TemporaryDirectory() as tmp:
        render_dataset(preset, None, long, str(Path(tmp) / "run"), workers=workers, seed=1, progress=False)
        written = sorted(p.stat().st_mtime_ns for p in (Path(tmp) / "run" / "depth").glob("*.png"))
    if len(written) < long:
        raise RuntimeError(f"expected {long} depth files, found {len(written)}")
    steady = written[short - 1:]  # from the end of the warm-up to the last frame
    return (len(steady) - 1) / max((steady[-1] - steady[0]) / 1e9, 1e-6)


def cpu_profile(preset_name: str, warm: int = 4, frames: int = 16) -> dict[str, float]:
    """Median CPU ms per stage of a render worker's frame (frames ``warm``..``frames - 1``, one thread)."""
    from ddsgen.io.framefiles import write_frame_files
    from ddsgen.raycast import object_labels
    from ddsgen.runner import NOISE_STREAM, RenderJob, _worker_state, prepare_output

    preset = load_preset(preset_name)
    stages: dict[str, list[float]] = {"scene": [], "raycast": [], "sensor": [], "write": []}
    with tempfile.TemporaryDirectory() as tmp:
        prepare_output(Path(tmp), preset, None, 1)
        state = _worker_state(RenderJob(str(Path(preset.source).resolve()), None, tmp, 1))
        sensor, intr = state["sensor"], preset.intrinsics
        for frame in range(frames):
            t0 = time.process_time()
            scene = sample_frame(state["scenes"], frame, 1)
            t1 = time.process_time()
            hits, geometry = cast_for_sensor(scene, intr, preset, output_shadows=False)  # as render_frame does
            t2 = time.process_time()
            with torch.no_grad():
                out = sensor(geometry, seed=[1, frame, NOISE_STREAM])
            t3 = time.process_time()
            write_frame_files(tmp, frame, out.depth.numpy().astype(np.float32), hits.depth, out.ir.numpy(),
                              2.0**preset.ir_bits - 1.0, hits.instance)  # fmt: skip
            object_labels(scene, hits, intr)
            t4 = time.process_time()
            if frame >= warm:
                for name, a, b in (("scene", t0, t1), ("raycast", t1, t2), ("sensor", t2, t3), ("write", t3, t4)):
                    stages[name].append(1000 * (b - a))
    return {name: statistics.median(values) for name, values in stages.items()}


def main() -> None:
    load_before = os.getloadavg()[0]
    stage_times()
    cores = os.cpu_count() or 1
    estimate = {}
    for name in ("kinect_v1", "kinect_v1_paper"):
        profile = cpu_profile(name)
        suffix = "" if name == "kinect_v1" else "_paper"
        for stage, ms in profile.items():
            print(f"bench: frame_cpu_{stage}{suffix}_ms {ms:.1f} ms")
        estimate[name] = cores * 1000.0 / sum(profile.values())
        print(f"bench: frame_cpu_fps_estimate{suffix} {estimate[name]:.2f} frames/s ({cores} cores, {name})")
    print(f"bench: frame_cpu_fps_estimate_vs_paper {estimate['kinect_v1'] / estimate['kinect_v1_paper']:.2f} ratio")
    print(f"bench: frame_fps_1worker {render_fps(1):.2f} frames/s")
    fps = render_fps(2)
    print(f"bench: frame_fps {fps:.2f} frames/s (--workers 2)")
    fps_paper = render_fps(2, preset="kinect_v1_paper")
    print(f"bench: frame_fps_paper {fps_paper:.2f} frames/s (--workers 2, kinect_v1_paper)")
    print(f"bench: frame_fps_vs_paper {fps / fps_paper:.2f} ratio")
    print(f"bench: frame_load_average {load_before:.1f} {os.getloadavg()[0]:.1f} (1-min, before / after; {os.cpu_count()} cores)")


if __name__ == "__main__":
    main()
