"""Holes at depth jumps: where a structured-light depth frame leaves a near surface's edge open, and on which side.

Three statistics of :func:`ddsgen.depth_statistics.realism_statistics` (definitions as in docs/validation.md):

* **holes at depth jumps**: along each image row, a *jump* is a near surface beside a far one
  (depths differing by more than ``JUMP_MIN_RELATIVE`` = 6 %, each flat over ``JUMP_FLAT_PX`` = 4
  valid pixels), with at most ``JUMP_MAX_GAP_PX`` invalid pixels between them. The statistic is
  the share of jumps that have a hole between the surfaces, separately for jumps whose near
  surface lies to the right (the hole is on its left: the side of a projector shadow when the
  projector sits at +x, as on a Kinect) and to the left. Geometry predicts a shadow hole of
  f b (1/z_near - 1/z_far) px on the left side of every near surface; the real frames have
  one at 9-58 % of such jumps (the matcher and the device fill the rest).

* **wide registration bands kept open**: depth registered to the RGB camera (LineMOD, IC-BIN, TUM, kinect_v1) has a
  band right of every near surface that the IR camera does not see, f b_r (1/z_near - 1/z_far) px wide (f b_r:
  ``KINECT_FOCAL_REGISTRATION_PX_M``). Along each row, a jump with the near surface on the left, only invalid pixels
  (at most ``JUMP_MAX_GAP_PX``) between, an edge within 45 deg of vertical (a jump of the same sign within
  ``BAND_EDGE_COLUMNS`` columns two rows above and below), and a band predicted from the two measured depths of at
  least ``WIDE_BAND_PX`` = 6 px. The statistic is the share of those jumps with a hole between the surfaces. Real
  frames keep nearly all such bands open (IC-BIN 0.98 pooled, the cat 0.93; bands up to 3-4 px are closed nine times
  in ten): a simulation that closes them draws the far surface, or the near one, where the device shows nothing.

* **narrow registration bands left as a slit**: the same jumps with a predicted band of 3-6 px
  (``NARROW_BAND_PX``), and the share of them with 1-2 invalid pixels (``SLIT_PX``) between the surfaces. Three
  real devices agree (docs/validation.md): IC-BIN 0.23 pooled, the LineMOD cat 0.15, TUM 0.14; row by row
  a 3-4 px band closes in 66-90 % of the rows and leaves a slit in 8-12 %, a 4-6 px band a slit in 13-22 %, one
  row here and there: most of the real frames' 1-2 px holes right of near surfaces (6 a frame on each device).
"""

from __future__ import annotations

import cv2
import numpy as np

JUMP_MIN_RELATIVE = 0.06
JUMP_FLAT_PX = 4
JUMP_MAX_GAP_PX = 40
#: f b_r of a registered Kinect V1 (px m): the IR camera sits b_r = 27 mm from the RGB camera (kinect_v1.yaml).
KINECT_FOCAL_REGISTRATION_PX_M = 572.41 * 0.027
WIDE_BAND_PX = 6.0
#: The narrow bands of :func:`narrow_band_slits` (px, [lo, hi)) and the slit it counts (invalid px, inclusive).
NARROW_BAND_PX = (3.0, 6.0)
SLIT_PX = (1, 2)
BAND_EDGE_COLUMNS = 3
#: Flatness tolerance of the surfaces on either side of a jump (m).
_JUMP_FLAT_M = 0.02


def region_or_all(shape, region) -> np.ndarray:
    """(H, W) bool: ``region``, or every pixel when it is None (the statistics' ``region`` argument)."""
    return np.ones(shape, bool) if region is None else np.asarray(region, bool)


def holes_at_depth_jumps(depth_m: np.ndarray, region: np.ndarray | None = None) -> tuple[float | None, float | None]:
    """(left, right): share of the horizontal depth jumps with invalid pixels between the two surfaces,
    for near surfaces on the right of the jump (hole on their left) and on its left; None without jumps.

    Args:
        depth_m: (H, W) metres, 0 = invalid.
        region: (H, W) bool or None; a jump counts when both its ends lie in it.
    """
    depth = np.asarray(depth_m, np.float64)
    region = region_or_all(depth.shape, region)
    height, width = depth.shape
    with_hole = {"left": [], "right": []}
    offsets = np.arange(JUMP_FLAT_PX)
    for y in range(height):
        row = depth[y]
        cols = np.flatnonzero(row > 0)
        a, b = cols[:-1], cols[1:]  # consecutive valid pixels, with b - a - 1 invalid ones between
        za, zb = row[a], row[b]
        jump = ((b - a - 1) <= JUMP_MAX_GAP_PX) & (np.abs(za - zb) > JUMP_MIN_RELATIVE * np.minimum(za, zb))
        jump &= (a >= JUMP_FLAT_PX - 1) & (b <= width - JUMP_FLAT_PX) & region[y, a] & region[y, b]
        a, b, za, zb = a[jump], b[jump], za[jump], zb[jump]
        if not len(a):
            continue
        before = row[a[:, None] - offsets]  # (n, JUMP_FLAT_PX): the surface ending at a
        after = row[b[:, None] + offsets]
        flat = (np.abs(before - za[:, None]) < _JUMP_FLAT_M).all(1) & (np.abs(after - zb[:, None]) < _JUMP_FLAT_M).all(1)
        hole = (b - a - 1) > 0
        near_on_right = zb < za
        with_hole["left"].append(hole[flat & near_on_right])
        with_hole["right"].append(hole[flat & ~near_on_right])
    shares = []
    for side in ("left", "right"):
        holes = np.concatenate(with_hole[side]) if with_hole[side] else np.zeros(0, bool)
        shares.append(float(holes.mean()) if len(holes) else None)
    return shares[0], shares[1]


def registration_band_jumps(depth_m: np.ndarray, region: np.ndarray | None = None,
                            focal_registration_px_m: float = KINECT_FOCAL_REGISTRATION_PX_M) -> tuple[np.ndarray, np.ndarray]:
    """(bands, gaps), each (N,): the near-left depth jumps on near-vertical edges (see the module docstring), their
    predicted registration band f b_r (1/z_near - 1/z_far) (px, >= 1) and the invalid pixels between the two
    surfaces (px, 0 = closed).

    Args:
        depth_m: (H, W) metres, 0 = invalid.
        region: (H, W) bool or None; a jump counts when both its ends lie in it.
    """
    depth = np.asarray(depth_m, np.float64)
    region = region_or_all(depth.shape, region)
    height, width = depth.shape
    inverse = np.where(depth > 0, 1.0 / np.where(depth > 0, depth, 1.0), 0.0).reshape(-1)
    valid = np.flatnonzero(inverse > 0)  # row-major: consecutive entries of one row are left to right
    a, b = valid[:-1], valid[1:]  # consecutive valid pixels, with b - a - 1 invalid ones between
    band = focal_registration_px_m * (inverse[a] - inverse[b])  # > 0: the near surface is on the left
    keep = (a // width == b // width) & ((b - a - 1) <= JUMP_MAX_GAP_PX) & (np.abs(band) >= 1.0)
    a, b, bands = a[keep], b[keep], band[keep]
    rows, lefts, rights = a // width, a % width, b % width
    centres = (lefts + rights) // 2
    # Jumps of each sign, widened by BAND_EDGE_COLUMNS along the row: the same edge two rows up and down.
    kernel = np.ones((1, 2 * BAND_EDGE_COLUMNS + 1), np.uint8)
    near_left = np.zeros((height, width), np.uint8)
    near_left[rows[bands > 0], centres[bands > 0]] = 1
    near_left = cv2.dilate(near_left, kernel).astype(bool)
    inner = (bands > 0) & (rows >= 2) & (rows < height - 2)
    rows, lefts, rights, centres, bands = rows[inner], lefts[inner], rights[inner], centres[inner], bands[inner]
    vertical = near_left[rows - 2, centres] & near_left[rows + 2, centres]
    counted = vertical & region[rows, lefts] & region[rows, rights]
    return bands[counted], (rights - lefts - 1)[counted]


def band_outcomes(bands: np.ndarray, gaps: np.ndarray) -> tuple[int, int, int, int]:
    """(wide kept open, wide, narrow left as a slit, narrow) counts of :func:`registration_band_jumps`' jumps:
    bands of at least ``WIDE_BAND_PX`` with any invalid pixel between the surfaces, and bands of ``NARROW_BAND_PX``
    with ``SLIT_PX`` invalid pixels between them."""
    wide = bands >= WIDE_BAND_PX
    narrow = (bands >= NARROW_BAND_PX[0]) & (bands < NARROW_BAND_PX[1])
    slit = (gaps >= SLIT_PX[0]) & (gaps <= SLIT_PX[1])
    return int((gaps[wide] > 0).sum()), int(wide.sum()), int(slit[narrow].sum()), int(narrow.sum())


def wide_band_holes(depth_m: np.ndarray, region: np.ndarray | None = None) -> tuple[int, int]:
    """(with_hole, jumps): the near-left depth jumps on near-vertical edges whose predicted registration band
    f b_r (1/z_near - 1/z_far) is at least ``WIDE_BAND_PX``, and how many of them keep invalid pixels between the
    two surfaces (see the module docstring). ``depth_m``: (H, W) metres, 0 = invalid; ``region``: (H, W) bool or
    None, a jump counts when both its ends lie in it."""
    return band_outcomes(*registration_band_jumps(depth_m, region))[:2]


def narrow_band_slits(depth_m: np.ndarray, region: np.ndarray | None = None) -> tuple[int, int]:
    """(slits, jumps): the near-left depth jumps on near-vertical edges whose predicted registration band is
    ``NARROW_BAND_PX`` (3-6 px), and how many of them leave a slit of ``SLIT_PX`` (1-2) invalid pixels between the
    two surfaces (see the module docstring); arguments as :func:`wide_band_holes`."""
    return band_outcomes(*registration_band_jumps(depth_m, region))[2:]
