"""The device's clean-up of its disparity map: small specks of valid pixels and small holes removed.

A Kinect V1 does not output the salt-and-pepper of a bare block matcher: its invalid pixels
come in clusters (shadows, dark and far surfaces, edges). Three morphological passes, all
OpenCV's, model that:

* **speckle filter** (``cv2.filterSpeckles``): a connected region of valid pixels whose
  disparities differ by at most ``max_diff_px`` between neighbours, smaller than
  ``speckle_px`` pixels, is a lone wrong match and is invalidated;
* **hole filling** (``cv2.connectedComponentsWithStats`` + ``cv2.distanceTransformWithLabels``):
  an 8-connected component of invalid pixels smaller than ``hole_px`` pixels *inside one
  surface* takes the disparity of its nearest valid pixel. A hole is inside one surface when
  the valid pixels around it (its rim) are one region by ``cv2.filterSpeckles``' rule: 8-adjacent
  rim pixels differ by at most ``max_diff_px``. A hole at a depth edge keeps its pixels. The
  real frames say so: the isolated holes of the ten real Kinect V1 / PrimeSense frames in
  ../shared/data sit at depth edges (median rim disparity range 6.7 px; 17 % within 1 px),
  while a bare block matcher's flat-surface holes have rims within 0.1-0.3 px.
* **narrow fill** (``cv2.boxFilter``): an invalid pixel whose (2w+1) x (2w+1) window (w =
  ``fill_width_px``) sees a gap at most w pixels wide on average (to the nearest pixel) takes the
  disparity of its nearest valid pixel along its row or column, at depth edges too. A matching window
  centred in a projector shadow or crack that narrow is mostly lit (w = 4 of a 9-px window leaves 5 lit
  columns) and matches the surface it sees; the ray-cast shadow mask and the matcher's ragged decisions at
  such edges leave 1-3 px bands instead, which the registration's shift and 2x2 splat break into fragments:
  5-10 times the real frames' isolated holes per length of depth edge (docs/validation.md). Deciding by the
  window, not per row and column, fills or keeps a shadow band along a slanted edge as a whole.

All three are a selection, not arithmetic: the output at a pixel is the matcher's disparity of
that pixel or of a valid neighbour, so the cleaned depth stays differentiable (the
gradient of a filled pixel flows to the pixel it copied) and keeps the device's disparity
levels.
"""

from __future__ import annotations

import cv2
import numpy as np
import torch

# filterSpeckles works on 16-bit fixed-point disparity with this many fractional steps per pixel.
_FIXED_POINT = 16


def remove_valid_specks(disparity: np.ndarray, valid: np.ndarray, speckle_px: int, max_diff_px: float) -> np.ndarray:
    """(H, W) bool: ``valid`` without the valid regions smaller than ``speckle_px`` pixels.

    Args:
        disparity: (H, W) float px.
        valid: (H, W) bool.
        speckle_px: regions of fewer pixels are removed (0: nothing removed).
        max_diff_px: neighbours whose disparities differ by more than this belong to different regions.
    """
    if speckle_px <= 0:
        return valid.copy()
    scaled = np.asarray(disparity * _FIXED_POINT)  # a new array: rounded and clipped in place
    np.rint(scaled, out=scaled)
    np.clip(scaled, 1, np.iinfo(np.int16).max, out=scaled)
    fixed = scaled.astype(np.int16)
    # Invalid pixels hold newVal = 0, which filterSpeckles never joins into a region.
    fixed[~valid] = 0
    cv2.filterSpeckles(fixed, 0, int(speckle_px), float(max_diff_px * _FIXED_POINT))
    return valid & (fixed != 0)


_NEIGHBOURS = ((-1, -1), (-1, 0), (-1, 1), (0, -1), (0, 1), (1, -1), (1, 0), (1, 1))


def _one_surface(labels: np.ndarray, candidates: np.ndarray, pixels: np.ndarray, disparity: np.ndarray,
                 valid: np.ndarray, max_diff_px: float) -> np.ndarray:  # fmt: skip
    """(N,) bool per label: is each candidate hole's rim one surface? ``pixels``: the candidates' pixels, flat
    indices in row-major order (:func:`_component_pixels`).

    The rim of a hole is the valid pixels 8-adjacent to it (a rim pixel touching two holes counts
    for one of them). It is one surface when every two 8-adjacent rim pixels differ by at most
    ``max_diff_px`` (``cv2.filterSpeckles``' rule for one region): the rim is a closed ring, so a
    depth edge that crosses the hole crosses the ring between two adjacent rim pixels. Works on
    the holes' pixels and their neighbours only (a few thousand), not on whole images.
    """
    height, width = labels.shape
    rows, cols = np.divmod(pixels, width)
    hole_of = labels[rows, cols]
    rim_label = np.zeros(height * width, np.int64)  # flat: the hole each rim pixel belongs to (labels are >= 1)
    rim_pixels = []
    for dy, dx in _NEIGHBOURS:
        r, c = rows + dy, cols + dx
        inside = (r >= 0) & (r < height) & (c >= 0) & (c < width)
        r, c, lab = r[inside], c[inside], hole_of[inside]
        on_rim = valid[r, c]
        flat = r[on_rim] * width + c[on_rim]
        rim_label[flat] = lab[on_rim]
        rim_pixels.append(flat)
    rim = np.unique(np.concatenate(rim_pixels))  # = np.flatnonzero(rim_label), without a whole-image pass
    rim_rows, rim_cols = np.divmod(rim, width)
    flat_disparity = disparity.reshape(-1)
    worst = np.zeros(len(candidates))
    for dy, dx in ((0, 1), (1, 0), (1, 1), (1, -1)):  # each adjacent pair once
        r, c = rim_rows + dy, rim_cols + dx
        inside = (r < height) & (c >= 0) & (c < width)
        here, there = rim[inside], r[inside] * width + c[inside]
        same = rim_label[there] == rim_label[here]
        here, there = here[same], there[same]
        np.maximum.at(worst, rim_label[here], np.abs(flat_disparity[here] - flat_disparity[there]))
    seen = np.zeros(len(candidates), bool)
    seen[rim_label[rim]] = True
    return candidates & seen & (worst <= max_diff_px)


def fill_small_holes(valid: np.ndarray, hole_px: int, disparity: np.ndarray | None = None,
                     max_diff_px: float | None = None,
                     mostly_in: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """Nearest-valid-pixel source of every pixel of a small hole inside one surface.

    Args:
        valid: (H, W) bool.
        hole_px: invalid 8-connected components of fewer pixels are filled (0: none).
        disparity: (H, W) px; with ``max_diff_px``, only holes whose rim is one surface (8-adjacent
            rim pixels within ``max_diff_px``) are filled (None: every small hole).
        mostly_in: (H, W) bool or None; only holes at least half of whose pixels it marks are filled.

    Returns:
        source: (H, W) int64 flat index of the pixel whose value each pixel takes (itself unless filled).
        filled: (H, W) bool, True where a hole pixel was filled.
    """
    height, width = valid.shape
    source = np.arange(height * width, dtype=np.int64).reshape(height, width)
    if hole_px <= 0 or valid.all() or not valid.any():
        return source, np.zeros_like(valid)
    invalid = (~valid).astype(np.uint8)
    _, labels, stats, _ = cv2.connectedComponentsWithStats(invalid, connectivity=8)
    small = stats[:, cv2.CC_STAT_AREA] < hole_px
    small[0] = False  # label 0 is the valid background
    if mostly_in is not None:
        marked = np.bincount(labels[np.asarray(mostly_in, bool)], minlength=len(small))
        small &= 2 * marked >= stats[:, cv2.CC_STAT_AREA]
    pixels = _component_pixels(labels, stats, small)
    if disparity is not None and max_diff_px is not None and len(pixels):
        small = _one_surface(labels, small, pixels, np.asarray(disparity), valid, max_diff_px)
        pixels = pixels[small[labels.reshape(-1)[pixels]]]
    filled = np.zeros_like(valid)
    if not len(pixels):
        return source, filled
    filled.reshape(-1)[pixels] = True
    source.reshape(-1)[pixels] = nearest_valid_source(valid, pixels)
    return source, filled


def _component_pixels(labels: np.ndarray, stats: np.ndarray, chosen: np.ndarray) -> np.ndarray:
    """(N,) int64: the flat indices, in row-major order, of the pixels of the components ``chosen`` (bool per label)
    of ``cv2.connectedComponentsWithStats``' ``labels`` and ``stats``. Small components are read from their
    bounding boxes (a few thousand pixels), not from a pass over the whole image (~1 ms at 640 x 480)."""
    ids = np.flatnonzero(chosen)
    height, width = labels.shape
    if not len(ids):
        return np.zeros(0, np.int64)
    x0, y0 = stats[ids, cv2.CC_STAT_LEFT], stats[ids, cv2.CC_STAT_TOP]
    box_w, box_h = stats[ids, cv2.CC_STAT_WIDTH], stats[ids, cv2.CC_STAT_HEIGHT]
    side = int(max(box_w.max(), box_h.max()))
    if len(ids) * side * side > height * width // 4:  # large components: the whole image is cheaper
        return np.flatnonzero(np.take(chosen, labels))
    dy, dx = np.divmod(np.arange(side * side), side)
    inside = (dy < box_h[:, None]) & (dx < box_w[:, None])
    flat = ((y0[:, None] + dy) * width + x0[:, None] + dx)[inside]
    own = np.broadcast_to(ids[:, None], inside.shape)[inside]
    return np.sort(flat[labels.reshape(-1)[flat] == own])


def fill_narrow_gaps(valid: np.ndarray, width_px: int) -> np.ndarray:
    """(H, W) bool: the invalid pixels whose (2w+1) x (2w+1) window (w = ``width_px``) holds more than (2w+1)(w + 1/2)
    valid pixels (``cv2.boxFilter``; nothing beyond the image's edges counts as valid): the gap the window sees is
    at most w pixels wide on average, to the nearest pixel. A straight gap of at most w pixels between two surfaces
    is filled, a wider one kept, a few stray holes beside it do not change that; a gap whose width wavers along a
    slanted edge (a staircase of 3 and 4 px, or 5 and 6) is filled or kept as a whole, as the window averages it over
    2w+1 rows (a rule per row and column filled every other step: a dashed line of 1-px fragments after the
    registration). The ends of a wide gap and the corners of a compact hole, where the window sees mostly valid
    pixels, are filled too."""
    if width_px <= 0 or valid.all() or not valid.any():
        return np.zeros_like(valid)
    side = 2 * width_px + 1
    count = cv2.boxFilter(valid.astype(np.float32), cv2.CV_32F, (side, side), normalize=False,
                          borderType=cv2.BORDER_CONSTANT)  # fmt: skip
    return ~valid & (count > side * (width_px + 0.5))  # exact: sums of at most 81 ones in float32


def narrow_gap_sources(valid: np.ndarray, width_px: int) -> tuple[np.ndarray, np.ndarray]:
    """``(pixels, sources)``: flat indices of the pixels :func:`fill_narrow_gaps` fills, and of the valid pixel each
    takes its value from: the nearest valid pixel along its row or column (left, right, up, down in that order on a
    tie: a window centred there mostly sees that side), searched up to ``width_px`` away, else the nearest valid
    pixel in any direction (:func:`nearest_valid_source`). Both (N,) int64."""
    fill = fill_narrow_gaps(valid, width_px)
    rows, cols = np.nonzero(fill)
    height, width = valid.shape
    flat_valid = valid.reshape(-1)
    sources = np.full(len(rows), -1, np.int64)
    todo = np.arange(len(rows))  # the pixels without a source yet: most find one a pixel away
    for step in range(1, width_px + 1):
        for dy, dx in ((0, -step), (0, step), (-step, 0), (step, 0)):
            r, c = rows[todo] + dy, cols[todo] + dx
            inside = (r >= 0) & (r < height) & (c >= 0) & (c < width)
            candidate = np.where(inside, r * width + c, 0)
            found = inside & flat_valid[candidate]
            sources[todo[found]] = candidate[found]
            todo = todo[~found]
    pixels = rows.astype(np.int64) * width + cols
    unresolved = sources < 0
    if unresolved.any():
        sources[unresolved] = nearest_valid_source(valid, pixels[unresolved])
    return pixels, sources


#: Hole pixels look for their nearest valid pixel among these offsets (dy, dx) first, nearest first (ties in
#: (dy, dx) order): every pixel of a hole below 8 px has one within 2 px. Beyond 3 px, a distance transform.
_RING_RADIUS_PX = 3
_RING = sorted(((dy, dx) for dy in range(-_RING_RADIUS_PX, _RING_RADIUS_PX + 1)
                for dx in range(-_RING_RADIUS_PX, _RING_RADIUS_PX + 1)
                if 0 < dy * dy + dx * dx <= _RING_RADIUS_PX**2), key=lambda o: (o[0] ** 2 + o[1] ** 2, o))  # fmt: skip


def nearest_valid_source(valid: np.ndarray, pixels: np.ndarray) -> np.ndarray:
    """(N,) int64: the flat index of the nearest valid pixel of each of the (N,) flat indices ``pixels`` (``valid``
    must have a valid pixel). Within 3 px: the exact Euclidean nearest (ties: the first in (dy, dx) order),
    found by looking at the pixels around each one, nearest first; farther: ``cv2.distanceTransformWithLabels``
    (L2 with a 3x3 mask), which costs ~9 ms for a 640x480 image where the ring costs well under one."""
    height, width = valid.shape
    pixels = np.asarray(pixels, np.int64)
    rows, cols = np.divmod(pixels, width)
    flat_valid = valid.reshape(-1)
    sources = np.full(len(pixels), -1, np.int64)
    for dy, dx in _RING:
        todo = np.flatnonzero(sources < 0)
        if not len(todo):
            break
        r, c = rows[todo] + dy, cols[todo] + dx
        inside = (r >= 0) & (r < height) & (c >= 0) & (c < width)
        candidate = np.where(inside, r * width + c, 0)
        found = inside & flat_valid[candidate]
        sources[todo[found]] = candidate[found]
    far = np.flatnonzero(sources < 0)
    if len(far):
        invalid = (~valid).astype(np.uint8)
        # Every valid pixel (a zero of `invalid`) gets its own label; each pixel learns its nearest one's.
        _, nearest = cv2.distanceTransformWithLabels(invalid, cv2.DIST_L2, 3, labelType=cv2.DIST_LABEL_PIXEL)
        label_to_index = np.zeros(int(nearest.max()) + 1, np.int64)
        valid_index = np.flatnonzero(valid)
        label_to_index[nearest.reshape(-1)[valid_index]] = valid_index
        sources[far] = label_to_index[nearest.reshape(-1)[pixels[far]]]
    return sources


def device_cleanup(disparity: torch.Tensor, valid: torch.Tensor, speckle_px: int, max_diff_px: float,
                   hole_px: int, fill_width_px: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """The clean-up as a selection: which pixels stay valid and where each takes its value from.

    Args:
        disparity: (H, W) px (any grad; read only).
        valid: (H, W) bool, the matcher's validity.
        speckle_px, max_diff_px, hole_px, fill_width_px: see the module docstring (0 switches a pass off);
            ``max_diff_px`` is also the hole fill's one-surface tolerance.

    Returns:
        valid: (H, W) bool after the clean-up.
        source: (H, W) int64 flat index into the (H, W) image of each pixel's value (gather with it).
    """
    d = disparity.detach().cpu().numpy()
    v = valid.detach().cpu().numpy()
    kept = remove_valid_specks(d, v, speckle_px, max_diff_px)
    source, filled = fill_small_holes(kept, hole_px, d, max_diff_px)
    cleaned = kept | filled
    pixels, ends = narrow_gap_sources(cleaned, fill_width_px)
    if len(pixels):  # after the hole fill: its pixels are valid ends, each already pointing at its own source
        flat_source, flat_cleaned = source.reshape(-1), cleaned.reshape(-1)
        flat_source[pixels] = flat_source[ends]
        flat_cleaned[pixels] = True
    device = valid.device
    return torch.from_numpy(cleaned).to(device), torch.from_numpy(source).to(device)
