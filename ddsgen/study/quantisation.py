"""Depth quantisation in the noise study: the step a disparity quantum predicts, the step a depth image shows, and
the real Kinect V1's depth values.

A disparity quantum of 2^-n px gives depth levels z^2 / (2^n f b) apart (:func:`quantisation_step`; the device's 1/8 px
gives z^2 / (8 f b)). :func:`lattice_step` measures the spacing of the distinct depth values near z, :func:`local_steps`
the spacing along the whole range; :func:`real_quantisation` reads the real device's values (the LineMOD frame's and
the list a Kinect for Windows can output, from ../shared/data) for the study's check.
"""

from __future__ import annotations

import dataclasses
import os
from importlib.resources import files
from pathlib import Path

import numpy as np

from ddsgen.errors import InputError
from ddsgen.io.images import read_image

#: Real depth data for the quantisation check: $DDSGEN_SHARED_DATA, else shared/data beside the
#: source checkout (absent in a wheel install: the check is then skipped with a message).
SHARED_DATA = Path(os.environ.get("DDSGEN_SHARED_DATA") or Path(str(files("ddsgen"))).parents[1] / "shared" / "data")
LINEMOD_DEPTH = SHARED_DATA / "linemod_bop" / "test" / "000006" / "depth" / "000000.png"
DISTREAL_MM = SHARED_DATA / "kinect_v1_landau_simulator_data" / "distReal_mm.txt"


def quantisation_step(z, focal_px: float, baseline_m: float, subpixel_level: int):
    """Depth step of one disparity quantum 2^-n px at depth z: z^2 / (2^n f b) (m)."""
    return np.asarray(z, dtype=np.float64) ** 2 / (2.0**subpixel_level * focal_px * baseline_m)


def _gap_free_mean(diffs: np.ndarray, resolution: float) -> float:
    """Mean of consecutive differences, leaving out gaps (> 1.5 x their median + the values' resolution)."""
    return float(diffs[diffs <= 1.5 * np.median(diffs) + resolution].mean())


def lattice_step(values: np.ndarray, z: float, tolerance: float = 0.05, resolution: float = 0.0) -> float | None:
    """Spacing of the distinct depth values near z (m), or None when fewer than two are found.

    Distinct values (rounded to 1 um) within ``tolerance`` * z of z; consecutive differences larger than 1.5
    times their median plus ``resolution`` (the rounding unit of the values, e.g. 1 mm for 16-bit PNG
    millimetres, whose steps alternate e.g. 1, 2, 1, 2 mm) are gaps (values nobody output), not steps, and are
    left out; the step is the mean of the rest.
    """
    values = np.unique(np.round(np.asarray(values, dtype=np.float64), 6))
    near = values[np.abs(values - z) <= tolerance * z]
    if len(near) < 2:
        return None
    diffs = np.diff(near)
    return _gap_free_mean(diffs, resolution)


def local_steps(values: np.ndarray, resolution: float = 0.0, window: int = 9) -> tuple[np.ndarray, np.ndarray]:
    """(depths, steps): the gap-free mean step of each run of ``window`` consecutive distinct values."""
    values = np.unique(np.asarray(values, dtype=np.float64))
    if len(values) < window + 1:
        return np.zeros(0), np.zeros(0)
    diffs = np.lib.stride_tricks.sliding_window_view(np.diff(values), window)
    centres = np.lib.stride_tricks.sliding_window_view(values, window + 1).mean(axis=1)
    steps = np.array([_gap_free_mean(d, resolution) for d in diffs])
    return centres, steps


@dataclasses.dataclass
class RealQuantisation:
    """Distinct depth values of real Kinect V1 output (m), for the quantisation check."""

    linemod: np.ndarray | None  # distinct values of the real LineMOD frame (OpenNI, whole mm)
    distreal: np.ndarray | None  # the values a real Kinect for Windows can output (Landau et al.)
    messages: list[str]

    def step_at(self, z: float) -> dict[str, float | None]:
        out = {}
        for name in ("linemod", "distreal"):
            values = getattr(self, name)
            out[name] = lattice_step(values, z, resolution=1e-3) if values is not None else None
        return out


def real_quantisation(linemod_png: Path | str | None = LINEMOD_DEPTH, distreal_txt: Path | str | None = DISTREAL_MM):
    """Read the real depth values; a missing file gives None and a message (the check is then skipped)."""
    messages = []
    linemod = distreal = None
    if linemod_png is not None and Path(linemod_png).is_file():
        try:
            image = read_image(linemod_png, "depth PNG")  # a corrupt file: our message, no library noise on stderr
        except InputError:
            image = None
        if image is None or image.dtype != np.uint16:
            messages.append(f"{linemod_png}: not a 16-bit depth PNG; LineMOD quantisation check skipped")
        else:
            linemod = np.unique(image[image > 0]).astype(np.float64) / 1000.0
    else:
        messages.append(f"{linemod_png}: not found; LineMOD quantisation check skipped")
    if distreal_txt is not None and Path(distreal_txt).is_file():
        try:
            distreal = np.unique(np.loadtxt(distreal_txt, dtype=np.float64)) / 1000.0
        except ValueError as error:
            messages.append(f"{distreal_txt}: unreadable ({error}); real value-list check skipped")
    else:
        messages.append(f"{distreal_txt}: not found; real Kinect value-list check skipped")
    return RealQuantisation(linemod, distreal, messages)
