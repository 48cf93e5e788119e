"""The simulated IR image as an 8-bit PNG that image viewers show readably and that decodes back to counts.

The sensor's IR image is in detector counts (10-bit for the Kinect: 0..1023). A dot pattern
is mostly dark between its dots, and a lit scene fills only the bottom of the detector's range:
at 0.5-1 m the median pixel is ~20 counts, the brightest dots ~600. Written linearly as
``counts / 1023 * 255`` the median pixel is 2-6 of 255 (black in any viewer), and a linear
auto-exposure that keeps the dots unsaturated still leaves it at ~10.

So each frame is written **auto-exposed and square-root encoded** (gamma 2, close to the sRGB
curve image viewers assume for 8-bit images, so brightness looks as a camera image would):

    png = round(255 * sqrt(counts / white)),   counts = white * (png / 255) ** 2

where ``white`` (:func:`ir_white_counts`) is the frame's :data:`EXPOSURE_PERCENTILE` th percentile
(brighter pixels saturate at 255: the brightest 0.1 %). ``white`` and the gamma go into the
frame's manifest record (``ir_white_counts``, ``ir_gamma``). Decoding is exact to one
quantisation step, ``white * (2 png + 1) / 255^2`` counts: finer than one count below
``white / 4``, where most pixels are. Deterministic: ``white`` depends on the frame's IR image only.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ddsgen.io.png import read_png8, write_png8

#: Percentile of a frame's IR counts shown as white (255); brighter pixels saturate.
EXPOSURE_PERCENTILE = 99.9
#: PNG value = 255 * (counts / white) ** (1 / GAMMA).
GAMMA = 2.0
#: Significant digits kept of ``white`` (the manifest states exactly the value the PNG was written with).
WHITE_DIGITS = 6


def ir_white_counts(counts: np.ndarray, full_scale: float) -> float:
    """The counts shown as white (PNG 255) for one frame.

    Args:
        counts: float (H, W) IR image in detector counts.
        full_scale: the detector's largest count (2^bits - 1); a black frame gets it.

    Returns:
        the :data:`EXPOSURE_PERCENTILE` th percentile of ``counts`` (> 0, at most ``full_scale``),
        rounded to :data:`WHITE_DIGITS` significant digits.
    """
    values = np.asarray(counts, dtype=np.float64)
    top = float(np.percentile(values, EXPOSURE_PERCENTILE)) if values.size else 0.0
    if not np.isfinite(top) or top <= 0.0:
        top = full_scale
    return float(f"{min(top, full_scale):.{WHITE_DIGITS}g}")


def encode_ir(counts: np.ndarray, white: float) -> np.ndarray:
    """float (H, W) counts -> uint8 (H, W): ``round(255 * sqrt(counts / white))``, clipped to [0, 255]."""
    relative = np.clip(np.asarray(counts, dtype=np.float64) / white, 0.0, 1.0)
    return np.floor(255.0 * relative ** (1.0 / GAMMA) + 0.5).astype(np.uint8)


def decode_ir(values: np.ndarray, white: float, gamma: float = GAMMA) -> np.ndarray:
    """uint8 (H, W) PNG values -> float32 (H, W) counts: ``white * (values / 255) ** gamma``."""
    return (white * (np.asarray(values, dtype=np.float64) / 255.0) ** gamma).astype(np.float32)


def write_ir_png(path: str | Path, counts: np.ndarray, full_scale: float) -> float:
    """Write ``counts`` (float (H, W), detector counts) auto-exposed and encoded; return its ``white``."""
    white = ir_white_counts(counts, full_scale)
    write_png8(path, encode_ir(counts, white))
    return white


def read_ir_counts(path: str | Path, white: float, gamma: float = GAMMA,
                   expected_shape: tuple[int, int] | None = None) -> np.ndarray:  # fmt: skip
    """Read an IR PNG written by :func:`write_ir_png` back to float32 (H, W) detector counts."""
    return decode_ir(read_png8(path, expected_shape), white, gamma)
