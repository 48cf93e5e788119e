"""A render that stops at a known point, so kill-and-resume tests do not race the render.

The render's process appends a frame's manifest record only after the frame's files are complete. Wrapping that
append, a render pauses right after its k-th record: the manifest then holds exactly k records, while pool workers may
be anywhere in the frames they hold (mid-frame, between files, idle). A test kills or signals the render there and
checks that a re-run gives the bytes of an uninterrupted one, whatever the workers were doing.

In this process: ``with paused_after_records(k) as pause:`` then ``pause.reached.wait()`` / ``pause.go_on.set()``.
As a command: ``python paused_render.py K FLAG -- ddsgen ARGS``: runs ``ddsgen ARGS``, creates the file FLAG when the
k-th record is written, and then waits until killed.
"""

from __future__ import annotations

import sys
import threading
import time
from contextlib import contextmanager
from pathlib import Path
from types import SimpleNamespace

import ddsgen.runner

#: Seconds a test waits for the pause before it fails (spawned workers import torch: slow on a loaded machine).
PAUSE_TIMEOUT_S = 180.0


def _pausing_append(k: int, on_pause):
    real = ddsgen.runner.append_record
    count = 0

    def append_then_pause(path, record, *args, **kwargs):
        nonlocal count
        line = real(path, record, *args, **kwargs)
        count += 1
        if count == k:
            on_pause()
        return line

    return append_then_pause


@contextmanager
def paused_after_records(k: int):
    """Renders in this process pause after their k-th manifest record until ``go_on`` is set."""
    pause = SimpleNamespace(reached=threading.Event(), go_on=threading.Event())

    def on_pause():
        pause.reached.set()
        if not pause.go_on.wait(PAUSE_TIMEOUT_S):
            raise AssertionError(f"nothing let the render go on within {PAUSE_TIMEOUT_S} s")

    real = ddsgen.runner.append_record
    ddsgen.runner.append_record = _pausing_append(k, on_pause)
    try:
        yield pause
    finally:
        pause.go_on.set()
        ddsgen.runner.append_record = real


def wait_for_pause(flag: Path, process, stderr_of) -> None:
    """Wait until the paused render of ``process`` created ``flag``; fail clearly if it ended or took too long."""
    deadline = time.monotonic() + PAUSE_TIMEOUT_S
    while not flag.exists():
        if process.poll() is not None:
            raise AssertionError(f"the render ended (exit {process.returncode}) before its pause: {stderr_of()}")
        if time.monotonic() > deadline:
            raise AssertionError(f"the render did not reach its pause within {PAUSE_TIMEOUT_S} s: {stderr_of()}")
        time.sleep(0.02)


def main() -> None:
    k, flag, separator, *argv = sys.argv[1:]
    assert separator == "--", "usage: paused_render.py K FLAG -- ddsgen ARGS"

    def on_pause():
        Path(flag).touch()
        while True:  # until a signal ends the process
            time.sleep(3600)

    ddsgen.runner.append_record = _pausing_append(int(k), on_pause)
    from ddsgen.cli import entry_point

    sys.argv = argv
    entry_point()


if __name__ == "__main__":
    main()
