"""Render a dataset: frames over a process pool (or a Dask cluster), resumable, reproducible.

Frame i depends only on (seed, i): its scene, camera and IR noise are drawn from
``numpy.random.default_rng([seed, i, stream])``, and every worker computes with one
torch thread, so the same seed gives byte-identical files whatever the number of
workers. Each frame's files are written atomically, and its manifest record is
appended only after they are complete; when the run finishes the manifest is
rewritten in frame order (atomically), so finished datasets compare byte for byte.
Re-running into the same folder skips frames that already have a record.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ddsgen.atomic import atomic_write_text
from ddsgen.cache import configure_torch_compile_cache
from ddsgen.distributed import check_address, connect, run_on_dask
from ddsgen.errors import InputError
from ddsgen.io.bop_writer import check_bop_root, scans_folder, write_bop_dataset
from ddsgen.io.class_table import write_class_table
from ddsgen.io.framefiles import DEPTH_SCALE, write_frame_files
from ddsgen.io.manifest import (
    BUILT_IN_SCENES,
    RUN_FILE,
    append_record,
    dumps_record,
    file_digest,
    read_manifest,
    repair_manifest,
    sorted_records,
)
from ddsgen.preset import SensorPreset, load_preset, save_preset, source_label
from ddsgen.raycast import object_labels
from ddsgen.scene.sampling import sample_frame
from ddsgen.scene.scenelist import SceneList, load_scene_list, models_folder
from ddsgen.sensor.depth_sensor import DepthSensor
from ddsgen.sensor.registration import ir_camera_record
from ddsgen.sensor.sensor_cast import cast_for_sensor
from ddsgen.worker_pool import run_in_pool

MANIFEST = "manifest.jsonl"
OUTPUT_FORMATS = ("ddsgen", "bop")

# Random streams of a frame: rng([seed, frame, STREAM]).
NOISE_STREAM = 1


@dataclass(frozen=True)
class RenderJob:
    """Everything a worker needs to render frames (picklable)."""

    preset_path: str
    scenes_path: str | None
    out: str
    seed: int
    camera: tuple[float, float, float, float] | None = None  # (fx, fy, cx, cy) px overriding the preset's
    models_dir: str | None = None  # where mesh files not found at their scene-list path are looked up


@dataclass
class SimulatedFrame:
    """One frame as arrays, before any file is written (``render_frame`` writes it; ``ddsgen.data`` reads it).

    depth: float32 (H, W) simulated depth (m), 0 = invalid. clean: float32 (H, W) noise-free depth (m), 0 = no
    hit. ir: float (H, W) IR image in detector counts. instance: (H, W) object ids, 0 = background.
    ir_full_scale: the detector's largest count. record: the manifest record without its file keys.
    """

    depth: np.ndarray
    clean: np.ndarray
    ir: np.ndarray
    instance: np.ndarray
    ir_full_scale: float
    record: dict


# ---- the camera override (render --camera) ----------------------------------------------
def parse_camera(text: str | None) -> tuple[float, float, float, float] | None:
    """``"fx,fy,cx,cy"`` (px) -> a tuple of four finite numbers; None for None. InputError on anything else."""
    if text is None:
        return None
    parts = str(text).split(",")
    try:
        values = tuple(float(p) for p in parts)
    except ValueError:
        values = ()
    if len(values) != 4 or not all(np.isfinite(values)):
        raise InputError(f"--camera: expected four numbers fx,fy,cx,cy (px), got {text!r}")
    return values


def apply_camera(preset: SensorPreset, camera: tuple[float, float, float, float] | None) -> SensorPreset:
    """The preset with its intrinsics (focal_px, focal_y_px, cx_px, cy_px) set from ``camera`` = (fx, fy, cx, cy)."""
    if camera is None:
        return preset
    fx, fy, cx, cy = camera
    if not (fx > 0 and fy > 0):
        raise InputError(f"--camera: focal lengths must be > 0, got fx={fx:g}, fy={fy:g}")
    if not (0 <= cx <= preset.width_px - 1 and 0 <= cy <= preset.height_px - 1):
        raise InputError(f"--camera: principal point ({cx:g}, {cy:g}) lies outside the {preset.width_px}x"
                         f"{preset.height_px} px image")  # fmt: skip
    try:
        return preset.replace(focal_px=fx, focal_y_px=fy, cx_px=cx, cy_px=cy)
    except InputError as error:  # e.g. a focal length that puts the largest disparity beyond the image
        raise InputError(f"--camera: {error}") from None


@dataclass
class RenderSummary:
    frames_total: int
    frames_rendered: int
    frames_skipped: int
    seconds: float
    out: str

    @property
    def frames_per_second(self) -> float:
        return self.frames_rendered / self.seconds if self.seconds > 0 else float("nan")


# ---- per-process state: built once per worker, not per frame ---------------------------
_WORKER: dict = {}


@contextlib.contextmanager
def one_thread():
    """One intra-op torch thread and one BLAS thread while frames render, then the caller's settings again.

    Parallelism comes from workers, and results must not depend on how a reduction was split over threads. numpy's
    BLAS (the ray cast's matrix products) otherwise keeps a thread per core that spins after each call, ~95 ms of CPU
    per frame beside a 125-ms sensor. Restoring matters where frames render in the caller's process (``--workers
    1``, :mod:`ddsgen.data`): the caller's own torch work keeps its thread count.
    """
    import torch
    from threadpoolctl import ThreadpoolController

    controller = _WORKER.setdefault("threadpools", ThreadpoolController())  # found once: a lookup costs ~0.5 ms
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        with controller.limit(limits=1, user_api="blas"):
            yield
    finally:
        torch.set_num_threads(before)


def _worker_state(job: RenderJob):
    if _WORKER.get("job") != job:
        configure_torch_compile_cache()
        preset = apply_camera(load_preset(job.preset_path), job.camera)
        for key in ("job", "preset", "scenes", "sensor"):
            _WORKER.pop(key, None)
        _WORKER.update(
            job=job,
            preset=preset,
            scenes=load_scene_list(job.scenes_path, job.models_dir),
            sensor=DepthSensor(preset).eval(),
        )
    return _WORKER


def render_frame(job: RenderJob, frame: int) -> dict:
    """Render frame ``frame`` and write its files; return its manifest record."""
    simulated = simulate_frame(job, frame)
    files = write_frame_files(job.out, frame, simulated.depth, simulated.clean, simulated.ir, simulated.ir_full_scale,
                              simulated.instance)  # fmt: skip
    return {**simulated.record, **files}


def simulate_frame(job: RenderJob, frame: int) -> SimulatedFrame:
    """Frame ``frame`` of the dataset ``job`` describes, as arrays (a pure function of the job and ``frame``)."""
    import torch

    state = _worker_state(job)
    preset: SensorPreset = state["preset"]
    intrinsics = preset.intrinsics
    scene = sample_frame(state["scenes"], frame, job.seed)
    hits, geometry = cast_for_sensor(scene, intrinsics, preset, output_shadows=False)
    with torch.no_grad():
        output = state["sensor"](geometry, seed=[job.seed, frame, NOISE_STREAM])
    depth = output.depth.numpy().astype(np.float32)
    ir = output.ir.numpy()
    clean, instance = np.asarray(hits.depth, dtype=np.float32), np.asarray(hits.instance)
    for warp in state["sensor"].image_effects.effects:  # a warped pixel grid: the labels follow the depth
        clean, instance = warp.warp_labels((clean, instance), intrinsics.fx, intrinsics.fy, intrinsics.cx,
                                           intrinsics.cy)  # fmt: skip

    objects = object_labels(scene, hits, intrinsics, instance)
    for label in objects:  # the stable identity of the class table (classes.json), the same in every frame
        entry = state["scenes"].class_entry(label["mesh"], label["mesh_scale"], label["class"])
        label.update(obj_id=entry.obj_id, class_id=entry.class_id)
    ir_camera = ir_camera_record(intrinsics, preset)  # registered: the IR image is this camera's, not the depth's
    record = {
        "frame": frame,
        "intrinsics": intrinsics.as_dict(),
        "depth_scale": DEPTH_SCALE,
        "world_T_cam": np.asarray(scene.world_T_cam, dtype=float).tolist(),
        "objects": objects,
        "seed": job.seed,
        "valid_fraction": round(float((depth > 0).mean()), 6),
        **({"ir_camera": ir_camera} if ir_camera else {}),
    }
    return SimulatedFrame(depth, clean, ir, instance, 2.0**preset.ir_bits - 1.0, record)


def _render_batch(job: RenderJob, frames: list[int]) -> list[dict]:
    with one_thread():
        return [render_frame(job, f) for f in frames]


# ---- the run ----------------------------------------------------------------------------
def _run_identity(preset: SensorPreset, scenes_path: str | None, seed: int) -> dict:
    """What must match for a resume to continue an earlier run into the same folder."""
    preset_text = json.dumps(preset.to_dict(), sort_keys=True)
    return {
        "seed": seed,
        "preset_sha": hashlib.sha256(preset_text.encode()).hexdigest()[:16],
        "scenes": str(Path(scenes_path).resolve()) if scenes_path else BUILT_IN_SCENES,
        "scenes_sha": file_digest(scenes_path),
    }


def prepare_output(out: Path, preset: SensorPreset, scenes_path: str | None, seed: int,
                   scene_list: SceneList | None = None) -> set[int]:  # fmt: skip
    """Create (or re-open) the output folder; return the frames already finished.

    With ``scene_list``, its class table is written as ``out/classes.json``.
    """
    identity = _run_identity(preset, scenes_path, seed)
    run_file = out / RUN_FILE
    if run_file.exists():
        try:
            previous = json.loads(run_file.read_text())
        except (OSError, json.JSONDecodeError):
            raise InputError(f"{run_file}: unreadable run description; use a new --out folder") from None
        if previous != identity:
            changed = ", ".join(k for k in identity if previous.get(k) != identity[k])
            raise InputError(
                f"{out}: holds a run with different settings ({changed} changed); use a new --out folder to render these"
            )
    elif out.exists() and (not out.is_dir() or any(out.iterdir())):
        what = "folder exists and is not a ddsgen render" if out.is_dir() else "exists and is not a folder"
        raise InputError(f"{out}: {what}; use a new --out folder")
    try:
        out.mkdir(parents=True, exist_ok=True)
        save_preset(preset, out / "sensor.yaml", comment=f"resolved from {source_label(preset)}")
        atomic_write_text(run_file, json.dumps(identity, indent=1, sort_keys=True) + "\n")
        if scene_list is not None:
            write_class_table(out, scene_list.classes)
    except OSError as error:
        raise InputError(f"{out}: cannot write the output folder ({_os_reason(error)})") from None
    manifest = out / MANIFEST
    if not manifest.exists():
        return set()
    repair_manifest(manifest)
    return {int(r["frame"]) for r in read_manifest(manifest)}


def _os_reason(error: OSError) -> str:
    """One-line reason of an OSError (also one re-raised from a worker process)."""
    reason = error.strerror or str(error) or type(error).__name__
    name = getattr(error, "filename", None)
    return f"{reason}: {name}" if name else reason


def remove_stale_temporaries(out: Path) -> int:
    """Delete temporary files that a killed process left behind (``.NAME.XXXX.tmp.EXT``, see atomic.py).

    Call only when no process is writing into ``out`` (the end of a run). Returns how many were removed.
    """
    removed = 0
    for folder in [out, *(p for p in out.iterdir() if p.is_dir())] if out.is_dir() else []:
        for path in folder.glob(".*.tmp*"):
            if path.is_file():
                path.unlink(missing_ok=True)
                removed += 1
    return removed


def finalise_manifest(out: Path) -> None:
    """Rewrite the manifest in frame order (atomic), one record per frame; drop stale temporary files."""
    remove_stale_temporaries(out)
    manifest = out / MANIFEST
    lines = "".join(dumps_record(r) + "\n" for r in sorted_records(read_manifest(manifest)))
    atomic_write_text(manifest, lines)


def check_sensor_assets(preset: SensorPreset) -> None:
    """Load the preset's dot pattern and fit it to the sensor now, so a missing or unusable pattern
    file is an :class:`InputError` before anything is written (the workers would fail later)."""
    try:
        DepthSensor(preset).pattern_field()
    except InputError as error:
        raise InputError(f"{preset.source}: pattern: {error}") from None


def render_dataset(
    preset_path: str,
    scenes_path: str | None,
    n: int,
    out: str,
    workers: int = 1,
    seed: int = 0,
    scheduler: str | None = None,
    progress: bool = True,
    batch_size: int = 1,
    output_format: str = "ddsgen",
    camera: str | tuple | None = None,
    models_dir: str | None = None,
) -> RenderSummary:
    """Render frames 0..n-1 into ``out`` (skipping finished ones).

    Args:
        preset_path: sensor preset file or shipped name.
        scenes_path: scene list YAML, or None for the built-in default.
        n: number of frames in the dataset.
        out: output folder.
        workers: local worker processes (1 = in this process).
        seed: dataset seed.
        scheduler: address of a Dask scheduler (``tcp://host:port``) to run on instead.
        progress: show a tqdm progress bar.
        batch_size: frames per task.
        output_format: ``"ddsgen"`` (the scan layout, README.md "Outputs") or ``"bop"``: a BOP dataset at ``out`` (see
            ``ddsgen/io/bop_writer.py``), rendered through the ddsgen layout in ``out/ddsgen``.
        camera: ``"fx,fy,cx,cy"`` (px) or a 4-tuple overriding the preset's intrinsics (focal_px, focal_y_px,
            cx_px, cy_px); the manifest's intrinsics and OUT/sensor.yaml record them.
        models_dir: folder where mesh files not found at their scene-list path are looked up by file name
            (default: the environment variable DDSGEN_MODELS).

    Raises:
        InputError: bad preset, scene list, arguments or output folder -- before anything is written.
    """
    if n < 1:  # a dataset of no frames has no manifest to finish: say so before the folder is started
        raise InputError(f"-n: must be >= 1, got {n}")
    if workers < 1:
        raise InputError(f"--workers: must be >= 1, got {workers}")
    if scheduler:  # a malformed address fails now, not after loading the preset and a connection timeout
        check_address(scheduler)
    camera = parse_camera(camera) if isinstance(camera, str) else camera
    preset = apply_camera(load_preset(preset_path), camera)
    models = models_folder(models_dir)  # resolved here: workers (also on a cluster) get the folder, not the variable
    scene_list: SceneList = load_scene_list(scenes_path, models)  # validates and loads every mesh now
    check_sensor_assets(preset)
    if output_format not in OUTPUT_FORMATS:
        raise InputError(f"--format: must be one of {', '.join(OUTPUT_FORMATS)}, got {output_format!r}")
    out_dir = Path(out)
    if output_format == "bop":
        check_bop_root(out_dir)
        out_dir = scans_folder(out_dir)
    client = None
    if scheduler:  # connect first: an unreachable scheduler must not leave an output folder behind
        client = connect(scheduler)
    try:
        summary = _render_into(out_dir, preset, scene_list, RenderJob(
            str(Path(preset.source).resolve()), str(Path(scenes_path).resolve()) if scenes_path else None,
            str(out_dir.resolve()), seed, camera, str(models.resolve()) if models else None,
        ), n, workers, client, progress, batch_size)  # fmt: skip
    finally:
        if client is not None:
            client.close()
    if output_format == "bop":
        try:
            write_bop_dataset(out_dir, Path(out))
        except OSError as error:
            raise InputError(f"{out}: cannot write the BOP dataset ({_os_reason(error)}); re-run to finish it") from None
    return summary


def _render_into(out_dir: Path, preset: SensorPreset, scene_list: SceneList, job: RenderJob, n, workers, client,
                 progress, batch_size):  # fmt: skip
    from tqdm import tqdm

    done = prepare_output(out_dir, preset, job.scenes_path, job.seed, scene_list)
    todo = [f for f in range(n) if f not in done]
    manifest = out_dir / MANIFEST
    batches = [todo[i : i + batch_size] for i in range(0, len(todo), batch_size)]
    start = time.perf_counter()
    bar = tqdm(total=n, initial=n - len(todo), unit="frame", desc="render", disable=not progress, dynamic_ncols=True)
    appended: set[int] = set()
    try:
        if client is not None:
            results = run_on_dask(client, _render_batch, job, batches)
        elif workers == 1:
            results = (_render_batch(job, b) for b in batches)
        else:
            results = run_in_pool(_render_batch, job, batches, workers, job.out)
        for records in results:
            for record in records:
                if int(record["frame"]) in appended:  # a re-run task (e.g. after a worker died): keep one record
                    continue
                append_record(manifest, record)
                appended.add(int(record["frame"]))
            bar.update(len(records))
        finalise_manifest(out_dir)
    except OSError as error:
        # Disk full, folder made read-only, ...: frames already in the manifest are complete and stay valid.
        raise InputError(
            f"{out_dir}: cannot write ({_os_reason(error)}); {len(done) + len(appended)} of {n} frames are complete, "
            f"re-run the same command to resume"
        ) from None
    finally:
        bar.close()
    return RenderSummary(n, len(todo), n - len(todo), time.perf_counter() - start, str(out_dir))


def default_workers() -> int:
    return max(1, min(os.cpu_count() or 1, 8))
