"""Runner: same bytes for any number of workers or a Dask cluster; survives killed workers,
a SIGKILLed client, a full disk and an unwritable folder.

Everything renders a tiny sensor (96x72 px, kinect_v1's focal length scaled by 96/640) on a
tiny scene list (upright shapes, a back wall), with torch.compile off (DDSGEN_NO_COMPILE=1:
it costs seconds per process and is not what these tests are about), so each run takes a
couple of seconds.
"""

from __future__ import annotations

import errno
import os
import signal
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest

from ddsgen.cli import main
from ddsgen.errors import InputError
from ddsgen.io.manifest import read_manifest
from ddsgen.runner import MANIFEST, render_dataset
from paused_render import PAUSE_TIMEOUT_S, paused_after_records, wait_for_pause
from tiny_inputs import tiny_preset_yaml, tiny_scenes_yaml, tree_hashes, written_inputs

N_FRAMES = 24
SEED = 7

@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    """(preset path, scene list path), with torch.compile off in this process and its children."""
    with written_inputs(tmp_path_factory.mktemp("inputs"), tiny_preset_yaml(96, 72),
                        tiny_scenes_yaml(frames=3, clutter=(2, 3))) as paths:  # fmt: skip
        yield paths


def assert_complete_and_valid(folder: Path, n: int) -> None:
    """n records, one per frame, in frame order; every file of every record exists and decodes."""
    from ddsgen.io.exr import read_exr
    from ddsgen.io.png import read_depth_png, read_png8, read_png16

    records = read_manifest(folder / MANIFEST)
    assert [r["frame"] for r in records] == list(range(n))
    for record in records:
        shape = (record["intrinsics"]["height"], record["intrinsics"]["width"])
        depth = read_depth_png(folder / record["depth"], record["depth_scale"])
        assert depth.shape == shape and np.isfinite(depth).all()
        assert read_exr(folder / record["depth_exr"]).shape == shape
        assert read_exr(folder / record["clean"]).shape == shape
        assert read_png8(folder / record["ir"]).shape == shape
        assert read_png16(folder / record["mask"]).shape == shape
    leftovers = [p for p in folder.rglob(".*") if p.is_file()]
    assert not leftovers, leftovers


def records_of(folder: Path) -> list[dict]:
    path = folder / MANIFEST
    return read_manifest(path) if path.exists() else []


@pytest.fixture(scope="module")
def reference(inputs, tmp_path_factory):
    """An uninterrupted render with --workers 1, and its file hashes."""
    preset, scenes = inputs
    out = tmp_path_factory.mktemp("ref") / "out"
    render_dataset(preset, scenes, N_FRAMES, str(out), workers=1, seed=SEED, progress=False)
    assert_complete_and_valid(out, N_FRAMES)
    return out, tree_hashes(out)


def test_reference_is_a_real_dataset(reference):
    out, hashes = reference
    records = read_manifest(out / MANIFEST)
    assert all(0.3 < r["valid_fraction"] <= 1.0 for r in records)  # a real depth image, not all-invalid
    # registered to an RGB camera: the IR image is the IR camera's, 27 mm left, principal point 17.4 px (at 640) left
    for r in records:
        ir = r["ir_camera"]
        assert ir["cam_T_ir"][0][3] == pytest.approx(-0.027)
        assert ir["intrinsics"]["cx"] == pytest.approx(r["intrinsics"]["cx"] - 17.4 * r["intrinsics"]["width"] / 640)
    assert all(r["objects"] for r in records)
    assert len(set(hashes.values())) > N_FRAMES  # frames differ from each other


@pytest.mark.slow
def test_workers_2_gives_identical_files(inputs, reference, tmp_path):
    preset, scenes = inputs
    out = tmp_path / "out"
    render_dataset(preset, scenes, N_FRAMES, str(out), workers=2, seed=SEED, progress=False)
    assert tree_hashes(out) == reference[1]


def test_resume_in_process_renders_only_missing_frames(inputs, reference, tmp_path):
    preset, scenes = inputs
    out = tmp_path / "out"
    first = render_dataset(preset, scenes, 10, str(out), workers=1, seed=SEED, progress=False)
    second = render_dataset(preset, scenes, N_FRAMES, str(out), workers=1, seed=SEED, progress=False)
    assert (first.frames_rendered, second.frames_rendered, second.frames_skipped) == (10, N_FRAMES - 10, 10)
    assert tree_hashes(out) == reference[1]


def _pool_children() -> list[int]:
    """pids of this process's multiprocessing spawn children (the pool workers)."""
    pids = []
    for proc in Path("/proc").iterdir():
        if not proc.name.isdigit():
            continue
        try:
            ppid = int((proc / "stat").read_text().rsplit(")", 1)[1].split()[1])
            cmdline = (proc / "cmdline").read_bytes()
        except (OSError, IndexError, ValueError):
            continue
        if ppid == os.getpid() and b"spawn_main" in cmdline:
            pids.append(int(proc.name))
    return pids


@pytest.mark.slow
@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="needs /proc")
def test_pool_worker_killed_mid_run_dataset_completes(inputs, reference, tmp_path):
    """A pool worker SIGKILLed while the render is paused after its 2nd record (the worker may be mid-frame or idle):
    the pool is rebuilt, the batches it had not returned are rendered again, and the files are the reference's."""
    preset, scenes = inputs
    out = tmp_path / "out"
    killed: list[int] = []

    def killer(pause):
        if pause.reached.wait(PAUSE_TIMEOUT_S):
            children = _pool_children()
            if children:
                os.kill(children[0], signal.SIGKILL)
                killed.append(children[0])
        pause.go_on.set()

    with paused_after_records(2) as pause:
        thread = threading.Thread(target=killer, args=(pause,), daemon=True)
        thread.start()
        render_dataset(preset, scenes, N_FRAMES, str(out), workers=2, seed=SEED, progress=False)
    thread.join(timeout=10)
    assert killed, "no pool worker was alive at the pause"
    assert_complete_and_valid(out, N_FRAMES)
    assert tree_hashes(out) == reference[1]


# ---------------------------------------------------------------- Dask


@pytest.fixture
def dask_cluster():
    distributed = pytest.importorskip("distributed")
    with distributed.LocalCluster(
        n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1", dashboard_address=None,
        silence_logs=50,
    ) as cluster:  # fmt: skip
        yield cluster


@pytest.mark.slow
def test_dask_local_cluster_gives_identical_files(inputs, reference, tmp_path, dask_cluster):
    from distributed import Client

    preset, scenes = inputs
    out = tmp_path / "out"
    render_dataset(preset, scenes, N_FRAMES, str(out), seed=SEED, scheduler=dask_cluster.scheduler_address,
                   progress=False, batch_size=2)  # fmt: skip
    assert tree_hashes(out) == reference[1]
    with Client(dask_cluster.scheduler_address) as client:  # the allocator fix reached every worker
        assert all(client.run(lambda dask_worker: "ddsgen-allocator" in dask_worker.plugins).values())


@pytest.mark.slow
def test_dask_worker_killed_mid_frame_dataset_completes(inputs, reference, tmp_path, dask_cluster):
    from distributed import Client

    preset, scenes = inputs
    out = tmp_path / "out"
    killed: list[int] = []

    def killer(pause):
        """At the pause after the 2nd record, SIGKILL a worker that holds tasks (any worker if none does): its
        tasks, finished or not, are lost and rerun elsewhere."""
        try:
            if pause.reached.wait(PAUSE_TIMEOUT_S):
                with Client(dask_cluster.scheduler_address) as client:
                    processing = client.processing()
                    chosen = max(processing, key=lambda worker: len(processing[worker]))
                    pid = client.run(os.getpid, workers=[chosen])[chosen]
                    os.kill(pid, signal.SIGKILL)
                    killed.append(pid)
        finally:
            pause.go_on.set()

    with paused_after_records(2) as pause:
        thread = threading.Thread(target=killer, args=(pause,), daemon=True)
        thread.start()
        render_dataset(preset, scenes, N_FRAMES, str(out), seed=SEED, scheduler=dask_cluster.scheduler_address,
                       progress=False, batch_size=2)  # fmt: skip
    thread.join(timeout=10)
    assert killed, "no Dask worker was killed at the pause"
    with pytest.raises(ProcessLookupError):
        os.kill(killed[0], 0)  # it really died
    lines = (out / MANIFEST).read_text().splitlines()
    assert len(lines) == len(set(lines)) == N_FRAMES  # no duplicate record
    assert_complete_and_valid(out, N_FRAMES)
    assert tree_hashes(out) == reference[1]


def test_unreachable_scheduler_is_one_line_exit_2(inputs, tmp_path, capsys, monkeypatch):
    pytest.importorskip("distributed")
    monkeypatch.setattr("ddsgen.distributed.CONNECT_TIMEOUT_S", 2.0)
    preset, scenes = inputs
    out = tmp_path / "out"
    code = main(["render", preset, "--scenes", scenes, "-n", "2", "--out", str(out), "--quiet",
                 "--scheduler", "tcp://127.0.0.1:9"])  # fmt: skip
    err = capsys.readouterr().err
    assert code == 2 and len(err.strip().splitlines()) == 1 and "--scheduler" in err, err
    assert not out.exists()


# ---------------------------------------------------------------- SIGKILL the client, resume


@pytest.mark.slow
@pytest.mark.parametrize("workers", [1, 2])
def test_sigkill_render_then_rerun_is_byte_identical(inputs, reference, tmp_path, workers):
    """SIGKILL to the command and its workers once the manifest holds 3 records (the render paused there; the workers
    may be anywhere in the frames they hold): a re-run keeps those 3 and ends with the reference's bytes."""
    preset, scenes = inputs
    out = tmp_path / "out"
    argv = ["ddsgen", "render", preset, "--scenes", scenes, "-n", str(N_FRAMES), "--out", str(out),
            "--seed", str(SEED), "--workers", str(workers), "--quiet"]  # fmt: skip
    env = dict(os.environ, DDSGEN_NO_COMPILE="1", PYTHONWARNINGS="ignore")
    flag, err_path = tmp_path / "paused", tmp_path / "stderr.txt"
    with open(err_path, "w") as err:  # a file, not a pipe: nobody reads it while the render runs
        process = subprocess.Popen([sys.executable, str(Path(__file__).with_name("paused_render.py")), "3", str(flag),
                                    "--", *argv], env=env, start_new_session=True, stdout=subprocess.DEVNULL,
                                   stderr=err)  # fmt: skip
    try:
        wait_for_pause(flag, process, err_path.read_text)
    finally:
        # the whole process group: the CLI and its pool workers (a crash, the OOM killer, a power cut)
        os.killpg(process.pid, signal.SIGKILL)
        process.wait()
    assert process.returncode == -signal.SIGKILL, err_path.read_text()
    done = records_of(out)
    assert len(done) == 3, f"the manifest holds {len(done)} records at the pause after the 3rd"
    # what is in the manifest is complete (files written before the record)
    for record in done:
        for key in ("depth", "depth_exr", "clean", "ir", "mask"):
            assert (out / record[key]).is_file()
    summary = render_dataset(preset, scenes, N_FRAMES, str(out), workers=workers, seed=SEED, progress=False)
    assert summary.frames_skipped == len({r["frame"] for r in done})
    assert_complete_and_valid(out, N_FRAMES)
    assert tree_hashes(out) == reference[1]


# ---------------------------------------------------------------- disk full, unwritable folder


def test_disk_full_is_a_clear_error_and_finished_frames_stay_valid(inputs, reference, tmp_path, monkeypatch, capsys):
    preset, scenes = inputs
    out = tmp_path / "out"
    real_fsync = os.fsync
    calls = {"n": 0}

    def fsync_then_full(fd):
        calls["n"] += 1
        if calls["n"] > 40:  # after a few frames (each frame: 5 files + 1 manifest line)
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return real_fsync(fd)

    monkeypatch.setattr(os, "fsync", fsync_then_full)
    code = main(["render", preset, "--scenes", scenes, "-n", str(N_FRAMES), "--out", str(out),
                 "--seed", str(SEED), "--quiet"])  # fmt: skip
    err = capsys.readouterr().err
    assert code == 2, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "No space left on device" in lines[0] and str(out) in lines[0], err
    assert "Traceback" not in err
    done = records_of(out)
    assert 1 <= len(done) < N_FRAMES
    # finished frames are valid and byte-identical to the reference; no partial file anywhere
    hashes = tree_hashes(out)
    assert not [p for p in hashes if Path(p).name.startswith(".")], hashes
    for record in done:
        for key in ("depth", "depth_exr", "clean", "ir", "mask"):
            assert hashes[record[key]] == reference[1][record[key]]
    # space is back: re-running completes the dataset, identical to an uninterrupted run
    monkeypatch.setattr(os, "fsync", real_fsync)
    render_dataset(preset, scenes, N_FRAMES, str(out), workers=1, seed=SEED, progress=False)
    assert tree_hashes(out) == reference[1]


def test_out_is_a_file_is_one_line_exit_2(inputs, tmp_path, capsys):
    preset, scenes = inputs
    blocker = tmp_path / "file"
    blocker.write_text("x")
    for out in (blocker, blocker / "sub"):
        code = main(["render", preset, "--scenes", scenes, "-n", "1", "--out", str(out), "--quiet"])
        err = capsys.readouterr().err
        assert code == 2 and len(err.strip().splitlines()) == 1 and str(blocker) in err, err
    assert blocker.read_text() == "x"


@pytest.mark.skipif(os.name != "posix" or os.geteuid() == 0, reason="root ignores folder permissions")
def test_read_only_folder_is_one_line_exit_2(inputs, tmp_path, capsys):
    preset, scenes = inputs
    parent = tmp_path / "ro"
    parent.mkdir()
    parent.chmod(0o500)
    try:
        code = main(["render", preset, "--scenes", scenes, "-n", "1", "--out", str(parent / "out"), "--quiet"])
    finally:
        parent.chmod(0o700)
    err = capsys.readouterr().err
    assert code == 2 and len(err.strip().splitlines()) == 1 and "cannot write" in err, err


def test_different_settings_into_same_folder_is_refused(inputs, tmp_path):
    preset, scenes = inputs
    out = tmp_path / "out"
    render_dataset(preset, scenes, 1, str(out), seed=SEED, progress=False)
    before = tree_hashes(out)
    with pytest.raises(InputError, match="seed changed"):
        render_dataset(preset, scenes, 2, str(out), seed=SEED + 1, progress=False)
    assert tree_hashes(out) == before
