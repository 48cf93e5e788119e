"""The local process pool behind ``render --workers K``: batches in, results out, workers that never outlive it.

Spawned workers (forking a process that already runs torch threads is unsafe), at most 2 batches per worker in
flight, the pool rebuilt when a worker dies (the OOM killer, kill -9), and every worker ended at once on Ctrl-C,
SIGTERM or an error. Split from :mod:`ddsgen.runner`, which decides what to render and writes the manifest.
"""

from __future__ import annotations

import concurrent.futures as cf
import contextlib
import multiprocessing
import os

from ddsgen.errors import InputError

#: How often a local pool is rebuilt after one of its processes died (OOM killer, kill -9) before giving up.
POOL_RESTARTS = 3


def run_in_pool(function, job, batches: list, workers: int, out_label: str):
    """Yield ``function(job, batch)`` for each of ``batches`` as they complete, keeping at most 2 batches per worker
    in flight (``function`` and ``job`` must pickle: the workers are spawned).

    If a worker process dies (the pool breaks), the pool is rebuilt and the batches that had
    not returned are rendered again (same bytes: frame i depends only on (seed, i)), up to
    :data:`POOL_RESTARTS` times; then :class:`InputError` says so in one line. Any other way out (Ctrl-C,
    SIGTERM, which the CLI raises as an exception, an error) ends the workers at once (:func:`_stop_workers`).
    """
    from concurrent.futures.process import BrokenProcessPool

    context = multiprocessing.get_context("spawn")
    todo = list(batches)  # batches not yet returned, in order
    restarts = 0
    while todo:
        pool = cf.ProcessPoolExecutor(max_workers=workers, mp_context=context, initializer=_init_worker,
                                      initargs=(os.getpid(),))  # fmt: skip
        pending: dict[cf.Future, int] = {}
        returned: set[int] = set()
        try:
            for index in range(len(todo)):
                pending[pool.submit(function, job, todo[index])] = index
                if len(pending) >= 2 * workers:
                    finished, _ = cf.wait(pending, return_when=cf.FIRST_COMPLETED)
                    for future in finished:
                        result = future.result()
                        returned.add(pending.pop(future))
                        yield result
            for future in cf.as_completed(list(pending)):
                result = future.result()
                returned.add(pending.pop(future))
                yield result
            todo = []
        except BrokenProcessPool:
            restarts += 1
            if restarts > POOL_RESTARTS:
                raise InputError(
                    f"{out_label}: a worker process died {restarts} times (out of memory? try fewer --workers); "
                    f"finished frames are kept, re-run the same command to resume"
                ) from None
            todo = [batch for i, batch in enumerate(todo) if i not in returned]
        except BaseException:
            _stop_workers(pool, pending)
            raise
        finally:  # after the last batch the workers have nothing in hand: they exit at once
            pool.shutdown(wait=True)


def _init_worker(parent_pid: int) -> None:
    """Pool worker start-up. A terminal's Ctrl-C reaches the whole process group: workers ignore it (no traceback
    from each) and the parent ends them. On Linux a worker also gets SIGTERM when its parent dies
    (``PR_SET_PDEATHSIG``), so not even a SIGKILLed command leaves workers behind (they would wait forever on a
    queue whose write end they hold themselves)."""
    import signal
    import sys

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    if sys.platform.startswith("linux"):
        import ctypes

        with contextlib.suppress(OSError, AttributeError):  # without prctl the parent's clean-up still ends them
            ctypes.CDLL(None).prctl(1, int(signal.SIGTERM), 0, 0, 0)  # 1 = PR_SET_PDEATHSIG
            if os.getppid() != parent_pid:  # the parent died before the request took effect
                os._exit(1)


def _stop_workers(pool: cf.ProcessPoolExecutor, pending: dict) -> None:
    """End the pool's worker processes now, not after the frames they are rendering. Safe for a resume: workers
    write files atomically (a killed one leaves at most a temporary file, which a finished run removes) and only this
    process appends to the manifest, after a frame's files are complete."""
    for future in pending:
        future.cancel()
    processes = list((getattr(pool, "_processes", None) or {}).values())  # the executor has no public list
    manager = getattr(pool, "_executor_manager_thread", None)  # shutdown() forgets it; joined below
    pool.shutdown(wait=False, cancel_futures=True)
    for process in processes:
        process.terminate()
    for process in processes:
        process.join(timeout=10)
        if process.is_alive():
            process.kill()
            process.join()
    # The pool's manager thread sees its workers gone and closes its wake-up pipe. At exit, concurrent.futures' own
    # hook writes to that pipe without a lock: if the thread closes it in between, Python prints "Exception ignored
    # ... OSError: [Errno 9] Bad file descriptor" after our line (3 SIGTERMs in 95 on a loaded machine). Waiting for
    # the thread here leaves the hook a pipe marked closed, which it skips.
    if manager is not None:
        manager.join(timeout=30)
