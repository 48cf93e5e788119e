"""Where a depth image puts the objects' outlines, against the ray cast's: fattening and jitter of the edges.

A block matcher carries a near surface past its outline over the far one behind it (the *fattening*: a correlation
window straddling the edge is dominated by one surface's dots), and where exactly it stops changes from row to row
with the dots it sees (the *jitter*, Nguyen et al. 2012's lateral noise). Both are measured on the objects' left and
right outlines, the rows where the ray-cast instance image has an object pixel beside a non-object one and the
surface beside it is at least :data:`MIN_JUMP_M` farther (so the outline is a depth edge a sensor can see):

* the true edge is the boundary between the object's outermost pixel and its neighbour outside;
* the measured edge is the first pixel, scanning from :data:`REACH_PX` outside the true edge inwards, whose depth is
  valid and nearer than halfway between the object's and the background's ray-cast depth (plus the next pixel
  inwards, so a lone misread pixel is not an edge); a row whose pixel :data:`REACH_PX` outside is already that near
  has no edge within reach and is left out, as are rows where the object is narrower than :data:`MIN_WIDTH_PX`;
* the offset is how far the measured edge lies outside the true one (px; negative: inside);
* the jitter of an edge row is its offset minus the mean offset of the up to eight rows within four of it on the same
  outline (the outline's own curvature and a pose error are smooth and cancel).

The same rows are measured on a real frame and its simulation, so the two are compared edge for edge.
"""

from __future__ import annotations

import numpy as np

#: The background must be at least this much farther (m) than the object for an outline row to count.
MIN_JUMP_M = 0.03
#: The measured edge is searched for within this many pixels of the true edge, either side.
REACH_PX = 8
#: Background depth is read this many pixels outside the object (beyond a fattened edge).
BACKGROUND_OFFSET_PX = 6
#: Rows where the object is narrower than this (px) are left out: at its top and bottom the outline runs along the
#: rows, and its outermost pixel jumps from row to row with the shape, not with the sensor.
MIN_WIDTH_PX = 10
#: Jitter: neighbouring rows within this distance on the same outline; at least MIN_NEIGHBOURS of them.
NEIGHBOUR_ROWS = 4
MIN_NEIGHBOURS = 6


def _outline_rows(clean_depth_m: np.ndarray, instance: np.ndarray, region: np.ndarray | None):
    """Yield (object id, side, row, edge column, object depth, background depth) of the countable outline rows.

    ``edge column`` is the object's outermost pixel (inside ``region`` when given); side ``-1`` is its left outline,
    ``+1`` its right one.
    """
    height, width = instance.shape
    for obj in np.unique(instance):
        if obj <= 0:
            continue
        mask = instance == obj
        for row in np.flatnonzero(mask.any(axis=1)):
            columns = np.flatnonzero(mask[row])
            if columns[-1] - columns[0] + 1 < MIN_WIDTH_PX:
                continue
            for side, column in ((-1, columns[0]), (1, columns[-1])):
                inner = column - side * 2
                outer = column + side * BACKGROUND_OFFSET_PX
                if not (0 <= inner < width and 0 <= outer < width) or column + side * REACH_PX not in range(width):
                    continue
                if region is not None and not region[row, column]:
                    continue
                near, far = clean_depth_m[row, inner], clean_depth_m[row, outer]
                if near > 0 and (far <= 0 or far - near >= MIN_JUMP_M):
                    yield int(obj), side, int(row), int(column), float(near), float(far) if far > 0 else np.inf


def edge_offsets(depth_m: np.ndarray, valid: np.ndarray, clean_depth_m: np.ndarray, instance: np.ndarray,
                 region: np.ndarray | None = None) -> dict:  # fmt: skip
    """The measured offset (px, + = outside) of every countable outline row.

    Args:
        depth_m: (H, W) measured depth (m); valid: (H, W) bool.
        clean_depth_m: (H, W) the ray cast's depth (m, 0 = no hit); instance: (H, W) int object ids (0 = none).
        region: (H, W) bool, or None: only outline rows whose outermost object pixel is in it count.

    Returns:
        ``{(object id, side): {row: offset}}``; rows whose edge was not found within reach are left out.
    """
    out: dict = {}
    for obj, side, row, column, near, far in _outline_rows(clean_depth_m, instance, region):
        threshold = 0.5 * (near + far) if np.isfinite(far) else 1.5 * near
        line = depth_m[row]
        objectlike = valid[row] & (line > 0) & (line < threshold)
        found = None
        for step in range(REACH_PX - 1, -REACH_PX - 1, -1):  # from outside inwards
            c = column + side * step
            c_in = c - side
            if 0 <= c_in < line.size and objectlike[c] and objectlike[c_in]:
                found = step
                break
        outermost = column + side * REACH_PX
        if found is not None and not objectlike[outermost]:  # object-like as far out as it looks: no edge there
            out.setdefault((obj, side), {})[row] = float(found)
    return out


def edge_statistics(depth_m: np.ndarray, valid: np.ndarray, clean_depth_m: np.ndarray, instance: np.ndarray,
                    region: np.ndarray | None = None) -> dict:  # fmt: skip
    """``{"edge_rows", "edge_fattening_px", "edge_jitter_px"}`` of one frame (None where no row was measured);
    arguments as :func:`edge_offsets`.

    edge_rows: measured outline rows; edge_fattening_px: their mean offset outside the true edge; edge_jitter_px:
    the root mean square of their offsets from their neighbouring rows' mean (rows with enough neighbours).
    """
    offsets = edge_offsets(depth_m, valid, clean_depth_m, instance, region)
    values, jitter = [], []
    for rows in offsets.values():
        for row, offset in rows.items():
            values.append(offset)
            window = range(row - NEIGHBOUR_ROWS, row + NEIGHBOUR_ROWS + 1)
            neighbours = [rows[r] for r in window if r != row and r in rows]
            if len(neighbours) >= MIN_NEIGHBOURS:
                jitter.append(offset - float(np.mean(neighbours)))
    return {
        "edge_rows": len(values),
        "edge_fattening_px": float(np.mean(values)) if values else None,
        "edge_jitter_px": float(np.sqrt(np.mean(np.square(jitter)))) if jitter else None,
    }


# ------------------------------------------------------------------------------------------------ without ground truth

#: A near surface's outline pixel: its next valid pixel along the row (within OUTLINE_GAP_PX) is this much farther.
OUTLINE_JUMP_RELATIVE = 0.06
OUTLINE_GAP_PX = 12
#: Outline pixels of consecutive rows within this many columns are one outline; outlines shorter than
#: OUTLINE_MIN_ROWS rows are left out.
OUTLINE_LINK_PX = 2
OUTLINE_MIN_ROWS = 2 * NEIGHBOUR_ROWS + 1


def _outline_pixels(depth_m: np.ndarray, side: int) -> np.ndarray:
    """(H, W) bool: valid pixels whose next valid pixel towards ``side`` (-1 left, +1 right) along the row, within
    :data:`OUTLINE_GAP_PX`, is at least :data:`OUTLINE_JUMP_RELATIVE` farther (the near surface's outermost pixel)."""
    depth = np.asarray(depth_m, np.float64)
    valid = depth > 0
    found = np.zeros(depth.shape, bool)
    farther = np.zeros(depth.shape, bool)
    width = depth.shape[1]
    for gap in range(1, OUTLINE_GAP_PX + 1):
        neighbour = np.zeros_like(depth)
        if side < 0:
            neighbour[:, gap:] = depth[:, : width - gap]
        else:
            neighbour[:, : width - gap] = depth[:, gap:]
        first = ~found & (neighbour > 0)  # the first valid pixel at this distance
        farther |= first & (neighbour > (1.0 + OUTLINE_JUMP_RELATIVE) * depth)
        found |= first
    return valid & farther


def outline_jitter(depth_m: np.ndarray, region: np.ndarray | None = None) -> dict:
    """How ragged the near surfaces' left and right outlines of a depth image are, without ground truth.

    Outline pixels (:func:`_outline_pixels`) of consecutive rows within :data:`OUTLINE_LINK_PX` columns are chained
    into outlines; along each outline at least :data:`OUTLINE_MIN_ROWS` rows long, a row's jitter is its column minus
    the mean column of the up to eight rows within four of it (a straight or gently curved outline cancels).

    Args:
        depth_m: (H, W) metres, 0 = invalid. region: (H, W) bool or None: outline pixels outside it do not count.

    Returns:
        ``{"outline_rows", "outline_jitter_px"}``: rows measured and their root mean square jitter (None if none).
    """
    squares = []
    for side in (-1, 1):
        pixels = _outline_pixels(depth_m, side)
        if region is not None:
            pixels &= region
        for chain in _chains(pixels):
            rows = dict(chain)
            for row, column in chain:
                window = range(row - NEIGHBOUR_ROWS, row + NEIGHBOUR_ROWS + 1)
                neighbours = [rows[r] for r in window if r != row and r in rows]
                if len(neighbours) >= MIN_NEIGHBOURS:
                    squares.append((column - float(np.mean(neighbours))) ** 2)
    return {"outline_rows": len(squares),
            "outline_jitter_px": float(np.sqrt(np.mean(squares))) if squares else None}  # fmt: skip


def _chains(pixels: np.ndarray) -> list[list[tuple[int, int]]]:
    """The outlines of an outline-pixel map: lists of (row, column), one pixel a row, rows consecutive; each pixel
    continues the open chain whose last column is nearest (within :data:`OUTLINE_LINK_PX`) in the row above."""
    finished, open_chains = [], []
    for row in range(pixels.shape[0]):
        columns = np.flatnonzero(pixels[row])
        continued = []
        taken = set()
        for chain in open_chains:
            last = chain[-1][1]
            candidates = [c for c in columns if abs(c - last) <= OUTLINE_LINK_PX and c not in taken]
            if candidates:
                column = min(candidates, key=lambda c: abs(c - last))
                taken.add(column)
                chain.append((row, int(column)))
                continued.append(chain)
            elif len(chain) >= OUTLINE_MIN_ROWS:
                finished.append(chain)
        open_chains = continued + [[(row, int(c))] for c in columns if c not in taken]
    finished.extend(chain for chain in open_chains if len(chain) >= OUTLINE_MIN_ROWS)
    return finished
