"""Read a folder of plain real depth images: 16-bit PNG (units x depth_scale) or EXR (metres).

No manifest, no poses: every ``*.png`` / ``*.exr`` below the folder (recursive, sorted) is a
depth frame -- except that when sub-folders named ``depth`` exist (the BOP / IC-BIN layout,
``seq/depth/*.png`` next to ``seq/rgb/*.png``), only the images inside them are, and that a PNG and an EXR of the
same name in one folder are one frame written twice (a ddsgen render's ``depth/``): the EXR (metres, not rounded) is
read. Any other PNG that is not single-channel 16-bit is refused with one line naming the file.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ddsgen.errors import InputError
from ddsgen.io.exr import read_exr
from ddsgen.io.png import read_depth_png

DEPTH_SUFFIXES = (".png", ".exr")
#: Metres per PNG unit of a folder's depth images unless told (millimetres, as most devices write).
DEFAULT_DEPTH_SCALE_M = 0.001


@dataclass
class RealDepthFrame:
    """One real depth frame: ``name`` (path relative to the folder), ``depth`` (H, W) float32 m
    (0 = invalid), ``resolution_m`` (rounding unit of the stored values: depth_scale for PNG, 0
    for EXR)."""

    name: str
    depth: np.ndarray
    resolution_m: float


def depth_files(folder: str | Path) -> list[Path]:
    """Sorted depth image paths below ``folder`` (recursive), one per frame (see the module docstring)."""
    folder = Path(folder)
    images = sorted(p for p in folder.rglob("*") if p.is_file() and p.suffix.lower() in DEPTH_SUFFIXES)
    in_depth_folders = [p for p in images if "depth" in p.relative_to(folder).parts[:-1]]
    images = in_depth_folders or images
    # The same frame as PNG and EXR: counted twice it would also sit on both sides of a held-out split.
    exr_stems = {p.with_suffix("") for p in images if p.suffix.lower() == ".exr"}
    return [p for p in images if p.suffix.lower() == ".exr" or p.with_suffix("") not in exr_stems]


def read_depth_folder(folder: str | Path, depth_scale: float = DEFAULT_DEPTH_SCALE_M) -> list[RealDepthFrame]:
    """All depth frames below ``folder``; they must share one image size.

    Raises:
        InputError: no depth image, an unreadable/non-16-bit file, sizes that differ,
            a frame without any valid pixel.
    """
    if not depth_scale > 0:
        raise InputError(f"--depth-scale: {depth_scale}: must be > 0 (metres per PNG unit)")
    paths = depth_files(folder)
    if not paths:
        raise InputError(f"{folder}: no depth images (*.png, *.exr) found below this folder")
    frames = []
    for path in paths:
        if path.suffix.lower() == ".exr":
            depth, resolution = read_exr(path), 0.0
        else:
            depth, resolution = read_depth_png(path, depth_scale), depth_scale
        depth = np.where(np.isfinite(depth) & (depth > 0), depth, 0).astype(np.float32)
        if frames and depth.shape != frames[0].depth.shape:
            raise InputError(f"{path}: image size {depth.shape[1]}x{depth.shape[0]} differs from "
                             f"{frames[0].name}'s {frames[0].depth.shape[1]}x{frames[0].depth.shape[0]}")  # fmt: skip
        if not (depth > 0).any():
            raise InputError(f"{path}: depth: no valid pixel (all zero)")
        frames.append(RealDepthFrame(str(path.relative_to(folder)), depth, resolution))
    return frames


def round_like(depth_m: np.ndarray, resolution_m: float) -> np.ndarray:
    """Round simulated depth to the real files' storage unit (a PNG in mm rounds to 1 mm), so
    quantisation features compare like with like. 0 stays 0."""
    if resolution_m <= 0:
        return np.asarray(depth_m, np.float32)
    return (np.round(np.asarray(depth_m, np.float64) / resolution_m) * resolution_m).astype(np.float32)
