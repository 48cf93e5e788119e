"""Scene-independent patch features of depth frames, pooled as additive per-frame counts.

A sensor parameter should move because of how the sensor renders, not because the real scenes
hold other objects. So every feature is conditioned on local geometry or depth:

* **noise texture** ``noise`` (2, D, B+1): histograms of |second difference| of the disparity
  proxy q = f b / z (px), along rows and along columns, per depth bin, over valid triples.
  On any plane 1/z is affine in (u, v), so its second difference is zero whatever the plane's
  pose: what remains is the sensor's noise and its disparity quantisation (a quantised
  disparity gives multiples of the sub-pixel step). Pixels on curved surfaces or near depth
  edges (second difference over +-4 px above 1 px) are left out; what is left above 1.5 px
  lands in an overflow bin, which the distance leaves out too.
* **hole structure by depth** ``holes`` (2, D, S) and ``valid`` (D,): invalid pixels of holes
  inside one surface (row 0) and on depth edges (row 1: the rim spans > 2 px of disparity;
  occlusions and shadows, i.e. scene content, left out of the distance), per hole size class
  (1, 2-3, 4-7, 8-19 px -- the isolated dropouts of :mod:`ddsgen.depth_statistics` -- then
  20-79, ..., 1280+ px), binned by the mean depth of the hole's valid rim, over the
  valid pixels of the same depth bin: a rate per surface depth, not per scene. Only interior
  holes below 80 px enter the distance.
* **validity by image radius** ``radius_valid`` / ``radius_all`` (R,): valid pixels per ring of
  the normalised image radius (projector beam and lens fall-off); compared relative to the
  whole frame's valid share.
* **grain of the noise** ``grain`` (2, 6): on flat surfaces, the residuals of local quadratic fits
  (:mod:`ddsgen.surface_roughness`) and their right (row 0) and lower (row 1) neighbours' under the
  same fit, as the sums that make a pooled correlation. The correlation does not depend on the
  noise's amplitude (beta, the SNR: measured on IC-BIN from kinect_v1, beta 10-25 moves it by
  0.01) nor, unlike the second differences, on how much of the scene slants (a quantised slope
  is a staircase): what sets it is how the device combines neighbouring matches (measured on
  real Kinect V1 frames: 0.62 along the rows, 0.43 down the columns; docs/validation.md).

Counts add over frames (:func:`pool`), so a bootstrap over frames only re-sums arrays.
"""

from __future__ import annotations

import cv2
import numpy as np

from ddsgen.depth_statistics import ISOLATED_MAX_PX, normalised_radius
from ddsgen.surface_roughness import FLAT_SLOPE, correlation_from_sums, correlation_sums, surface_residuals

#: Depth bin edges (m) of the conditioned features.
DEPTH_EDGES = np.array([0.4, 0.8, 1.2, 1.8, 4.0])
#: |second difference| histogram: bins of 1/32 px centred on multiples of 1/32, up to 1.5 px;
#: one overflow bin after (edges, not noise).
NOISE_BIN_PX = 1.0 / 32.0
NOISE_MAX_PX = 1.5
NOISE_EDGES = np.append(np.arange(0.0, NOISE_MAX_PX + NOISE_BIN_PX, NOISE_BIN_PX) - NOISE_BIN_PX / 2, np.inf)
NOISE_EDGES[0] = 0.0
#: Planarity test of the noise feature: second difference over +-PLANAR_SPAN_PX px (px of disparity).
PLANAR_SPAN_PX = 4
PLANAR_MAX_PX = 1.0
#: A hole whose valid rim spans more disparity than this (px) lies on a depth edge.
EDGE_SPREAD_PX = 2.0
#: Hole size classes (px): the first four are isolated dropouts (< ISOLATED_MAX_PX = 20).
HOLE_SIZE_EDGES = np.array([1, 2, 4, 8, ISOLATED_MAX_PX, 80, 320, 1280, np.iinfo(np.int64).max])
RADIUS_EDGES = np.array([0.0, 0.3, 0.5, 0.7, 0.85, 1.01])
#: Bins with fewer samples than this (real or simulated) are left out of the distance.
MIN_SAMPLES = 200

#: Local fits of the grain feature at every GRAIN_STRIDE-th row and column: pooled over frames a
#: sixteenth of the pixels is plenty, at half the cost of surface_roughness's stride 2 (0.075 s per
#: 640 x 480 frame; IC-BIN seq1/0000: correlations 0.534 / 0.498 at stride 4, 0.533 / 0.482 at 2).
GRAIN_STRIDE = 4

FEATURE_KEYS = ("noise", "holes", "valid", "radius_valid", "radius_all", "grain")
#: Hole size classes in the distance: holes below 80 px (the sensor's); larger ones are mostly
#: projector shadows and out-of-range background, set by the scenes (reported, not fitted).
SENSOR_HOLE_CLASSES = 5
#: Size classes of isolated dropouts in ``holes``.
ISOLATED_CLASSES = int(np.searchsorted(HOLE_SIZE_EDGES, ISOLATED_MAX_PX))


def _depth_bin(depth: np.ndarray) -> np.ndarray:
    """Bin index per pixel (-1 outside the edges)."""
    index = np.digitize(depth, DEPTH_EDGES) - 1
    return np.where((index >= 0) & (index < len(DEPTH_EDGES) - 1), index, -1)


def _second_difference_hist(q: np.ndarray, valid: np.ndarray, depth: np.ndarray, axis: int) -> np.ndarray:
    """(D, B+1) histogram of |q[i-1] - 2 q[i] + q[i+1]| along ``axis`` per depth bin of the centre,
    over the pixels whose surface is planar at a coarser scale: |q[i-S] - 2 q[i] + q[i+S]| <=
    PLANAR_MAX_PX with S = PLANAR_SPAN_PX (curved objects and depth edges are left out, so the
    histogram is the sensor's noise, not the scene's shape)."""
    q, valid, depth = (np.moveaxis(a, axis, -1) for a in (q, valid, depth))
    s = PLANAR_SPAN_PX
    centre = slice(s, -s)
    second = np.abs(q[..., s - 1:-s - 1] - 2 * q[..., centre] + q[..., s + 1:q.shape[-1] - s + 1])
    coarse = np.abs(q[..., :-2 * s] - 2 * q[..., centre] + q[..., 2 * s:])
    ok = (valid[..., s - 1:-s - 1] & valid[..., centre] & valid[..., s + 1:q.shape[-1] - s + 1]
          & valid[..., :-2 * s] & valid[..., 2 * s:] & (coarse <= PLANAR_MAX_PX))  # fmt: skip
    bins = _depth_bin(depth[..., centre])[ok]
    values = second[ok]
    n_depth, n_noise = len(DEPTH_EDGES) - 1, len(NOISE_EDGES) - 1
    noise_bin = np.clip(np.digitize(values, NOISE_EDGES) - 1, 0, n_noise - 1)
    keep = bins >= 0
    flat = np.bincount(bins[keep] * n_noise + noise_bin[keep], minlength=n_depth * n_noise)
    return flat.reshape(n_depth, n_noise)


def _hole_histogram(valid: np.ndarray, depth: np.ndarray, q: np.ndarray) -> np.ndarray:
    """(2, D, S) invalid pixels per (interior/edge, depth of the hole's rim, hole size class).

    A hole is an 8-connected invalid component; its rim is the valid pixels touching it, and
    the mean rim depth places it in a depth bin (holes with no valid rim are left out). A hole
    whose rim spans more than EDGE_SPREAD_PX of disparity q lies on a depth edge (occlusion,
    shadow: scene content) -> row 1; otherwise it is inside one surface (the sensor's
    dropouts) -> row 0.
    """
    n, labels, stats, _ = cv2.connectedComponentsWithStats((~valid).astype(np.uint8), connectivity=8)
    # Each rim pixel takes the label of a hole it touches (largest label among its neighbours).
    touching = cv2.dilate(labels.astype(np.float32), np.ones((3, 3), np.uint8)).astype(np.int64)
    rim = valid & (touching > 0)
    rim_labels = touching[rim]
    rim_sum = np.bincount(rim_labels, weights=depth[rim], minlength=n)
    rim_count = np.bincount(rim_labels, minlength=n)
    rim_depth = np.where(rim_count > 0, rim_sum / np.maximum(rim_count, 1), 0.0)
    q_min, q_max = np.full(n, np.inf), np.full(n, -np.inf)
    np.minimum.at(q_min, rim_labels, q[rim])
    np.maximum.at(q_max, rim_labels, q[rim])
    edge = (q_max - q_min > EDGE_SPREAD_PX).astype(np.int64)
    area = stats[:, cv2.CC_STAT_AREA]
    depth_bin, size_class = _depth_bin(rim_depth), np.digitize(area, HOLE_SIZE_EDGES) - 1
    keep = (np.arange(n) > 0) & (depth_bin >= 0)
    n_depth, n_size = len(DEPTH_EDGES) - 1, len(HOLE_SIZE_EDGES) - 1
    index = (edge * n_depth + depth_bin) * n_size + size_class
    flat = np.bincount(index[keep], weights=area[keep], minlength=2 * n_depth * n_size)
    return flat.reshape(2, n_depth, n_size)


def _grain_sums(depth: np.ndarray, focal_baseline_px_m: float) -> np.ndarray:
    """(2, 6) :func:`~ddsgen.surface_roughness.correlation_sums` of flat-surface residuals with their right (row 0)
    and lower (row 1) neighbours'."""
    flat = surface_residuals(depth, focal_baseline_px_m, stride=GRAIN_STRIDE).where(*FLAT_SLOPE)
    return np.stack([correlation_sums(flat.residual, flat.right), correlation_sums(flat.residual, flat.below)])


def grain_correlations(grain: np.ndarray) -> np.ndarray | None:
    """(2,) correlation of flat-surface residuals with their right and lower neighbours' from pooled
    ``grain`` sums; None with fewer than MIN_PIXELS pairs either way."""
    correlations = [correlation_from_sums(sums) for sums in grain]
    return None if None in correlations else np.array(correlations)


def frame_features(depth_m: np.ndarray, focal_baseline_px_m: float) -> dict[str, np.ndarray]:
    """The additive feature counts of one frame.

    Args:
        depth_m: (H, W) metres, 0 = invalid.
        focal_baseline_px_m: f * b (px * m) converting depth to the disparity proxy f b / z.
            Use the same value for real and simulated frames (the preset's).

    Returns:
        dict of int64 arrays: ``noise`` (2, D, B+1), ``holes`` (2, D, S), ``valid`` (D,),
        ``radius_valid`` (R,), ``radius_all`` (R,); and float64 sums ``grain`` (2, 6).
    """
    depth = np.asarray(depth_m, np.float64)
    valid = depth > 0
    q = np.where(valid, focal_baseline_px_m / np.where(valid, depth, 1.0), 0.0)
    noise = np.stack([_second_difference_hist(q, valid, depth, axis) for axis in (1, 0)])

    holes = _hole_histogram(valid, depth, q)
    valid_bins = _depth_bin(depth[valid])
    valid_count = np.bincount(valid_bins[valid_bins >= 0], minlength=len(DEPTH_EDGES) - 1)

    ring = np.digitize(normalised_radius(*depth.shape), RADIUS_EDGES) - 1
    n_ring = len(RADIUS_EDGES) - 1
    radius_valid = np.bincount(ring[valid], minlength=n_ring)[:n_ring]
    radius_all = np.bincount(ring.ravel(), minlength=n_ring)[:n_ring]
    return {"noise": noise.astype(np.int64), "holes": holes.astype(np.int64), "valid": valid_count.astype(np.int64),
            "radius_valid": radius_valid.astype(np.int64), "radius_all": radius_all.astype(np.int64),
            "grain": _grain_sums(depth, focal_baseline_px_m)}  # fmt: skip


def pool(per_frame: list[dict[str, np.ndarray]], indices=None) -> dict[str, np.ndarray]:
    """Sum the counts of the frames ``indices`` (default all; repeats allowed, for the bootstrap)."""
    indices = range(len(per_frame)) if indices is None else indices
    return {key: np.sum([per_frame[i][key] for i in indices], axis=0) for key in FEATURE_KEYS}


# ---- distance -----------------------------------------------------------------------------------
#: Weights of the feature groups in the distance (noise is a Hellinger^2 in [0, 1]; the rates are
#: squared log ratios, so a factor of 2 costs 0.48 x weight; grain is the sum of the two
#: correlations' squared differences: 0.1 off in each costs 0.02 x weight).
WEIGHTS = {"noise": 1.0, "holes": 0.05, "radius": 0.05, "grain": 1.0}
#: Floor of a hole rate (invalid pixels per valid pixel) so that "none" and "almost none" compare finitely.
_RATE_FLOOR = 1e-4


def distance_terms(sim: dict[str, np.ndarray], real: dict[str, np.ndarray]) -> dict[str, float]:
    """Per-group distances between pooled simulated and real features (0 = same distribution).

    Bins are weighted by the real frames' share of samples in them; bins where either side has
    fewer than :data:`MIN_SAMPLES` samples are left out (a depth the fit's scenes do not cover
    says nothing about the sensor).
    """
    terms = {}
    hellinger, weight = 0.0, 0.0
    for axis in range(2):
        for d in range(len(DEPTH_EDGES) - 1):
            s, r = sim["noise"][axis, d, :-1].astype(float), real["noise"][axis, d, :-1].astype(float)
            if s.sum() < MIN_SAMPLES or r.sum() < MIN_SAMPLES:
                continue
            h = 1.0 - np.sum(np.sqrt(s / s.sum() * r / r.sum()))
            hellinger, weight = hellinger + r.sum() * h, weight + r.sum()
    terms["noise"] = hellinger / weight if weight else 0.0

    rate_err, weight = 0.0, 0.0
    for d in range(len(DEPTH_EDGES) - 1):
        if sim["valid"][d] < MIN_SAMPLES or real["valid"][d] < MIN_SAMPLES:
            continue
        rs = sim["holes"][0, d, :SENSOR_HOLE_CLASSES] / sim["valid"][d] + _RATE_FLOOR
        rr = real["holes"][0, d, :SENSOR_HOLE_CLASSES] / real["valid"][d] + _RATE_FLOOR
        rate_err, weight = rate_err + real["valid"][d] * np.mean(np.log(rs / rr) ** 2), weight + real["valid"][d]
    terms["holes"] = rate_err / weight if weight else 0.0

    def relative_share(f):
        whole = f["radius_valid"].sum() / max(f["radius_all"].sum(), 1)
        return (f["radius_valid"] + 1.0) / (f["radius_all"] + 1.0) / max(whole, 1e-6)

    terms["radius"] = float(np.mean(np.log(relative_share(sim) / relative_share(real)) ** 2))
    sim_grain, real_grain = grain_correlations(sim["grain"]), grain_correlations(real["grain"])
    measured = sim_grain is not None and real_grain is not None
    terms["grain"] = float(np.sum((sim_grain - real_grain) ** 2)) if measured else 0.0
    terms["total"] = float(sum(WEIGHTS[k] * terms[k] for k in WEIGHTS))
    return {k: float(v) for k, v in terms.items()}


def summary(pooled: dict[str, np.ndarray]) -> dict:
    """Readable statistics of pooled features (for the report): per depth bin the median and
    90th percentile of |second difference| (px, rows), the isolated-dropout rate and the hole
    rate per size class (invalid px per 1e4 valid px), the valid share per radius ring, and the
    flat-surface noise's correlation with the next pixel in the row and in the column."""
    centres = np.arange(len(NOISE_EDGES) - 2) * NOISE_BIN_PX  # bin k holds |second difference| ~ k/32 px
    rows = []
    for d in range(len(DEPTH_EDGES) - 1):
        hist = pooled["noise"][0, d, :-1].astype(float)
        cdf = np.cumsum(hist) / hist.sum() if hist.sum() else None
        pick = (lambda p: float(centres[np.searchsorted(cdf, p)]) if cdf is not None else None)  # noqa: E731
        per_valid = 1e4 / pooled["valid"][d] if pooled["valid"][d] else None
        rows.append({
            "depth_m": [float(DEPTH_EDGES[d]), float(DEPTH_EDGES[d + 1])],
            "samples": int(hist.sum()),
            "second_diff_median_px": pick(0.5), "second_diff_p90_px": pick(0.9),
            "dropouts_per_1e4_valid": (float(pooled["holes"][:, d, :ISOLATED_CLASSES].sum() * per_valid)
                                       if per_valid else None),
            "interior_hole_px_per_1e4_valid": ([round(float(h * per_valid), 2) for h in pooled["holes"][0, d]]
                                               if per_valid else None),
        })  # fmt: skip
    share = pooled["radius_valid"] / np.maximum(pooled["radius_all"], 1)
    grain = grain_correlations(pooled["grain"])
    return {"depth_bins": rows, "hole_size_edges_px": HOLE_SIZE_EDGES[:-1].tolist(),
            "valid_share_by_radius": [round(float(s), 4) for s in share],
            "radius_edges": RADIUS_EDGES.tolist(),
            "noise_correlation_row": None if grain is None else round(float(grain[0]), 4),
            "noise_correlation_column": None if grain is None else round(float(grain[1]), 4)}  # fmt: skip
