"""The files of one simulated frame in ddsgen's scan layout (README.md "Outputs"), written atomically.

Shared by ``render`` (ddsgen/runner.py) and ``compare --save-sim`` (ddsgen/realscan/save_sim.py), so
both write the same files under the same names and a saved folder reads back with
:func:`ddsgen.io.scanfolder.read_scan_folder`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ddsgen.io.exr import write_exr
from ddsgen.io.ir_png import GAMMA as IR_GAMMA
from ddsgen.io.ir_png import write_ir_png
from ddsgen.io.png import write_depth_png, write_png16

DEPTH_SCALE = 0.001  # metres per depth-PNG unit (millimetres)


def frame_paths(frame: int) -> dict[str, str]:
    """Relative paths of a frame's files in the scan layout."""
    name = f"{frame:06d}"
    return {
        "depth": f"depth/{name}.png",
        "depth_exr": f"depth/{name}.exr",
        "clean": f"clean/{name}.exr",
        "ir": f"ir/{name}.png",
        "mask": f"mask/{name}.png",
    }


def write_frame_files(out: str | Path, frame: int, depth_m, clean_m, ir, ir_max: float, instance) -> dict:
    """Write one simulated frame's files into ``out``; return their manifest keys (relative paths and
    the IR PNG's exposure ``ir_white_counts`` and ``ir_gamma``, see :mod:`ddsgen.io.ir_png`).

    Args:
        depth_m: float32 (H, W) simulated depth, metres, 0 = invalid -> depth EXR and 16-bit mm PNG.
        clean_m: float32 (H, W) noise-free depth, metres, 0 = no hit -> clean EXR.
        ir: (H, W) IR image in counts -> 8-bit PNG, auto-exposed (``ir_max``: the detector's full scale).
        instance: (H, W) integer object ids (0 = background) -> 16-bit PNG.
    """
    out = Path(out)
    paths = frame_paths(frame)
    depth = np.asarray(depth_m, dtype=np.float32)
    write_exr(out / paths["depth_exr"], depth)
    write_depth_png(out / paths["depth"], depth, DEPTH_SCALE)
    write_exr(out / paths["clean"], np.asarray(clean_m, dtype=np.float32))
    ir_white = write_ir_png(out / paths["ir"], ir, full_scale=ir_max)
    write_png16(out / paths["mask"], np.asarray(instance).astype(np.uint16))
    return {**paths, "ir_white_counts": ir_white, "ir_gamma": IR_GAMMA}
