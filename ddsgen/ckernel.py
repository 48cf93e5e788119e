"""Build and load ddsgen's C sources (package data) with the system C compiler, through ctypes.

A library is compiled once per source, compiler, flags and CPU, cached in ddsgen's cache folder
(:func:`ddsgen.cache.cache_dir`, ``kernels/``), and loaded once per process. :func:`load_c_library`
returns None when there is no compiler (``$CC``, default ``cc``) or ``DDSGEN_NO_C_KERNEL`` is set; every
caller has a pure-Python (numpy / torch / Embree) path that gives the same results.
"""

from __future__ import annotations

import ctypes
import hashlib
import logging
import os
import platform
import subprocess
import tempfile
from importlib.resources import files
from pathlib import Path

from ddsgen.cache import cache_dir

log = logging.getLogger(__name__)


def cpu_tag() -> str:
    """The CPU's feature flags (``-march=native`` code is only valid on a CPU with the same ones)."""
    try:
        with open("/proc/cpuinfo", encoding="utf-8", errors="replace") as handle:
            for line in handle:
                if line.startswith("flags"):
                    return line
    except OSError:
        pass
    return platform.processor() or platform.machine()


def c_source(package: str, *path: str) -> bytes:
    """A C source shipped as package data, e.g. ``c_source("ddsgen", "csrc", "raster.c")``."""
    return files(package).joinpath(*path).read_bytes()


def load_c_library(source: bytes, stem: str, flags: list[str], what: str, fallback: str) -> ctypes.CDLL | None:
    """Compile ``source`` (cached as ``kernels/<stem>_<hash>.so``) and load it.

    Returns None, after one warning naming ``what`` and the ``fallback`` that runs instead, when compiling
    fails (no compiler, no OpenMP), and without a warning when ``DDSGEN_NO_C_KERNEL`` is set. The file appears atomically, so concurrent
    worker processes never load half of one.
    """
    if os.environ.get("DDSGEN_NO_C_KERNEL"):
        return None
    compiler = os.environ.get("CC", "cc")
    try:
        digest = hashlib.sha256(source + "\n".join(["", compiler, *flags, cpu_tag()]).encode()).hexdigest()[:16]
        folder = cache_dir() / "kernels"
        lib_path = folder / f"{stem}_{digest}.so"
        if not lib_path.exists():
            folder.mkdir(parents=True, exist_ok=True)
            with tempfile.TemporaryDirectory(dir=folder) as tmp:
                src = Path(tmp) / f"{stem}.c"
                src.write_bytes(source)
                out = Path(tmp) / f"{stem}.so"
                subprocess.run([compiler, *flags, str(src), "-o", str(out), "-lm"],
                               check=True, capture_output=True, timeout=120)  # fmt: skip
                os.replace(out, lib_path)
        return ctypes.CDLL(str(lib_path))
    except (OSError, subprocess.SubprocessError) as error:
        log.warning("ddsgen %s: C kernel unavailable (%s); using the %s", what, error, fallback)
        return None


#: Flags of the kernels that repeat a torch or numpy definition's float32 operations one by one: no FMA contraction
#: (which would fuse a multiply and an add into one rounding), -fno-math-errno only so that sqrtf can vectorise.
EXACT_FLOAT_FLAGS = ["-O3", "-march=native", "-ffp-contract=off", "-fno-math-errno", "-fPIC", "-shared", "-std=gnu11"]


def load_exact_c_library(package: str, filename: str, what: str, fallback: str,
                         signatures: dict[str, list]) -> ctypes.CDLL | None:  # fmt: skip
    """``package``'s ``csrc/filename`` compiled with :data:`EXACT_FLOAT_FLAGS` (:func:`load_c_library`), each
    function of ``signatures`` (name -> ctypes argument types) declared returning nothing; None as there."""
    stem = filename.rsplit(".", 1)[0]
    lib = load_c_library(c_source(package, "csrc", filename), stem, EXACT_FLOAT_FLAGS, what, fallback)
    if lib is not None:
        for name, argtypes in signatures.items():
            function = getattr(lib, name)
            function.argtypes, function.restype = argtypes, None
    return lib
