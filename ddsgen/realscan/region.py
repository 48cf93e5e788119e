"""The comparison region: the pixels of a real frame that the modelled scene can explain.

A real frame shows more than the modelled scene (the posed objects and, optionally, a support
plane fitted to the real table): other objects, the floor beyond the table's edge, people.
Where such an unmodelled thing returns depth, it is far from the modelled depth and easy to
leave out. Where the real frame has *no* depth, the cause may be modelled (a shadow of a posed
object, a dark or oblique modelled surface) or not; only the first kind is a discrepancy the
simulation should answer for. The rule (:func:`comparison_region`), in disparity px (f b / z):

1. **modelled and plausible** -- modelled geometry is hit, and the real depth is either within
   ``plausible_px`` of the clean depth or invalid;
2. **on the support plane's real extent** -- the fitted plane is infinite, the real table is not.
   The pixels where the real depth lies on the plane (within ``plausible_px``), with the posed
   objects' silhouettes and their modelled projector shadows, are closed with a disc one
   matching block wide; a connected part of the rest in which the real frame sees an unmodelled
   surface (the floor beyond the table's edge) is off the table, and its real-invalid pixels do
   not count; a part without such evidence is a hole in the table (a dark patch, a far part the
   device cannot reach) and counts;
3. **not in an unmodelled shadow** -- a real-invalid pixel that lies in the projector shadow of
   an unmodelled real surface (valid real pixels that are not plausible -- nearer than the
   modelled geometry, or where nothing is modelled -- at least half a block wide, so that a
   lone wrong match is no occluder) does not count. With the projector at +b on
   the camera's x axis (docs/model.md), a point at column u with disparity d is lit by projector
   column u - d; it is shadowed when some nearer point to its right on the same row maps to a
   projector column <= u - d. The shadow is widened by half a matching block, since the real
   matcher loses the window that straddles a shadow's edge.

Real-valid pixels are never removed by rules 2-3 (where the real frame has plausible depth, the
scene is modelled). Pure numpy/OpenCV on (H, W) arrays.
"""

from __future__ import annotations

import cv2
import numpy as np

from ddsgen.sensor.output_window import OutputWindow

RULE = ("compare region = pixels where modelled geometry is hit and the real depth is within plausible_px px of "
        "disparity of the clean depth or invalid; a real-invalid pixel counts only if it is on a posed object or on "
        "the support plane's real footprint (the plane's plausible pixels with the objects and their modelled "
        "shadows, closed by one matching block; of the rest, the connected parts where the real frame sees an "
        "unmodelled surface are off the table, the others are holes in it), and not in the projector shadow of an "
        "unmodelled real surface (valid, implausible real pixels at least half a block wide, whose shadow, widened "
        "by half a block, reaches it)")


def disparity(depth_m: np.ndarray, fb: float) -> np.ndarray:
    """(H, W) f b / z in px, 0 where the depth is 0 (invalid or nothing hit)."""
    with np.errstate(divide="ignore"):
        return np.where(depth_m > 0, fb / np.where(depth_m > 0, depth_m, 1.0), 0.0)


def plane_footprint(on_plane: np.ndarray, modelled: np.ndarray, unmodelled: np.ndarray, block_px: int,
                    window: OutputWindow = OutputWindow()) -> np.ndarray:  # fmt: skip
    """(H, W) bool: the support plane's real extent, see rule 2 of the module docstring.

    The plane's pixels (with the objects and their shadows) are closed with a disc one block
    wide; each connected part of the rest is beyond the real table when the real frame sees an
    unmodelled surface in it (the floor, a wall), and a hole in the table otherwise (a dark
    patch, the far part of the table the device cannot reach: no evidence that the table ends).

    Args:
        on_plane: (H, W) bool, real depth on the fitted plane (within the plausibility threshold).
        modelled: (H, W) bool, the posed objects' silhouettes and modelled shadows (on the table
            even where the real depth is missing, also at the table's edge).
        unmodelled: (H, W) bool, real surfaces the model does not explain (valid, implausible).
        block_px: the matching block (the closing disc's diameter).
        window: the device's output window: border bands where it outputs no depth at all.
            They, and the next block's width where the real matcher's window still overlaps
            them, say nothing about the table, which is taken to continue there as in the
            first column (row) beyond.
    """
    seed = (on_plane | modelled).astype(np.uint8)
    for axis, near_band, far_band in ((1, window.left, window.right), (0, window.top, window.bottom)):
        view = seed if axis == 1 else seed.T
        size = view.shape[1]
        near = near_band + block_px if near_band > 0 else 0
        far = far_band + block_px if far_band > 0 else 0
        if near < size:
            view[:, :near] = view[:, near : near + 1]
        if far < size and far > 0:
            view[:, size - far :] = view[:, size - far - 1 : size - far]
    disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (block_px, block_px))
    closed = cv2.morphologyEx(seed, cv2.MORPH_CLOSE, disc)
    _, labels = cv2.connectedComponents((closed == 0).astype(np.uint8), connectivity=8)
    beyond = np.unique(labels[unmodelled & (closed == 0)])
    return ~np.isin(labels, beyond[beyond > 0])


def unmodelled_shadow(real_disparity: np.ndarray, clean_disparity: np.ndarray, occluder: np.ndarray,
                      widen_px: float) -> np.ndarray:  # fmt: skip
    """(H, W) bool: pixels of the modelled geometry in the projector shadow of ``occluder`` pixels.

    Args:
        real_disparity: (H, W) px of the real frame (the occluders' depth).
        clean_disparity: (H, W) px of the modelled geometry (the shadowed surface), 0 = not hit.
        occluder: (H, W) bool, the unmodelled real surfaces that may cast a shadow.
        widen_px: the shadow is widened by this much (px) on its far side.
    """
    height, width = real_disparity.shape
    columns = np.arange(width, dtype=np.float64)[None, :]
    projector_column = np.where(occluder, columns - real_disparity, np.inf)
    # Smallest projector column of the occluders strictly to the right of each pixel.
    right_min = np.minimum.accumulate(projector_column[:, ::-1], axis=1)[:, ::-1]
    right_min = np.concatenate([right_min[:, 1:], np.full((height, 1), np.inf)], axis=1)
    return (clean_disparity > 0) & (columns - clean_disparity >= right_min - widen_px)


def comparison_region(real_depth: np.ndarray, clean_depth: np.ndarray, hit: np.ndarray, objects: np.ndarray,
                      shadow: np.ndarray, fb: float, plausible_px: float, block_px: int, has_plane: bool,
                      window: OutputWindow = OutputWindow()) -> np.ndarray:  # fmt: skip
    """(H, W) bool: the comparison region (the module docstring's rule).

    Args:
        real_depth: (H, W) metres, 0 = invalid.
        clean_depth: (H, W) metres of the modelled geometry (ray cast), 0 = nothing hit.
        hit: (H, W) bool, modelled geometry hit.
        objects: (H, W) bool, pixels of the posed objects (instance > 0).
        shadow: (H, W) bool, the modelled projector shadow (ray cast).
        fb: focal length (px) x baseline (m).
        plausible_px: plausibility threshold (px of disparity).
        block_px: the matching block size (px).
        has_plane: a support plane is modelled (hit pixels that are not objects are plane).
        window: the device's output window (see :func:`plane_footprint`).
    """
    real_valid = real_depth > 0
    d_real, d_clean = disparity(real_depth, fb), disparity(clean_depth, fb)
    agrees = hit & real_valid & (np.abs(d_real - d_clean) <= plausible_px)
    region = hit & (agrees | ~real_valid)
    # Unmodelled surfaces at least half a block wide: a lone wrong match of the real matcher is no evidence.
    half = block_px // 2 + 1
    unmodelled = cv2.morphologyEx((real_valid & ~agrees).astype(np.uint8), cv2.MORPH_OPEN,
                                  np.ones((half, half), np.uint8)) > 0  # fmt: skip
    explained = np.ones_like(region)
    if has_plane:
        explained = objects | plane_footprint(agrees & ~objects, objects | (hit & shadow), unmodelled, block_px,
                                              window)  # fmt: skip
    explained &= ~unmodelled_shadow(d_real, d_clean, unmodelled, block_px // 2)
    return region & (real_valid | explained)
