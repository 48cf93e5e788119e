"""Statistics that tell a real structured-light depth frame from a simulated one.

Plain numpy functions on one depth image, used by ``compare`` (real and simulated side by
side), the realism benchmark and the presets' tuning. Definitions (those docs/validation.md
reports real and simulated frames by):

* **isolated dropout**: a connected component (8-connected) of invalid pixels with fewer
  than ``ISOLATED_MAX_PX`` = 20 pixels. Real PrimeSense frames have 21-46 per 640x480 frame
  holding 0.1-0.6 % of the invalid pixels: their holes are clustered (shadows, dark and far
  surfaces, edges), not salt-and-pepper. Their **mean size** (whole components, px) is 2.5-4.6 on the real frames
  (1-px holes the most common).
* **their share off the blind border**: the same isolated pixels as a share of the invalid pixels outside the
  *blind border bands* (:func:`blind_border_bands`: the image's outer columns and rows in which no pixel is valid).
  A device registered to a wider RGB camera leaves such bands: IC-BIN's PrimeSense frames 33-39 columns on the
  right and 10-11 rows at the top and bottom (~30,000 px, most of their 37,000-71,000 invalid pixels), the LineMOD
  cat 7 columns on the left. Off the bands the nine IC-BIN frames read 0.27-3.97 % (median 1.18 %), the cat
  0.80 %: the whole-frame share compares scenes' border bands as much as their holes.
* **corner valid share**: the valid share of the pixels farther than ``CORNER_RADIUS`` = 0.7
  of the half-diagonal from the image centre (real: 0.42-0.80, below the whole frame's
  0.77-0.94: projector beam and lens vignetting).
* **depth step at 1 m**: the spacing of the depth levels the device outputs, scaled to 1 m
  with the step's z^2 law (1/8 px disparity at f = 572 px, b = 75 mm: 2.92 mm).
* **isolated dropouts per edge**: isolated dropouts per 1000 pixels of depth edge. An edge
  pixel is one whose depth differs from its right or lower neighbour's by more than
  ``EDGE_MIN_RELATIVE`` = 3 %, on the depth map with every hole filled from its nearest valid
  pixel (so a jump hidden in a shadow still counts once), within ``EDGE_NEAR_VALID_PX`` = 8 px of
  a valid pixel (not deep inside the device's blind border bands). Every isolated dropout counts
  (on real frames they sit at edges). It separates how many edges a scene has from how ragged
  the sensor leaves them: the ten real frames have 5.3-11.0 per 1000 edge pixels whatever their
  content (cluttered bins at 0.6 m, a table at 1 m).

* **isolated dropouts inside one surface**: the share of the isolated dropouts whose rim (the valid pixels
  8-adjacent to them) is one surface: all its disparities f b / z within ``ONE_SURFACE_DISPARITY_PX`` = 1 px of
  each other (the hole fill's tolerance applied to the whole rim's range, stricter than
  ``ddsgen.sensor.cleanup``'s rule on adjacent rim pixels, which a slanted rim can pass; f b of a Kinect V1 by
  default). The eleven real frames: 18 % (71 of 386, most of them 1-2 px); the rest sit at depth edges. A simulation with many more has holes no real device leaves, such as a
  registration band drawn inside the near surface (docs/model.md, registration).

* **holes at depth jumps** and **wide registration bands kept open**: :mod:`ddsgen.depth_jumps`.

* **vertical share of elongated isolated dropouts**: an isolated dropout is *vertical* when its bounding box is at
  least twice as tall as wide, *horizontal* when at least twice as wide as tall (the rest, single pixels included,
  are neither). The statistic is vertical / (vertical + horizontal). Real frames have both about equally often:
  IC-BIN 61 of 105 pooled (0.58; per frame 0.31-0.86 on 7-15 of them), the LineMOD cat 6 of 12, TUM 5 of 9. It
  tells how a simulation's registration breaks its bands into holes: the backward map leaves thin vertical slivers
  beside near surfaces (16 rendered kinect_v1 frames: 0.78), a forward map without a vertical fill leaves dashes
  along near-horizontal edges (0.19; docs/validation.md). Per frame it rests on few holes: pool frames.

* **roughness and grain** (with the sensor's f b): how rough flat and slanted surfaces are in disparity and how the
  noise is grained, from local quadratic fits (:mod:`ddsgen.surface_roughness`).

A ``region`` (bool (H, W)) restricts every statistic to the pixels that count (e.g. the
modelled geometry of a real frame); components are still found on the whole image, and a
component counts for the region when any of its pixels lies in it.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import cv2
import numpy as np

from ddsgen.depth_jumps import (
    band_outcomes,
    holes_at_depth_jumps,
    region_or_all,
    registration_band_jumps,
)
from ddsgen.silhouette_edges import outline_jitter
from ddsgen.surface_roughness import (
    ROUGHNESS_KEYS,
    roughness_summary,
    surface_residuals,
)

if TYPE_CHECKING:
    from ddsgen.surface_roughness import SurfaceResiduals

#: The statistics of :func:`realism_statistics`, in reporting order, with their table labels.
STATISTIC_LABELS = {
    "valid_share": "valid share",
    "corner_valid_share": "corner valid share",
    "isolated_dropouts": "isolated dropouts / frame",
    "isolated_dropout_share": "  their share of invalid",
    "isolated_dropout_share_off_border": "  their share off the blind border",
    "isolated_dropout_mean_px": "  their mean size (px)",
    "depth_step_at_1m_mm": "depth step at 1 m (mm)",
    "jump_holes_left": "depth jumps, hole left of near",
    "jump_holes_right": "depth jumps, hole right of near",
    "isolated_dropouts_per_1000_edge_px": "isolated dropouts / 1000 edge px",
    "isolated_one_surface_share": "  their share inside one surface",
    "isolated_vertical_share": "  vertical share of elongated",
    "wide_band_hole_share": "wide registration bands kept open",
    "narrow_band_slit_share": "narrow registration bands left as a slit",
    "outline_jitter_px": "outline jitter (px rms)",
    "flat_roughness_px": "roughness, flat surfaces (px)",
    "slanted_roughness_px": "roughness, slanted surfaces (px)",
    "slant_roughness_ratio": "  slanted / flat",
    "noise_correlation_row": "noise correlation, next in row",
    "noise_correlation_column": "noise correlation, next in column",
}
ISOLATED_MAX_PX = 20
CORNER_RADIUS = 0.7
EDGE_MIN_RELATIVE = 0.03
EDGE_NEAR_VALID_PX = 8
ONE_SURFACE_DISPARITY_PX = 1.0
#: f b of a Kinect V1 (px m, f = 572.41 px, b = 75 mm): the disparity of depth z is f b / z.
KINECT_FOCAL_BASELINE_PX_M = 572.41 * 0.075
# Depth values are compared within this relative window around each reference depth.
_STEP_WINDOW = 0.05
_MIN_LEVELS = 4


def isolated_dropouts(valid: np.ndarray, region: np.ndarray | None = None,
                      max_pixels: int = ISOLATED_MAX_PX) -> tuple[int, float]:
    """(count, share): invalid components smaller than ``max_pixels`` touching the region, and the
    share of the region's invalid pixels that they hold.

    Args:
        valid: (H, W) bool, True where the sensor output depth.
        region: (H, W) bool or None (whole image).
    """
    return _count_and_share(*_isolated_components(valid, region, max_pixels), region_or_all(np.shape(valid), region))


def _count_and_share(invalid: np.ndarray, labels: np.ndarray, stats: np.ndarray, isolated: np.ndarray,
                     region: np.ndarray) -> tuple[int, float]:  # fmt: skip
    """:func:`isolated_dropouts` from :func:`_isolated_components`' result."""
    invalid_in_region = int((invalid & region).sum())
    isolated_pixels = int((isolated[labels] & region & invalid).sum())  # a pixel in the region: its component touches it
    return int(isolated.sum()), (isolated_pixels / invalid_in_region if invalid_in_region else 0.0)


def blind_border_bands(valid: np.ndarray) -> np.ndarray:
    """(H, W) bool: the outer columns (left, right) and rows (top, bottom) of the image with no valid pixel, each
    counted inwards from its edge up to the first line that has one (all True for an image with none valid)."""
    valid = np.asarray(valid, bool)
    bands = np.zeros(valid.shape, bool)
    if not valid.any():
        return ~bands
    columns, rows = valid.any(axis=0), valid.any(axis=1)
    first_col, last_col = int(np.argmax(columns)), len(columns) - int(np.argmax(columns[::-1]))
    first_row, last_row = int(np.argmax(rows)), len(rows) - int(np.argmax(rows[::-1]))
    bands[:, :first_col] = bands[:, last_col:] = True
    bands[:first_row] = bands[last_row:] = True
    return bands


def _share_off_border(valid: np.ndarray, labels: np.ndarray, isolated: np.ndarray, region: np.ndarray) -> float:
    """Isolated dropouts' pixels / the region's invalid pixels outside :func:`blind_border_bands` (0 without any)."""
    invalid_off_border = ~valid & region & ~blind_border_bands(valid)
    off = int(invalid_off_border.sum())
    return int((isolated[labels] & invalid_off_border).sum()) / off if off else 0.0


def _mean_size(stats: np.ndarray, isolated: np.ndarray) -> float | None:
    """Mean area (px, whole components) of the isolated dropouts; None without any."""
    return float(stats[isolated, cv2.CC_STAT_AREA].mean()) if isolated.any() else None


def _isolated_components(valid: np.ndarray, region: np.ndarray | None,
                         max_pixels: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
    """(invalid (H, W) bool, labels (H, W) int32, stats (n, 5) of cv2.connectedComponentsWithStats, isolated (n,)
    bool): the 8-connected invalid components; ``isolated`` marks those under ``max_pixels`` touching the region."""
    valid = np.asarray(valid, bool)
    region = region_or_all(valid.shape, region)
    invalid = ~valid
    n, labels, stats, _ = cv2.connectedComponentsWithStats(invalid.astype(np.uint8), connectivity=8)
    isolated = np.zeros(n, bool)
    isolated[1:] = stats[1:, cv2.CC_STAT_AREA] < max_pixels
    in_region = np.zeros(n, bool)
    in_region[np.unique(labels[region & invalid])] = True
    return invalid, labels, stats, isolated & in_region


def isolated_dropout_orientation(valid: np.ndarray, region: np.ndarray | None = None) -> tuple[int, int]:
    """(vertical, horizontal): the isolated dropouts touching the region whose bounding box is at least twice as
    tall as wide, and at least twice as wide as tall (see the module docstring).

    Args:
        valid: (H, W) bool, True where the sensor output depth.
        region: (H, W) bool or None (whole image).
    """
    return _orientation(*_isolated_components(valid, region, ISOLATED_MAX_PX)[2:])


def _orientation(stats: np.ndarray, isolated: np.ndarray) -> tuple[int, int]:
    """:func:`isolated_dropout_orientation` from :func:`_isolated_components`' stats and isolated mask."""
    width, height = stats[isolated, cv2.CC_STAT_WIDTH], stats[isolated, cv2.CC_STAT_HEIGHT]
    return int((height >= 2 * width).sum()), int((width >= 2 * height).sum())


def isolated_dropouts_by_rim(depth_m: np.ndarray, region: np.ndarray | None = None,
                             focal_baseline_px_m: float = KINECT_FOCAL_BASELINE_PX_M) -> tuple[int, int]:
    """(inside one surface, at a depth edge): the isolated dropouts touching the region, split by their rim.

    Args:
        depth_m: (H, W) metres, 0 = invalid.
        region: (H, W) bool or None (whole image).
        focal_baseline_px_m: f b (px m) of the disparity f b / z the one-surface test compares.
    """
    depth = np.asarray(depth_m, np.float64)
    valid = depth > 0
    region = region_or_all(depth.shape, region)
    n, labels, stats, _ = cv2.connectedComponentsWithStats((~valid).astype(np.uint8), connectivity=8)
    disparity = np.divide(focal_baseline_px_m, depth, out=np.zeros_like(depth), where=valid)
    height, width = depth.shape
    inside = at_edge = 0
    for label in np.flatnonzero(stats[:, cv2.CC_STAT_AREA] < ISOLATED_MAX_PX):
        if label == 0:
            continue  # the valid pixels
        x, y, w, h = stats[label, :4]
        y0, y1, x0, x1 = max(y - 1, 0), min(y + h + 1, height), max(x - 1, 0), min(x + w + 1, width)
        hole = labels[y0:y1, x0:x1] == label
        if not (hole & region[y0:y1, x0:x1]).any():
            continue
        rim = cv2.dilate(hole.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool) & valid[y0:y1, x0:x1]
        if not rim.any():
            continue  # inside the image's border only: no rim to judge
        rim_disparity = disparity[y0:y1, x0:x1][rim]
        if rim_disparity.max() - rim_disparity.min() <= ONE_SURFACE_DISPARITY_PX:
            inside += 1
        else:
            at_edge += 1
    return inside, at_edge


def depth_edges(depth_m: np.ndarray, min_relative: float = EDGE_MIN_RELATIVE,
                near_valid_px: float = EDGE_NEAR_VALID_PX) -> np.ndarray:
    """(H, W) bool: the depth-edge pixels of a depth image (see the module docstring).

    Args:
        depth_m: (H, W) metres, 0 = invalid.
    """
    depth = np.asarray(depth_m, np.float64)
    valid = depth > 0
    edges = np.zeros(depth.shape, bool)
    if not valid.any():
        return edges
    # Each pixel's nearest valid pixel (OpenCV labels every zero of the input, i.e. every valid pixel).
    distance, nearest = cv2.distanceTransformWithLabels((~valid).astype(np.uint8), cv2.DIST_L2, 3,
                                                        labelType=cv2.DIST_LABEL_PIXEL)  # fmt: skip
    label_to_depth = np.zeros(int(nearest.max()) + 1)
    label_to_depth[nearest[valid]] = depth[valid]
    filled = label_to_depth[nearest]
    edges[:, 1:] |= np.abs(np.diff(filled, axis=1)) > min_relative * np.minimum(filled[:, 1:], filled[:, :-1])
    edges[1:, :] |= np.abs(np.diff(filled, axis=0)) > min_relative * np.minimum(filled[1:], filled[:-1])
    return edges & (distance <= near_valid_px)


def normalised_radius(height: int, width: int) -> np.ndarray:
    """(H, W) distance of each pixel centre from the image centre, in units of the half-diagonal."""
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    du, dv = u - (width - 1) / 2.0, v - (height - 1) / 2.0
    return np.hypot(du, dv) / np.hypot(width / 2.0, height / 2.0)


#: Ring edges (fractions of the half-diagonal) of the radial validity profile: the rings of ../shared/data/README.md.
RADIAL_RING_EDGES = (0.0, 0.3, 0.5, 0.7, 0.85, np.inf)


def radial_valid_profile(valid: np.ndarray, ring_edges: tuple[float, ...] = RADIAL_RING_EDGES,
                         in_window: bool = False) -> list[float]:  # fmt: skip
    """Share of valid pixels in each ring of :func:`normalised_radius` (len(ring_edges) - 1 values in 0..1).

    Args:
        valid: (H, W) bool (or depth, > 0 = valid).
        in_window: count only the device's output window, the image less its :func:`blind_border_bands`. The bands
            are the output window of the device (border columns and rows it never fills, whatever the scene: 33-39
            px right and 10-11 px top and bottom on the IC-BIN frames), which cut through the corners; the window is
            measured apart from the radial validity (``ddsgen fit --unpaired``, :mod:`ddsgen.sensor.output_window`).
    """
    valid = np.asarray(valid) > 0
    radius = normalised_radius(*valid.shape)
    window = ~blind_border_bands(valid) if in_window else np.ones(valid.shape, bool)
    return [float(valid[window & (radius >= low) & (radius < high)].mean())
            for low, high in zip(ring_edges, ring_edges[1:])]  # fmt: skip


def corner_valid_share(valid: np.ndarray, region: np.ndarray | None = None, corner_radius: float = CORNER_RADIUS,
                       in_window: bool = False) -> tuple[float | None, float | None]:  # fmt: skip
    """(corner share, whole share) of valid pixels; None where the region has no such pixel. ``in_window``: the
    region less the device's :func:`blind_border_bands` (see :func:`radial_valid_profile`)."""
    valid = np.asarray(valid, bool)
    region = region_or_all(valid.shape, region)
    if in_window:
        region = region & ~blind_border_bands(valid)
    corner = region & (normalised_radius(*valid.shape) > corner_radius)
    share = lambda mask: float(valid[mask].mean()) if mask.any() else None  # noqa: E731
    return share(corner), share(region)


def depth_step_at_1m(depth_m: np.ndarray, valid: np.ndarray | None = None, region: np.ndarray | None = None,
                     resolution_m: float = 0.001) -> float | None:
    """Median spacing of the output's depth levels, scaled to 1 m by the z^2 law (metres).

    The distinct valid depth values are grouped in windows of +-5 % around each level; within
    a window, consecutive differences larger than 1.5 x their median plus ``resolution_m``
    (the file's rounding: a 16-bit PNG in mm alternates 2 and 3 mm steps near 1 m) are gaps,
    levels nobody observed, and are left out. None when too few levels are seen.

    Args:
        depth_m: (H, W) metres, 0 = invalid.
        valid, region: (H, W) bool or None.
        resolution_m: the rounding unit of the values (0.001 for millimetre PNGs, 0 for EXR).
    """
    depth = np.asarray(depth_m, np.float64)
    mask = region_or_all(depth.shape, region) & (depth > 0)
    if valid is not None:
        mask &= np.asarray(valid, bool)
    levels = np.unique(np.round(depth[mask], 6))
    if len(levels) < _MIN_LEVELS:
        return None
    scaled = []
    # Windows centred on every 8th level: enough samples, each window sees several steps.
    for centre in levels[:: max(1, len(levels) // 64)]:
        near = levels[np.abs(levels - centre) <= _STEP_WINDOW * centre]
        if len(near) < _MIN_LEVELS:
            continue
        diffs = np.diff(near)
        diffs = diffs[diffs <= 1.5 * np.median(diffs) + resolution_m]
        if len(diffs):
            scaled.append(diffs.mean() / centre**2)
    return float(np.median(scaled)) if scaled else None


def realism_statistics(depth_m: np.ndarray, valid: np.ndarray | None = None, region: np.ndarray | None = None,
                       resolution_m: float = 0.001, disparity_fb: float | None = None,
                       residuals: SurfaceResiduals | None = None) -> dict:  # fmt: skip
    """The hole, validity and quantisation statistics of one frame, as a JSON-ready dict.

    Keys: ``valid_share``, ``corner_valid_share``, ``isolated_dropouts`` (count),
    ``isolated_dropout_share`` (of the invalid pixels), ``isolated_dropout_share_off_border`` (of those outside the
    blind border bands), ``isolated_dropout_mean_px`` (their mean size; None
    without any), ``depth_step_at_1m_mm``, ``jump_holes_left``,
    ``jump_holes_right`` (:func:`ddsgen.depth_jumps.holes_at_depth_jumps`), ``isolated_dropouts_per_1000_edge_px``
    (:func:`depth_edges`; None without edges), ``isolated_one_surface_share`` (:func:`isolated_dropouts_by_rim`;
    None without isolated dropouts), ``wide_band_hole_share`` (:func:`ddsgen.depth_jumps.wide_band_holes`; None
    without such jumps), ``narrow_band_slit_share`` (:func:`ddsgen.depth_jumps.narrow_band_slits`; None without such
    jumps),
    ``isolated_vertical_share`` (:func:`isolated_dropout_orientation`; None without elongated ones),
    ``outline_jitter_px`` (:func:`ddsgen.silhouette_edges.outline_jitter`; None without outlines),
    ``flat_roughness_px``, ``slanted_roughness_px``, ``slant_roughness_ratio``, ``noise_correlation_row``,
    ``noise_correlation_column`` (:func:`ddsgen.surface_roughness.surface_roughness`, in the disparity of a sensor
    with ``disparity_fb`` = f b in px m; None without it or without enough such surface; ``residuals``: those of
    :func:`ddsgen.surface_roughness.surface_residuals` for this frame when already computed), ``pixels``.
    """
    depth = np.asarray(depth_m, np.float64)
    valid = depth > 0 if valid is None else np.asarray(valid, bool)
    region = region_or_all(depth.shape, region)
    components = _isolated_components(valid, region, ISOLATED_MAX_PX)  # found once, for count, share and orientation
    count, share = _count_and_share(*components, region)
    corner, whole = corner_valid_share(valid, region)
    step = depth_step_at_1m(depth, valid, region, resolution_m)
    valid_depth = np.where(valid, depth, 0.0)
    left, right = holes_at_depth_jumps(valid_depth, region)
    edge_px = int((depth_edges(valid_depth) & region).sum())
    one_surface, at_edge = isolated_dropouts_by_rim(valid_depth, region)
    band_holes, band_jumps, slits, narrow_jumps = band_outcomes(*registration_band_jumps(valid_depth, region))
    vertical, horizontal = _orientation(*components[2:])
    if residuals is None and disparity_fb:
        residuals = surface_residuals(valid_depth, disparity_fb, valid, region)
    return {
        "valid_share": whole,
        "corner_valid_share": corner,
        "isolated_dropouts": count,
        "isolated_dropout_share": share,
        "isolated_dropout_share_off_border": _share_off_border(valid, components[1], components[3], region),
        "isolated_dropout_mean_px": _mean_size(*components[2:]),
        "depth_step_at_1m_mm": None if step is None else step * 1000.0,
        "jump_holes_left": left,
        "jump_holes_right": right,
        "isolated_dropouts_per_1000_edge_px": 1000.0 * count / edge_px if edge_px else None,
        "isolated_one_surface_share": one_surface / (one_surface + at_edge) if one_surface + at_edge else None,
        "wide_band_hole_share": band_holes / band_jumps if band_jumps else None,
        "narrow_band_slit_share": slits / narrow_jumps if narrow_jumps else None,
        "isolated_vertical_share": vertical / (vertical + horizontal) if vertical + horizontal else None,
        "outline_jitter_px": outline_jitter(valid_depth, region)["outline_jitter_px"],
        **(roughness_summary(residuals) if residuals is not None else dict.fromkeys(ROUGHNESS_KEYS)),
        "pixels": int(region.sum()),
    }
