"""Costs at the product's edges: the PNG structure check against the decode it guards, and how quickly a bad
--scheduler ends the command.

Prints `bench: NAME VALUE UNIT` lines:
  png_check_ms, png_decode_ms          best of 30: png_problem and cv2.imdecode of a 640x480 16-bit depth PNG
  png_check_vs_decode                  their ratio (target < 0.1: the check reads each chunk's CRC only)
  cli_import_s                         reference: a fresh interpreter importing ddsgen.cli (median of 3)
  scheduler_malformed_s                `render --scheduler notaurl` in a fresh interpreter, to its one error line
  scheduler_malformed_vs_import        its ratio to cli_import_s (target < 2: the address is refused before any
                                       connection; a half-built client used to wait 40 s)
  dask_import_s                        reference: a fresh interpreter importing ddsgen.distributed and distributed
  scheduler_unreachable_s              connect() to an address whose client fails to start (3 s timeout), in a fresh
                                       interpreter, to its one line
  scheduler_unreachable_vs_import      its ratio to dask_import_s (target < 3: the half-built client is closed at once;
                                       left to the garbage collector it waited 2 x the timeout at exit)

The subprocess figures include interpreter start-up and imports, which a loaded machine slows down: compare each with
cli_import_s of the same run.
"""

from __future__ import annotations

import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from ddsgen.io.images import png_problem  # noqa: E402
from ddsgen.io.png import depth_to_units  # noqa: E402

CONNECT_TIMEOUT_S = 3
ENV = dict(os.environ, DDSGEN_NO_COMPILE="1")


def bench(name: str, value: float, unit: str) -> None:
    print(f"bench: {name} {value:.4g} {unit}", flush=True)


def best_of(function, repeat: int = 30) -> float:
    """The fastest of ``repeat`` calls, in seconds (the least disturbed by other work on the machine)."""
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        function()
        times.append(time.perf_counter() - start)
    return min(times)


def seconds_of(code: str) -> tuple[float, subprocess.CompletedProcess]:
    """Wall time of ``python -c CODE`` in a fresh interpreter, and its result."""
    start = time.perf_counter()
    result = subprocess.run([sys.executable, "-c", code], env=ENV, cwd=ROOT, capture_output=True, text=True,
                            timeout=300)  # fmt: skip
    return time.perf_counter() - start, result


def png_figures() -> None:
    depth = depth_to_units(np.random.default_rng(3).uniform(0.5, 2.0, (480, 640)))
    ok, encoded = cv2.imencode(".png", depth)
    assert ok and png_problem(encoded) is None
    check = best_of(lambda: png_problem(encoded))
    decode = best_of(lambda: cv2.imdecode(encoded, cv2.IMREAD_UNCHANGED))
    bench("png_check_ms", check * 1e3, "ms")
    bench("png_decode_ms", decode * 1e3, "ms")
    bench("png_check_vs_decode", check / decode, "ratio")


def scheduler_figures() -> None:
    imports = statistics.median(seconds_of("import ddsgen.cli")[0] for _ in range(3))
    bench("cli_import_s", imports, "s")
    with tempfile.TemporaryDirectory() as tmp:
        argv = ["render", "kinect_v1", "-n", "2", "--scheduler", "notaurl", "--out", str(Path(tmp) / "x")]
        code = f"import sys; from ddsgen.cli import entry_point; sys.argv = {['ddsgen', *argv]!r}; entry_point()"
        malformed, result = seconds_of(code)
    if result.returncode != 2:
        print(f"# malformed --scheduler: exit {result.returncode}, {result.stderr.strip()[-200:]}", flush=True)
    bench("scheduler_malformed_s", malformed, "s")
    bench("scheduler_malformed_vs_import", malformed / imports, "ratio")
    code = ("from ddsgen.distributed import connect\nfrom ddsgen.errors import InputError\n"
            f"try:\n    connect('inproc://192.0.2.1/1/1', timeout={CONNECT_TIMEOUT_S})\n"
            "except InputError as error:\n    print(error)\n")  # fmt: skip
    dask_imports = statistics.median(seconds_of("import distributed, ddsgen.distributed")[0] for _ in range(3))
    bench("dask_import_s", dask_imports, "s")
    unreachable, result = seconds_of(code)
    if result.returncode != 0 or result.stderr:
        print(f"# unreachable --scheduler: exit {result.returncode}, {result.stderr.strip()[-200:]}", flush=True)
    bench("scheduler_unreachable_s", unreachable, "s")
    bench("scheduler_unreachable_vs_import", unreachable / dask_imports, "ratio")


def main() -> None:
    png_figures()
    try:
        import distributed  # noqa: F401
    except ImportError:
        print("# scheduler figures skipped: Dask distributed is not installed", flush=True)
        return
    scheduler_figures()


if __name__ == "__main__":
    main()
