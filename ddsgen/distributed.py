"""Render on an existing Dask distributed cluster (``ddsgen render ... --scheduler tcp://HOST:PORT``).

Needs the optional extra ``pip install ddsgen[dask]`` on the client and on every worker,
and an output folder that every worker can reach under the same absolute path (a shared
file system); the preset and scene-list files must be readable by the workers too.

How a run goes:

* The client submits batches of frames (``--batch-size``) as tasks, keeping a bounded
  window in flight (a few per worker thread, re-read as workers join or leave), and
  yields each batch's manifest records as the task finishes; the runner appends them to
  ``manifest.jsonl`` (only the client writes the manifest) and moves the progress bar.
* Workers write the frame files themselves, atomically (temporary name, then rename),
  so a file is either complete or absent.
* A worker that dies mid-frame: the scheduler re-runs its tasks on another worker (up to
  ``distributed.scheduler.allowed-failures`` deaths per task); a task that raises is
  retried ``retries`` times. A frame that runs twice writes the same bytes again (frame
  ``i`` depends only on ``(seed, i)``), and the client yields each frame's record once,
  so the manifest never holds duplicates. Temporary files a killed worker leaves behind
  are removed by the runner when the run ends.

Worker memory allocator: Dask's nanny starts worker processes with
``MALLOC_TRIM_THRESHOLD_=65536`` (config ``distributed.nanny.pre-spawn-environ``), which
switches off glibc's adaptive mmap threshold: every large torch temporary is then a fresh
``mmap``/``munmap`` with page faults, and the matcher ran 2.7x slower inside workers than
outside. :class:`AllocatorPlugin` (registered on the cluster by :func:`run_on_dask`) sets
large ``M_MMAP_THRESHOLD``/``M_TRIM_THRESHOLD`` values with ``mallopt`` in every worker,
present and future, which restores the speed. To avoid the variable altogether, start
your workers with it unset, e.g. in the cluster's dask config::

    distributed:
      nanny:
        pre-spawn-environ:
          MALLOC_TRIM_THRESHOLD_: null

Threads: a frame uses one torch thread; run workers with ``--nthreads 1`` and as many
worker processes as cores (``dask worker ADDR --nworkers K --nthreads 1``). Frames of
one worker process are rendered one at a time (a per-process lock), so several threads
per worker are safe but do not add speed.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterator

from ddsgen.errors import InputError

#: Retries of a task that raised (a worker that *died* is handled by the scheduler's
#: ``allowed-failures`` instead, which re-runs the task elsewhere).
TASK_RETRIES = 2
#: Tasks kept in flight per worker thread, and at least MIN_IN_FLIGHT (hides the per-task round trip).
IN_FLIGHT_PER_THREAD = 4
MIN_IN_FLIGHT = 16
#: Seconds to wait for the scheduler before giving up with a one-line error.
CONNECT_TIMEOUT_S = 20.0
#: glibc mallopt parameters (malloc.h).
M_TRIM_THRESHOLD = -1
M_MMAP_THRESHOLD = -3
MMAP_THRESHOLD_BYTES = 32 * 1024 * 1024  # glibc's maximum (HEAP_MAX_SIZE / 2 on 64-bit)
TRIM_THRESHOLD_BYTES = 128 * 1024 * 1024

_RENDER_LOCK = threading.Lock()


def tune_allocator() -> bool:
    """Undo ``MALLOC_TRIM_THRESHOLD_=65536`` in this process (glibc only); True if applied."""
    import ctypes
    import ctypes.util

    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False  # not glibc (macOS, musl): nothing to undo
    ok_mmap = mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES)
    ok_trim = mallopt(M_TRIM_THRESHOLD, TRIM_THRESHOLD_BYTES)
    return bool(ok_mmap and ok_trim)


def _plugin_class():
    from distributed.diagnostics.plugin import WorkerPlugin

    class AllocatorPlugin(WorkerPlugin):
        """Runs :func:`tune_allocator` in every worker process (also in workers that join later)."""

        name = "ddsgen-allocator"
        idempotent = True

        def setup(self, worker):  # noqa: D401 - Dask hook
            tune_allocator()

    return AllocatorPlugin


def run_batch_on_worker(fn: Callable, job, batch: list[int]) -> list[dict]:
    """The task body: render ``batch`` with ``fn`` under the per-process render lock."""
    with _RENDER_LOCK:
        return fn(job, batch)


ADDRESS_HINT = "give tcp://HOST:PORT or HOST:PORT, e.g. tcp://10.0.0.5:8786"


def check_address(scheduler: str) -> None:
    """:class:`InputError` unless ``scheduler`` has the form of a Dask scheduler address.

    Dask takes ``SCHEME://LOCATION`` or a bare ``HOST:PORT`` (scheme ``tcp``); every scheme but ``inproc`` needs a
    host and a port. Checked with Dask's own parser before any connection is tried: a malformed address fails at
    once and in one line, never after a connection timeout.
    """
    _require_distributed()
    from distributed.comm.addressing import parse_address, parse_host_port
    from distributed.comm.registry import backends

    def bad(problem: str) -> InputError:
        return InputError(f"--scheduler: {scheduler!r} is not a scheduler address ({problem}); {ADDRESS_HINT}")

    try:
        scheme, location = parse_address(scheduler)
    except ValueError as error:
        raise bad(str(error)) from None
    if scheme not in backends:
        raise bad(f"unknown scheme {scheme}://; Dask knows {', '.join(s + '://' for s in sorted(backends))}")
    if scheme == "inproc":
        return
    try:
        host, port = parse_host_port(location)
    except ValueError as error:
        raise bad("no port number" if "missing port" in str(error) else "the port is not a number") from None
    if not host:
        raise bad("no host name")
    if not 0 < port < 65536:
        raise bad(f"port {port} is out of range 1-65535")


def _require_distributed() -> None:
    try:
        import distributed  # noqa: F401
    except ImportError:
        raise InputError("--scheduler: needs Dask distributed (pip install 'ddsgen[dask]')") from None


def connect(scheduler: str, timeout: float | None = None):
    """A :class:`distributed.Client` for ``scheduler``; :class:`InputError` if malformed, unreachable or Dask is missing.

    A Client whose constructor failed still exists, half built, with its event-loop thread running; left to the
    garbage collector, its ``__del__`` closed it at interpreter exit against a loop already gone, which waited
    2 x the timeout (40 s) and printed an ``Exception ignored in: Client.__del__`` traceback. So the object is made
    first and initialised in a second step, and a failed one is closed here, while its loop still runs.
    """
    check_address(scheduler)
    from distributed import Client

    client = Client.__new__(Client)
    try:
        client.__init__(scheduler, timeout=timeout or CONNECT_TIMEOUT_S, set_as_default=False)
    except (OSError, TimeoutError, ValueError) as error:
        _discard(client)
        first = str(error).splitlines()[0] if str(error) else type(error).__name__
        raise InputError(f"--scheduler: cannot connect to {scheduler} ({first})") from None
    except BaseException:  # Ctrl-C while connecting
        _discard(client)
        raise
    return client


def _discard(client) -> None:
    """Close a Client whose start failed; never raise (its own error is the one to report)."""
    try:
        client.close(timeout=5)
    except Exception:  # noqa: BLE001 - a half-built client may lack any attribute close() touches
        pass


def _total_threads(client) -> int:
    try:
        return max(1, sum(client.nthreads().values()))
    except Exception:  # noqa: BLE001 - a transient scheduler hiccup must not end the run
        return 1


def run_on_dask(
    scheduler,
    fn: Callable,
    job,
    batches: list[list[int]],
    retries: int = TASK_RETRIES,
) -> Iterator[list[dict]]:
    """Run ``fn(job, batch)`` for every batch on a Dask cluster; yield each batch's records as it finishes.

    Args:
        scheduler: scheduler address (``tcp://HOST:PORT``), or a connected ``distributed.Client``.
        fn: picklable by reference (a module-level function), ``fn(job, frames) -> list[record]``.
        job: picklable argument shared by every task (sent once per task; keep it small).
        batches: lists of frame numbers; every frame appears in at most one batch.
        retries: re-runs of a task that raised.

    Yields:
        The record list of each batch, in completion order; a frame's records are yielded once.

    Raises:
        InputError: Dask missing or scheduler unreachable (before any task is sent).
        Whatever a task raised after its retries (e.g. OSError from a full disk), or
        ``distributed.KilledWorker`` when a task kept killing workers.
    """
    from distributed import as_completed

    own_client = isinstance(scheduler, str)
    client = connect(scheduler) if own_client else scheduler
    try:
        client.register_plugin(_plugin_class()())
        queue = iter(enumerate(batches))
        seen: set[int] = set()
        job_token = _job_token(job)

        def submit(count: int) -> list:
            """Send up to ``count`` more batches in one message."""
            chosen = [item for _, item in zip(range(count), queue)]
            if not chosen:
                return []
            keys = [f"ddsgen-render-{job_token}-{index}" for index, _ in chosen]
            return client.map(run_batch_on_worker, [fn] * len(chosen), [job] * len(chosen),
                              [batch for _, batch in chosen], key=keys, pure=False, retries=retries)  # fmt: skip

        window = max(MIN_IN_FLIGHT, IN_FLIGHT_PER_THREAD * _total_threads(client))
        checked = time.monotonic()
        pending = as_completed(submit(window), with_results=True, loop=client.loop)
        try:
            for finished in pending.batches():  # everything that completed since the last look
                for future, records in finished:
                    future.release()
                    fresh = [r for r in records if int(r["frame"]) not in seen]
                    seen.update(int(r["frame"]) for r in fresh)
                    yield fresh
                if time.monotonic() - checked > 2.0:  # workers may join or leave; ask now and then
                    window = max(MIN_IN_FLIGHT, IN_FLIGHT_PER_THREAD * _total_threads(client))
                    checked = time.monotonic()
                pending.update(submit(window - pending.count()))
        except BaseException:
            for future in list(pending.futures):
                future.cancel()
            raise
    finally:
        if own_client:
            client.close()


def _job_token(job) -> str:
    """A token unique to this run (job, process, time), so task keys of different runs never collide on a shared cluster."""
    import hashlib
    import os
    import time

    text = f"{job!r}-{os.getpid()}-{time.time_ns()}"
    return hashlib.sha1(text.encode()).hexdigest()[:10]
