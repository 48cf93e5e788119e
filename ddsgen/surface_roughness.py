"""How rough a depth map's surfaces are, in disparity, and how that noise is grained (no ground truth needed).

Two things real and simulated structured-light depth can be compared on without knowing the scene:

* **Roughness against the disparity's slope.** The sensor matches a window of the IR image against its reference
  pattern at one disparity. On a surface whose disparity changes along the row (a board turned about the vertical
  axis, seen at slope g = |dd/du| = b tan(alpha) / z px per px), the window holds dots at different disparities and
  the match lands on their texture-weighted mean, off the centre's disparity by a random amount proportional to g
  (the window's size cancels: a larger window holds more dots but spreads them wider). So the noise grows with g.
  Real PrimeSense frames show it (IC-BIN: 0.052 px where flat, 0.095 px at g = 0.10-0.15), where Nguyen 2012's
  10-60 deg curve has none.
* **The noise's grain**: the correlation of the residuals of neighbouring pixels along a row and along a column
  (real PrimeSense frames: 0.64-0.73 along the row, 0.51-0.65 along the column).

The measurement: disparity d = f b / z (px) of the pixels with depth in :data:`DEPTH_RANGE_M`; in every
``WINDOW_PX`` x ``WINDOW_PX`` window at least :data:`MIN_FILL` valid, a least-squares quadratic surface
d(u, v) (a quadratic, not a plane: curved objects' own shape then hardly counts, 0.01-0.04 px on ray-cast depth);
its residual at the window's centre pixel, at the centre's right and lower neighbours, and its slope at the centre.
Windows across a depth edge are dropped: those whose fit leaves a root mean square residual above
:data:`WINDOW_RMS_PX`, and residuals beyond :data:`OUTLIER_PX`. Per bin of the horizontal slope |dd/du|
(:data:`SLOPE_BINS`, pixels whose vertical slope stays below :data:`MAX_VERTICAL_SLOPE`), the roughness is the
robust sigma 1.4826 MAD of the residuals, in px.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable

import cv2
import numpy as np

WINDOW_PX = 15
MIN_FILL = 0.9
OUTLIER_PX = 1.0
#: A window whose fit leaves a larger root mean square residual holds a depth edge (or is no surface): not measured.
WINDOW_RMS_PX = 0.5
DEPTH_RANGE_M = (0.5, 2.5)
#: Bins of the horizontal disparity slope |dd/du| (px per px). A board at 1 m turned by 60 deg: 0.13.
SLOPE_BINS = (0.0, 0.02, 0.04, 0.07, 0.10, 0.15)
MAX_VERTICAL_SLOPE = 0.1
#: The bins of :func:`surface_roughness`'s summary: flat (first bin) and slanted (slopes 0.07-0.15 pooled). The
#: noise's grain is measured where flat.
FLAT_SLOPE = (0.0, 0.02)
SLANTED_SLOPE = (0.07, 0.15)
#: Residuals are taken at every STRIDE-th row and column (a window's fit costs a 6 x 6 solve; neighbours' residuals
#: share most of their window anyway).
STRIDE = 2
#: The depth bins (m) of :func:`flat_roughness_by_depth`: real PrimeSense frames have flat surfaces in each of them
#: (IC-BIN's piles of objects from 0.5 m, the LineMOD cat's table to 1.8 m).
DEPTH_BINS_M = (0.5, 0.6, 0.7, 0.85, 1.0, 1.25, 1.6, 2.2)
#: A bin with fewer residuals has no roughness (None).
MIN_PIXELS = 200
#: The keys of :func:`surface_roughness`'s result.
ROUGHNESS_KEYS = ("flat_roughness_px", "slanted_roughness_px", "slant_roughness_ratio", "noise_correlation_row",
                  "noise_correlation_column")  # fmt: skip
# Polynomial coordinates are the pixel's offset from the image centre in units of this many px (conditioning).
_COORDINATE_SCALE = 100.0


@dataclasses.dataclass
class LocalFit:
    """Per-pixel local quadratic fits (:func:`local_quadratic_fit`). All (H, W); float64 maps are NaN where not fitted.

    residual: d - fit at the window's centre (px); right_residual, below_residual: the same fit's residual at the
    centre's right and lower neighbours (NaN where that neighbour is not usable); slope_u, slope_v: the fit's dd/du,
    dd/dv at the centre (px per px); window_rms: the root mean square residual over the whole window (px; large
    where the window holds a depth edge); fitted: bool, the pixel is usable, on the stride's lattice and its window
    full enough.
    """

    residual: np.ndarray
    right_residual: np.ndarray
    below_residual: np.ndarray
    slope_u: np.ndarray
    slope_v: np.ndarray
    window_rms: np.ndarray
    fitted: np.ndarray


def local_quadratic_fit(disparity: np.ndarray, usable: np.ndarray, window: int = WINDOW_PX, min_fill: float = MIN_FILL,
                        stride: int = 1) -> LocalFit:  # fmt: skip
    """Per pixel, a least-squares quadratic d(u, v) over the usable pixels of its ``window`` x ``window`` window.

    Args:
        disparity: (H, W) disparity (px; any value where not usable).
        usable: (H, W) bool, the pixels that enter the fits.
        window: odd window side (px).
        min_fill: the share of the window that must be usable for its centre to be fitted.
        stride: fit only the pixels whose row and column are multiples of ``stride`` (the windows still hold
            every usable pixel; a stride of 2 fits a quarter of the pixels, 3-4x faster).
    """
    h, w = disparity.shape
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    x, y = (u - w / 2) / _COORDINATE_SCALE, (v - h / 2) / _COORDINATE_SCALE
    basis = (np.ones_like(x), x, y, x * x, x * y, y * y)
    weight = usable.astype(np.float64)
    values = np.where(usable, disparity, 0.0).astype(np.float64)

    def window_sum(image: np.ndarray) -> np.ndarray:
        return cv2.boxFilter(image, cv2.CV_64F, (window, window), normalize=False, borderType=cv2.BORDER_CONSTANT)

    count = window_sum(weight)
    fitted = usable & (count >= min_fill * window * window)
    if stride > 1:
        fitted &= (u % stride == 0) & (v % stride == 0)
    # The normal equations only where a fit is made: (N, 6, 6) and (N, 6).
    normal = np.empty((int(fitted.sum()), 6, 6))
    rhs = np.empty((normal.shape[0], 6))
    squares = window_sum(values * values * weight)[fitted]
    for i in range(6):
        rhs[:, i] = window_sum(basis[i] * values * weight)[fitted]
        for j in range(i, 6):
            normal[:, i, j] = normal[:, j, i] = window_sum(basis[i] * basis[j] * weight)[fitted]
    coef = np.linalg.solve(normal, rhs[..., None])[..., 0]  # (N, 6)
    rows, cols = np.nonzero(fitted)

    def residual_at(du: int, dv: int) -> np.ndarray:
        """(N,) residual under each fit at the pixel (du, dv) from its centre; NaN off the image or not usable."""
        r, c = rows + dv, cols + du
        inside = (r < h) & (c < w)
        r, c = np.minimum(r, h - 1), np.minimum(c, w - 1)
        xs, ys = x[r, c], y[r, c]
        fit = coef[:, 0] + coef[:, 1] * xs + coef[:, 2] * ys + coef[:, 3] * xs * xs + coef[:, 4] * xs * ys
        fit += coef[:, 5] * ys * ys
        return np.where(inside & usable[r, c], values[r, c] - fit, np.nan)

    maps = {name: np.full((h, w), np.nan) for name in ("residual", "right", "below", "slope_u", "slope_v", "rms")}
    maps["residual"][fitted] = residual_at(0, 0)
    maps["right"][fitted] = residual_at(1, 0)
    maps["below"][fitted] = residual_at(0, 1)
    xs, ys = x[fitted], y[fitted]
    maps["slope_u"][fitted] = (coef[:, 1] + 2 * coef[:, 3] * xs + coef[:, 4] * ys) / _COORDINATE_SCALE
    maps["slope_v"][fitted] = (coef[:, 2] + coef[:, 4] * xs + 2 * coef[:, 5] * ys) / _COORDINATE_SCALE
    # Least squares: the window's sum of squared residuals is sum(d^2) - coef . rhs.
    maps["rms"][fitted] = np.sqrt(np.maximum(squares - np.einsum("nk,nk->n", coef, rhs), 0.0) / count[fitted])
    return LocalFit(maps["residual"], maps["right"], maps["below"], maps["slope_u"], maps["slope_v"], maps["rms"],
                    fitted)  # fmt: skip


@dataclasses.dataclass
class SurfaceResiduals:
    """The residuals of the pixels measured (:func:`surface_residuals`), all (N,).

    residual: px; slope: |dd/du| (px per px); right, below: the neighbours' residuals under the same fit (px; NaN
    where not usable or beyond :data:`OUTLIER_PX`); depth_m: the pixel's measured depth (m).
    """

    residual: np.ndarray
    slope: np.ndarray
    right: np.ndarray
    below: np.ndarray
    depth_m: np.ndarray

    def _subset(self, keep: np.ndarray) -> SurfaceResiduals:
        return SurfaceResiduals(*(getattr(self, f.name)[keep] for f in dataclasses.fields(self)))

    def where(self, low: float, high: float) -> SurfaceResiduals:
        """The pixels whose slope lies in [low, high)."""
        return self._subset((self.slope >= low) & (self.slope < high))

    def at_depth(self, low: float, high: float) -> SurfaceResiduals:
        """The pixels whose measured depth lies in [low, high) (m)."""
        return self._subset((self.depth_m >= low) & (self.depth_m < high))


def surface_residuals(depth_m: np.ndarray, disparity_fb: float, valid: np.ndarray | None = None,
                      region: np.ndarray | None = None, stride: int = STRIDE) -> SurfaceResiduals:  # fmt: skip
    """The local-fit residuals of a depth image's surfaces (see the module docstring).

    Args:
        depth_m: (H, W) depth (m), 0 where invalid.
        disparity_fb: f b of the sensor (px m): disparity = f b / z.
        valid: (H, W) bool (default depth > 0); region: (H, W) bool, the pixels that count (default all).
        stride: fit every ``stride``-th row and column (:func:`local_quadratic_fit`).
    """
    depth = np.asarray(depth_m, np.float64)
    usable = (depth >= DEPTH_RANGE_M[0]) & (depth <= DEPTH_RANGE_M[1])
    if valid is not None:
        usable &= np.asarray(valid, bool)
    if region is not None:
        usable &= np.asarray(region, bool)
    disparity = disparity_fb / np.where(usable, depth, 1.0)
    fit = local_quadratic_fit(disparity, usable, stride=stride)
    measured = fit.fitted & (fit.window_rms < WINDOW_RMS_PX) & (np.abs(fit.residual) < OUTLIER_PX)
    measured &= np.abs(fit.slope_v) < MAX_VERTICAL_SLOPE

    def neighbour(values: np.ndarray) -> np.ndarray:
        values = values[measured]
        return np.where(np.abs(values) < OUTLIER_PX, values, np.nan)

    return SurfaceResiduals(fit.residual[measured], np.abs(fit.slope_u[measured]), neighbour(fit.right_residual),
                            neighbour(fit.below_residual), depth[measured])  # fmt: skip


def robust_sigma(values: np.ndarray) -> float | None:
    """1.4826 x the median absolute deviation (a normal's sigma); None with fewer than :data:`MIN_PIXELS` values."""
    if len(values) < MIN_PIXELS:
        return None
    return float(1.4826 * np.median(np.abs(values - np.median(values))))


def correlation_sums(residual: np.ndarray, neighbour: np.ndarray) -> np.ndarray:
    """(6,) float64 over the pairs where the neighbour's residual exists: [pairs, sum a, sum b, sum ab, sum a^2,
    sum b^2] (a: residual, b: neighbour). Sums of several frames add up to the pooled ones."""
    both = np.isfinite(neighbour)
    a, b = residual[both], neighbour[both]
    return np.array([both.sum(), a.sum(), b.sum(), (a * b).sum(), (a * a).sum(), (b * b).sum()], np.float64)


def correlation_from_sums(sums: np.ndarray) -> float | None:
    """The correlation of a and b from :func:`correlation_sums` (one frame's or pooled); None under MIN_PIXELS
    pairs."""
    n, sum_a, sum_b, sum_ab, sum_aa, sum_bb = np.asarray(sums, np.float64)
    if n < MIN_PIXELS:
        return None
    covariance = sum_ab / n - sum_a * sum_b / n**2
    return float(covariance / np.sqrt((sum_aa / n - (sum_a / n) ** 2) * (sum_bb / n - (sum_b / n) ** 2)))


def neighbour_correlation(residual: np.ndarray, neighbour: np.ndarray) -> float | None:
    """Correlation of residuals with their neighbours' (pairs where both exist); None with under MIN_PIXELS pairs."""
    return correlation_from_sums(correlation_sums(residual, neighbour))


def roughness_by_slope(residuals: SurfaceResiduals, bins=SLOPE_BINS) -> list[dict]:
    """Per slope bin: ``{"slope_px": [low, high], "roughness_px": robust sigma or None, "pixels": n}``."""
    rows = []
    for low, high in zip(bins[:-1], bins[1:]):
        inside = residuals.where(low, high).residual
        rows.append({"slope_px": [low, high], "roughness_px": robust_sigma(inside), "pixels": int(len(inside))})
    return rows


def flat_roughness_by_depth(frames: Iterable[SurfaceResiduals], bins=DEPTH_BINS_M) -> list[dict]:
    """The flat roughness (slopes :data:`FLAT_SLOPE`) per depth bin, pooled over frames.

    The sensor's disparity noise against distance, measured where real frames have it without ground truth: a
    real PrimeSense device's stays near 0.06 px from 0.5 to 2.2 m (docs/validation.md).

    Args:
        frames: each frame's :func:`surface_residuals` (one sensor: the same f b).
        bins: depth bin edges (m), increasing.

    Returns:
        Per bin ``{"depth_m": [low, high], "roughness_px": robust sigma or None, "pixels": n}``.
    """
    return pooled_flat_roughness((flat_residuals_by_depth(residuals, bins) for residuals in frames), bins)


def flat_residuals_by_depth(residuals: SurfaceResiduals, bins=DEPTH_BINS_M) -> list[np.ndarray]:
    """One frame's flat residuals (float32 px) per depth bin: what a :class:`FlatRoughnessPool` pools."""
    flat = residuals.where(*FLAT_SLOPE)
    return [flat.at_depth(low, high).residual.astype(np.float32) for low, high in zip(bins[:-1], bins[1:])]


def pooled_flat_roughness(frames: Iterable[list[np.ndarray]], bins=DEPTH_BINS_M) -> list[dict]:
    """:func:`flat_roughness_by_depth` from each frame's :func:`flat_residuals_by_depth` (the same ``bins``), exact."""
    pool = FlatRoughnessPool(bins, cap=None)
    for per_bin in frames:
        pool.add(per_bin)
    return pool.rows()


class FlatRoughnessPool:
    """Flat residuals per depth bin, pooled over frames in bounded memory, for folders of any length.

    Per bin it keeps a uniform random sample of at most ``cap`` of all the residuals added: each residual gets a
    random key and the ``cap`` smallest keys stay (seeded: the same frames give the same sample). The robust sigma
    of 200,000 residuals is within about 0.3 % of all of them. With ``cap`` None, or fewer residuals, it is exact.
    """

    def __init__(self, bins=DEPTH_BINS_M, cap: int | None = 200_000, seed: int = 0):
        self.bins = tuple(bins)
        self.cap = cap
        self._rng = np.random.default_rng(seed)
        n = len(self.bins) - 1
        self._values = [np.empty(0, np.float32) for _ in range(n)]
        self._keys = [np.empty(0) for _ in range(n)]
        self._counts = [0] * n

    def add(self, per_bin: list[np.ndarray]) -> None:
        """Add one frame's :func:`flat_residuals_by_depth` (made with this pool's bins)."""
        if len(per_bin) != len(self._values):
            raise ValueError(f"FlatRoughnessPool.add: {len(per_bin)} bins, the pool has {len(self._values)}")
        for index, new in enumerate(per_bin):
            self._counts[index] += len(new)
            values = np.concatenate([self._values[index], np.asarray(new, np.float32)])
            if self.cap is None:
                self._values[index] = values
                continue
            keys = np.concatenate([self._keys[index], self._rng.random(len(new))])
            if len(values) > self.cap:
                keep = np.argpartition(keys, self.cap)[: self.cap]
                values, keys = values[keep], keys[keep]
            self._values[index], self._keys[index] = values, keys

    def rows(self) -> list[dict]:
        """Per bin ``{"depth_m": [low, high], "roughness_px": robust sigma or None, "pixels": n}`` (n: every residual
        added, the sample's robust sigma)."""
        edges = zip(self.bins[:-1], self.bins[1:])
        return [{"depth_m": [low, high], "roughness_px": robust_sigma(values), "pixels": count}
                for (low, high), values, count in zip(edges, self._values, self._counts)]  # fmt: skip


def surface_roughness(depth_m: np.ndarray, disparity_fb: float, valid: np.ndarray | None = None,
                      region: np.ndarray | None = None) -> dict:  # fmt: skip
    """The frame's roughness on flat and on slanted surfaces (px), their ratio, and the flat noise's grain:
    :func:`roughness_summary` of :func:`surface_residuals` (same arguments)."""
    return roughness_summary(surface_residuals(depth_m, disparity_fb, valid, region))


def roughness_summary(residuals: SurfaceResiduals) -> dict:
    """``{"flat_roughness_px", "slanted_roughness_px", "slant_roughness_ratio", "noise_correlation_row",
    "noise_correlation_column"}`` of one frame's residuals: the robust sigma of the residuals at slopes
    :data:`FLAT_SLOPE` and :data:`SLANTED_SLOPE`, slanted / flat, and where flat the correlation of a residual with its
    right and with its lower neighbour's; None where fewer than :data:`MIN_PIXELS` pixels are measured.
    """
    flat = residuals.where(*FLAT_SLOPE)
    flat_sigma = robust_sigma(flat.residual)
    slanted_sigma = robust_sigma(residuals.where(*SLANTED_SLOPE).residual)
    return {
        "flat_roughness_px": flat_sigma,
        "slanted_roughness_px": slanted_sigma,
        "slant_roughness_ratio": slanted_sigma / flat_sigma if flat_sigma and slanted_sigma is not None else None,
        "noise_correlation_row": neighbour_correlation(flat.residual, flat.right),
        "noise_correlation_column": neighbour_correlation(flat.residual, flat.below),
    }
