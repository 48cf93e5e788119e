"""The real depth frames of ../shared/data, split into the frames kinect_v1 is tuned on and the frames only checked.

TUNE: IC-BIN seq1 and seq2 (six PrimeSense frames): the frames the preset's keys were set against.
CHECK: IC-BIN seq3, the LineMOD cat, the TUM frame and the raw NYU frame: never used to set a key, only to judge.
Realism bounds are the range of all of them (tests/test_rendered_realism.py); docs/validation.md lists the split.
"""

from pathlib import Path

import numpy as np

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"
TUNE = ("icbin_seq1_0000", "icbin_seq1_0001", "icbin_seq1_0002", "icbin_seq2_0000", "icbin_seq2_0001",
        "icbin_seq2_0002")  # fmt: skip
CHECK = ("icbin_seq3_0000", "icbin_seq3_0001", "icbin_seq3_0002", "linemod_cat", "tum", "nyu_raw")
#: The frames whose depth is registered to an RGB camera like kinect_v1's output (the NYU frame is not).
REGISTERED = TUNE + CHECK[:-1]


def nyu_raw_depth_m() -> np.ndarray:
    """(480, 640) metres of the raw NYU Kinect V1 frame, 0 = invalid (11-bit codes, little-endian, 2047 invalid)."""
    data = (SHARED / "nyu_depth_v2_raw_kinect_v1" / "NYU_depth.pgm").read_bytes()
    code = np.frombuffer(data[-640 * 480 * 2:], "<u2").reshape(480, 640).astype(np.float64)
    return np.where(code < 2047, 351.3 / (1092.5 - code), 0.0)


def real_frames() -> dict[str, tuple[np.ndarray, float]]:
    """Name -> ((480, 640) depth in metres, 0 = invalid; f b in px m) for every real frame, TUNE then CHECK."""
    import cv2

    frames = {}
    for path in sorted((SHARED / "icbin_primesense_unpaired").glob("seq*/depth/*.png")):
        frames[f"icbin_{path.parts[-3]}_{path.stem}"] = (cv2.imread(str(path), -1) / 1000.0, 550.0 * 0.075)
    cat = SHARED / "linemod_bop" / "test" / "000006" / "depth" / "000000.png"
    frames["linemod_cat"] = (cv2.imread(str(cat), -1) / 1000.0, 572.41 * 0.075)
    tum = SHARED / "tum_rgbd_frame_open3d" / "TUM_depth.png"
    frames["tum"] = (cv2.imread(str(tum), -1) / 5000.0, 525.0 * 0.075)  # TUM depth in 1/5000 m
    frames["nyu_raw"] = (nyu_raw_depth_m(), 582.62 * 0.075)  # NYU toolbox fx_d
    assert tuple(frames) == TUNE + CHECK, tuple(frames)
    return frames
