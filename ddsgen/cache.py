"""ddsgen's cache folder: the compiled matcher kernel and torch.compile's kernels.

``$DDSGEN_CACHE_DIR`` if set, else the user's cache directory for this version of ddsgen
(platformdirs: ``~/.cache/ddsgen/<version>`` on Linux, ``~/Library/Caches/ddsgen/<version>``
on macOS), so nothing is written into site-packages or the current folder. The version
sub-folder keeps what different releases compiled apart. Writers put a file in place
atomically (a temporary file in the same folder, then ``os.replace``), so concurrent
render workers never read half a file. torch.compile's Inductor cache is pointed here
(TORCHINDUCTOR_CACHE_DIR) instead of /tmp, so compiled kernels survive between runs.
"""

from __future__ import annotations

import os
from pathlib import Path

import platformdirs

from ddsgen import __version__


def cache_dir() -> Path:
    """The cache folder (created if missing)."""
    override = os.environ.get("DDSGEN_CACHE_DIR")
    path = Path(override).expanduser() if override else Path(platformdirs.user_cache_dir("ddsgen")) / __version__
    path.mkdir(parents=True, exist_ok=True)
    return path


def configure_torch_compile_cache() -> Path:
    """Point torch.compile's Inductor cache into ddsgen's cache (unless the user chose one)."""
    path = cache_dir() / "torchinductor"
    os.environ.setdefault("TORCHINDUCTOR_CACHE_DIR", str(path))
    return Path(os.environ["TORCHINDUCTOR_CACHE_DIR"])
