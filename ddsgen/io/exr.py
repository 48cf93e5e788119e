"""Single-channel float32 EXR files (depth in metres, 0 = invalid; never NaN).

Uses the OpenEXR Python bindings (``OpenEXR.File``, OpenEXR >= 3.3): the OpenCV
wheel is built without EXR support. Files are scanline, ZIP-compressed, one
FLOAT channel named ``"Z"``. Identical input gives identical bytes (no time
stamps in the header; ZIP is deterministic), which keeps datasets
byte-identical across runs and worker counts.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ddsgen.errors import InputError
from ddsgen.atomic import atomic_path

#: Channel names accepted by :func:`read_exr`, in order of preference.
PREFERRED_CHANNELS = ("Z", "Y", "R", "depth", "Depth", "G", "B")


def write_exr(path: str | Path, image, channel: str = "Z") -> None:
    """Write ``image`` (H, W) as a float32 single-channel ZIP EXR, atomically.

    ``image`` is anything ``np.asarray`` accepts (numpy array, CPU tensor);
    it is converted to float32. Raises ``ValueError`` for a non-2-D or empty
    array and for NaN/inf values (invalid depth must be written as 0).
    """
    import OpenEXR

    array = np.ascontiguousarray(np.asarray(image, dtype=np.float32))
    if array.ndim != 2 or array.size == 0:
        raise ValueError(f"{path}: write_exr needs a non-empty (H, W) array, got shape {array.shape}")
    if not np.isfinite(array).all():
        raise ValueError(f"{path}: write_exr: image has NaN/inf values; write invalid pixels as 0")
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with atomic_path(path) as tmp:
        OpenEXR.File(header, {channel: array}, num_threads=1).write(str(tmp))


def _pick_channel(names: list[str]) -> str | None:
    if len(names) == 1:
        return names[0]
    for wanted in PREFERRED_CHANNELS:
        for name in names:  # exact name, or a layer-qualified one such as "depth.Z"
            if name == wanted or name.rsplit(".", 1)[-1] == wanted:
                return name
    return names[0] if names else None


def read_exr(path: str | Path) -> np.ndarray:
    """Read the depth channel of an EXR file -> float32 (H, W).

    Takes the only channel, else the first of :data:`PREFERRED_CHANNELS`
    (``Z``, ``Y``, ``R``, ...; so RGB files give their R channel). Half and
    uint channels are converted to float32; NaN/inf (other tools' "invalid")
    become 0, the project's convention. A missing, unreadable or corrupt
    file raises :class:`InputError` ``"PATH: cannot read EXR (...)"``.
    """
    import OpenEXR

    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: cannot read EXR (no such file)")
    try:
        exr = OpenEXR.File(str(path), separate_channels=True, num_threads=1)
        channels = exr.channels()
        name = _pick_channel(list(channels))
        if name is None:
            raise InputError(f"{path}: cannot read EXR (no channels)")
        pixels = np.asarray(channels[name].pixels)
    except InputError:
        raise
    except Exception as exc:  # the bindings raise RuntimeError/ValueError for bad files
        raise InputError(f"{path}: cannot read EXR ({type(exc).__name__}: {exc})") from None
    if pixels.ndim != 2 or pixels.size == 0:
        raise InputError(f"{path}: cannot read EXR (channel {name!r} has shape {pixels.shape})")
    out = np.array(pixels, dtype=np.float32)  # a fresh, writable, C-contiguous copy
    out[~np.isfinite(out)] = 0.0  # foreign files may mark invalid depth with NaN/inf; ours use 0
    return out
