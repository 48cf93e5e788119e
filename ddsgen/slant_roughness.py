"""How rough a depth map is on surfaces whose disparity runs steeply along the rows (no ground truth needed).

A structured-light sensor matches a window of the IR image against its reference pattern at one disparity. On a
surface whose disparity changes along the row (a board turned about the vertical axis, seen at slope
g = |dd/du| = b tan(alpha) / z px per px), the window holds dots at different disparities and the match lands on
their texture-weighted mean, which differs from the centre's disparity by a random amount proportional to g (the
window's size cancels: a larger window holds more dots but spreads them wider). So the noise grows with g. Real
PrimeSense frames show it (IC-BIN: 0.052 px at g < 0.02, 0.107 px at g = 0.10-0.15), where Nguyen 2012's
10-60 deg curve has none; this module measures it the same way on real and simulated depth.

The measurement: disparity d = f b / z (px) of the pixels with depth in :data:`DEPTH_RANGE_M`; in every
``WINDOW_PX`` x ``WINDOW_PX`` window at least :data:`MIN_FILL` valid, a least-squares quadratic surface
d(u, v) (a quadratic, not a plane: curved objects' own shape then hardly counts, 0.03-0.04 px on ray-cast depth);
its residual at the window's centre pixel and its slope there. Windows across a depth edge are dropped: those
whose fit leaves a root mean square residual above :data:`WINDOW_RMS_PX`, and residuals beyond :data:`OUTLIER_PX`. Per bin of the horizontal slope |dd/du| (:data:`SLOPE_BINS`, pixels whose vertical slope
stays below :data:`MAX_VERTICAL_SLOPE`), the roughness is the robust sigma 1.4826 MAD of the residuals, in px.
"""

from __future__ import annotations

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
#: The bins of :func:`slant_roughness`'s summary: flat (first bin) and slanted (slopes 0.07-0.15 pooled).
FLAT_SLOPE = (0.0, 0.02)
SLANTED_SLOPE = (0.07, 0.15)
#: Residuals are taken at every STRIDE-th row and column (a window's fit costs a 6 x 6 solve; neighbours' residuals
#: share most of their window anyway).
STRIDE = 2
#: A bin with fewer residuals has no roughness (None).
MIN_PIXELS = 200
# Polynomial coordinates are the pixel's offset from the image centre in units of this many px (conditioning).
_COORDINATE_SCALE = 100.0


def local_quadratic_fit(disparity: np.ndarray, usable: np.ndarray, window: int = WINDOW_PX, min_fill: float = MIN_FILL,
                        stride: int = 1) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
    """Per pixel, a least-squares quadratic d(u, v) over the usable pixels of its ``window`` x ``window`` window.

    Args:
        disparity: (H, W) disparity (px; any value where not usable).
        usable: (H, W) bool, the pixels that enter the fits.
        window: odd window side (px).
        min_fill: the share of the window that must be usable for its centre to be fitted.
        stride: fit only the pixels whose row and column are multiples of ``stride`` (the windows still hold
            every usable pixel; a stride of 2 fits a quarter of the pixels, 3-4x faster).

    Returns:
        ``(residual, slope_u, slope_v, window_rms, fitted)``: (H, W) float64 residual d - fit at the centre pixel
        (px), the fit's slopes dd/du, dd/dv there (px per px) and the root mean square residual over the whole
        window (px; large where the window holds a depth edge), NaN where not fitted; (H, W) bool ``fitted`` (the
        pixel is usable, on the stride's lattice and its window full enough).
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
    xs, ys = x[fitted], y[fitted]
    residual, slope_u, slope_v, window_rms = (np.full((h, w), np.nan) for _ in range(4))
    # Least squares: the window's sum of squared residuals is sum(d^2) - coef . rhs.
    window_rms[fitted] = np.sqrt(np.maximum(squares - np.einsum("nk,nk->n", coef, rhs), 0.0) / count[fitted])
    residual[fitted] = values[fitted] - np.einsum("nk,kn->n", coef, np.stack([b[fitted] for b in basis]))
    slope_u[fitted] = (coef[:, 1] + 2 * coef[:, 3] * xs + coef[:, 4] * ys) / _COORDINATE_SCALE
    slope_v[fitted] = (coef[:, 2] + coef[:, 4] * xs + 2 * coef[:, 5] * ys) / _COORDINATE_SCALE
    return residual, slope_u, slope_v, window_rms, fitted


def slope_residuals(depth_m: np.ndarray, disparity_fb: float, valid: np.ndarray | None = None,
                    region: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """The residuals (px) of the pixels measured and their horizontal slopes |dd/du| (px per px), both (N,).

    Args:
        depth_m: (H, W) depth (m), 0 where invalid.
        disparity_fb: f b of the sensor (px m): disparity = f b / z.
        valid: (H, W) bool (default depth > 0); region: (H, W) bool, the pixels that count (default all).
    """
    depth = np.asarray(depth_m, np.float64)
    usable = (depth >= DEPTH_RANGE_M[0]) & (depth <= DEPTH_RANGE_M[1])
    if valid is not None:
        usable &= np.asarray(valid, bool)
    if region is not None:
        usable &= np.asarray(region, bool)
    disparity = disparity_fb / np.where(usable, depth, 1.0)
    residual, slope_u, slope_v, window_rms, fitted = local_quadratic_fit(disparity, usable, stride=STRIDE)
    measured = fitted & (window_rms < WINDOW_RMS_PX) & (np.abs(residual) < OUTLIER_PX)
    measured &= np.abs(slope_v) < MAX_VERTICAL_SLOPE
    return residual[measured], np.abs(slope_u[measured])


def robust_sigma(values: np.ndarray) -> float | None:
    """1.4826 x the median absolute deviation (a normal's sigma); None with fewer than :data:`MIN_PIXELS` values."""
    if len(values) < MIN_PIXELS:
        return None
    return float(1.4826 * np.median(np.abs(values - np.median(values))))


def roughness_by_slope(residuals: np.ndarray, slopes: np.ndarray, bins=SLOPE_BINS) -> list[dict]:
    """Per slope bin: ``{"slope_px": [low, high], "roughness_px": robust sigma or None, "pixels": n}``."""
    rows = []
    for low, high in zip(bins[:-1], bins[1:]):
        inside = residuals[(slopes >= low) & (slopes < high)]
        rows.append({"slope_px": [low, high], "roughness_px": robust_sigma(inside), "pixels": int(len(inside))})
    return rows


def slant_roughness(depth_m: np.ndarray, disparity_fb: float, valid: np.ndarray | None = None,
                    region: np.ndarray | None = None) -> dict:  # fmt: skip
    """The frame's roughness on flat and on slanted surfaces (px) and their ratio.

    Returns ``{"flat_roughness_px", "slanted_roughness_px", "slant_roughness_ratio"}``: the robust sigma of the
    residuals at slopes :data:`FLAT_SLOPE` and :data:`SLANTED_SLOPE` (None with fewer than :data:`MIN_PIXELS`),
    and slanted / flat (None if either is None).
    """
    residuals, slopes = slope_residuals(depth_m, disparity_fb, valid, region)
    flat = robust_sigma(residuals[(slopes >= FLAT_SLOPE[0]) & (slopes < FLAT_SLOPE[1])])
    slanted = robust_sigma(residuals[(slopes >= SLANTED_SLOPE[0]) & (slopes < SLANTED_SLOPE[1])])
    ratio = slanted / flat if flat and slanted is not None else None
    return {"flat_roughness_px": flat, "slanted_roughness_px": slanted, "slant_roughness_ratio": ratio}
