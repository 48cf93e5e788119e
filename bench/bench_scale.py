"""Scale-out benchmark: how rendering speeds up with workers, and what a Dask task costs.

Prints `bench: NAME VALUE UNIT` lines:
  scale_fps_1worker, scale_fps_2workers   steady-state kinect_v1 frames/s to disk (--workers 1, 2)
  scale_2workers_vs_1                     their ratio (target >= 1.8 on 2 cores)
  scale_fps_dask_2workers                 the same through a Dask LocalCluster (2 worker processes, loopback)
  scale_dask_vs_1                         Dask (2 workers) / --workers 1
  dask_task_overhead_ms                   wall time per no-op task with all 2000 in flight (2 workers)
  dask_run_on_dask_overhead_ms            the same through ddsgen.distributed.run_on_dask (bounded window)

Steady state: each configuration renders LONG frames; the rate is timed from the SKIP-th
(= LONG/2-th) manifest record to the last, so process start-up, torch.compile and the
warm-up of every worker are left out (a worker that compiles slower than its peer can
still be warming up after the first few frames arrive, so the first half is skipped).
Other work on the machine shows up in every figure: compare them within one run.
"""

from __future__ import annotations

import sys
import tempfile
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from ddsgen.runner import render_dataset  # noqa: E402

PRESET = "kinect_v1"
LONG = 32  # frames per render; the rate is timed over the second half
SKIP = LONG // 2
OVERHEAD_TASKS = 2000


def steady_fps(workers: int = 1, scheduler: str | None = None) -> float:
    """Frames/s between the SKIP-th and the LONG-th frame of one render (start-up and warm-up excluded)."""
    marks: dict[int, float] = {}
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "run"
        done = threading.Event()

        def watch():
            manifest = out / "manifest.jsonl"
            while not done.is_set():
                count = manifest.read_bytes().count(b"\n") if manifest.exists() else 0
                for mark in (SKIP, LONG):
                    if count >= mark and mark not in marks:
                        marks[mark] = time.perf_counter()
                time.sleep(0.005)

        watcher = threading.Thread(target=watch, daemon=True)
        watcher.start()
        render_dataset(PRESET, None, LONG, str(out), workers=workers, seed=1, progress=False, scheduler=scheduler)
        marks.setdefault(LONG, time.perf_counter())
        done.set()
        watcher.join()
    return (LONG - SKIP) / max(marks[LONG] - marks[SKIP], 1e-9)


def noop_batch(job, frames):
    return [{"frame": f} for f in frames]


def noop(i):
    return i


def dask_task_overhead_ms(address: str) -> tuple[float, float]:
    """(ms per task with every task in flight, ms per task through run_on_dask's bounded window)."""
    from distributed import Client

    from ddsgen.distributed import run_on_dask

    with Client(address) as client:
        client.gather(client.map(noop, range(100), pure=False))  # warm-up
        start = time.perf_counter()
        client.gather(client.map(noop, range(OVERHEAD_TASKS), pure=False))
        raw = time.perf_counter() - start
        batches = [[i] for i in range(OVERHEAD_TASKS)]
        for _ in run_on_dask(client, noop_batch, "warm-up", batches[:50]):
            pass
        start = time.perf_counter()
        count = sum(len(r) for r in run_on_dask(client, noop_batch, "bench", batches))
        windowed = time.perf_counter() - start
    assert count == OVERHEAD_TASKS
    return 1000.0 * raw / OVERHEAD_TASKS, 1000.0 * windowed / OVERHEAD_TASKS


def main() -> None:
    fps1 = steady_fps(1)
    print(f"bench: scale_fps_1worker {fps1:.2f} frames/s", flush=True)
    fps2 = steady_fps(2)
    print(f"bench: scale_fps_2workers {fps2:.2f} frames/s", flush=True)
    print(f"bench: scale_2workers_vs_1 {fps2 / fps1:.2f} ratio (target >= 1.8 on 2 cores)", flush=True)
    try:
        from distributed import LocalCluster
    except ImportError:
        print("# distributed not installed: Dask figures skipped")
        return
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                      dashboard_address=None, silence_logs=50) as cluster:  # fmt: skip
        raw, windowed = dask_task_overhead_ms(cluster.scheduler_address)
        print(f"bench: dask_task_overhead_ms {raw:.2f} ms ({OVERHEAD_TASKS} no-op tasks in flight, 2 workers)", flush=True)
        print(f"bench: dask_run_on_dask_overhead_ms {windowed:.2f} ms (the same through run_on_dask's window)",
              flush=True)  # fmt: skip
        fps_dask = steady_fps(scheduler=cluster.scheduler_address)
    print(f"bench: scale_fps_dask_2workers {fps_dask:.2f} frames/s", flush=True)
    print(f"bench: scale_dask_vs_1 {fps_dask / fps1:.2f} ratio", flush=True)


if __name__ == "__main__":
    main()
