"""The project's cache folder (per-sensor pattern caches, torch.compile's kernels).

``$DDSGEN_CACHE_DIR`` if set, else ``.cache/`` at the project root. torch.compile's
Inductor cache is pointed here (TORCHINDUCTOR_CACHE_DIR) instead of /tmp, so
compiled kernels survive between runs and workers.
"""

from __future__ import annotations

import os
from pathlib import Path

from ddsgen.preset import PROJECT_ROOT


def cache_dir() -> Path:
    path = Path(os.environ.get("DDSGEN_CACHE_DIR", PROJECT_ROOT / ".cache"))
    path.mkdir(parents=True, exist_ok=True)
    return path


def configure_torch_compile_cache() -> Path:
    """Point torch.compile's Inductor cache into the project cache (unless the user chose one)."""
    path = cache_dir() / "torchinductor"
    os.environ.setdefault("TORCHINDUCTOR_CACHE_DIR", str(path))
    return Path(os.environ["TORCHINDUCTOR_CACHE_DIR"])
