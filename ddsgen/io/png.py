"""PNG files: 16-bit depth (millimetres by default, 0 = invalid), 16-bit instance masks, 8-bit previews.

Encoding goes through ``cv2.imencode``, decoding through ``io/images.py`` (so paths
with any characters work; bad files are one line, without library noise) and writes are atomic. Identical input gives identical
bytes with a given OpenCV build (fixed encoder parameters :data:`PNG_PARAMS`,
no time stamps).
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from ddsgen.errors import InputError
from ddsgen.atomic import atomic_write_bytes
from ddsgen.io.images import read_image

#: cv2.imencode parameters. Empty = OpenCV's defaults, measured fastest here
#: (about 5 ms for a 640x480 uint16 depth image) and deterministic.
PNG_PARAMS: list[int] = []

UINT16_MAX = 65535


def _encode(path, array: np.ndarray) -> None:
    ok, buffer = cv2.imencode(".png", np.ascontiguousarray(array), PNG_PARAMS)
    if not ok:  # pragma: no cover - cv2 only fails on unsupported dtypes, which we exclude
        raise ValueError(f"{path}: PNG encoding failed")
    atomic_write_bytes(path, buffer.tobytes())


def _check_2d(path, array: np.ndarray, what: str) -> None:
    if array.ndim != 2 or array.size == 0:
        raise ValueError(f"{path}: {what} needs a non-empty (H, W) array, got shape {array.shape}")


def depth_to_units(depth_m, depth_scale: float = 0.001) -> np.ndarray:
    """Metres (H, W) -> uint16 units of ``depth_scale`` metres (mm by default).

    Rounds to the nearest unit (halves up). 0 stays 0 (invalid); negative
    values and values beyond 65535 units become 0 (invalid) rather than
    wrapping or saturating. NaN/inf raise ``ValueError`` (write invalid as 0).
    """
    if not depth_scale > 0:
        raise ValueError(f"depth_scale must be > 0, got {depth_scale}")
    depth = np.asarray(depth_m, dtype=np.float64)
    if not np.isfinite(depth).all():
        raise ValueError("depth has NaN/inf values; write invalid pixels as 0")
    units = np.floor(depth / depth_scale + 0.5)
    units[(units < 0) | (units > UINT16_MAX)] = 0
    return units.astype(np.uint16)


def write_depth_png(path: str | Path, depth_m, depth_scale: float = 0.001) -> None:
    """Write depth in metres (H, W) as a 16-bit PNG of ``depth_scale``-metre units (see :func:`depth_to_units`)."""
    units = depth_to_units(depth_m, depth_scale)
    _check_2d(path, units, "write_depth_png")
    _encode(path, units)


def _decode(path: str | Path, what: str) -> np.ndarray:
    """Decode through :func:`ddsgen.io.images.read_image`: one line on a bad file, no library noise on stderr."""
    return read_image(path, f"{what} PNG")


def _check_single_channel(path, image: np.ndarray, dtype, what: str, expected_shape) -> None:
    bits = {np.dtype(np.uint8): "8-bit", np.dtype(np.uint16): "16-bit"}.get(image.dtype, str(image.dtype))
    wanted_bits = {np.dtype(np.uint8): "8-bit", np.dtype(np.uint16): "16-bit"}[np.dtype(dtype)]
    if image.ndim != 2:
        raise InputError(
            f"{path}: {what} PNG must be single-channel {wanted_bits}, got {image.shape[2]} channels ({bits})"
        )
    if image.dtype != dtype:
        raise InputError(f"{path}: {what} PNG must be {wanted_bits} single-channel, got {bits}")
    if expected_shape is not None and tuple(image.shape) != tuple(int(s) for s in expected_shape):
        h, w = image.shape
        eh, ew = expected_shape
        raise InputError(f"{path}: {what} PNG is {w}x{h} px, expected {int(ew)}x{int(eh)} (width x height)")


def read_png16(path: str | Path, expected_shape: tuple[int, int] | None = None, what: str = "image") -> np.ndarray:
    """Read a single-channel 16-bit PNG -> uint16 (H, W).

    ``expected_shape`` = (H, W) if known. Missing, corrupt, 8-bit, colour or
    wrong-size files raise :class:`InputError` naming the file and the problem.
    """
    image = _decode(path, what)
    _check_single_channel(path, image, np.uint16, what, expected_shape)
    return image


def read_depth_png(
    path: str | Path, depth_scale: float = 0.001, expected_shape: tuple[int, int] | None = None
) -> np.ndarray:
    """Read a 16-bit depth PNG -> float32 metres (H, W), ``png * depth_scale``; 0 stays 0 (invalid).

    ``depth_scale`` is metres per PNG unit (0.001 for millimetres). Errors as :func:`read_png16`.
    """
    if not depth_scale > 0:
        raise ValueError(f"depth_scale must be > 0, got {depth_scale}")
    units = read_png16(path, expected_shape, what="depth")
    return (units.astype(np.float64) * depth_scale).astype(np.float32)


def write_png16(path: str | Path, array) -> None:
    """Write an integer (H, W) array with values in [0, 65535] (e.g. instance ids) as a 16-bit PNG."""
    array = np.asarray(array)
    _check_2d(path, array, "write_png16")
    if array.dtype != np.uint16:
        if array.dtype.kind not in "biu":
            raise ValueError(f"{path}: write_png16 needs an integer array, got {array.dtype}")
        if array.size and (array.min() < 0 or array.max() > UINT16_MAX):
            raise ValueError(f"{path}: write_png16 values must lie in [0, 65535]")
        array = array.astype(np.uint16)
    _encode(path, array)


def to_uint8(image, max_value: float | None = None) -> np.ndarray:
    """uint8 stays as is; other arrays map [0, max_value] -> [0, 255] (clipped, rounded)."""
    array = np.asarray(image)
    if array.dtype == np.uint8:
        return array
    if max_value is None:
        raise ValueError(f"a {array.dtype} image needs max_value to be scaled to 8 bits")
    if not (np.isfinite(max_value) and max_value > 0):
        raise ValueError(f"max_value must be finite and > 0, got {max_value}")
    values = np.asarray(array, dtype=np.float64)
    if not np.isfinite(values).all():
        raise ValueError("image has NaN/inf values")
    return np.floor(np.clip(values / max_value, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


def write_png8(path: str | Path, image, max_value: float | None = None) -> None:
    """Write an 8-bit single-channel PNG (e.g. an IR preview).

    uint8 input is written as is; any other (H, W) array is scaled so that
    ``max_value`` -> 255 (clipped, rounded; e.g. ``max_value=1023`` for 10-bit IR counts).
    """
    array = to_uint8(image, max_value)
    _check_2d(path, array, "write_png8")
    _encode(path, array)


def read_png8(path: str | Path, expected_shape: tuple[int, int] | None = None) -> np.ndarray:
    """Read a single-channel 8-bit PNG -> uint8 (H, W); errors as :func:`read_png16`."""
    image = _decode(path, "image")
    _check_single_channel(path, image, np.uint8, "image", expected_shape)
    return image
