"""Roughness against the disparity's slope, and the noise's grain (ddsgen.surface_roughness), on made-up and real
frames."""

from pathlib import Path

import numpy as np
import pytest

from ddsgen.surface_roughness import (FlatRoughnessPool, flat_roughness_by_depth, local_quadratic_fit, robust_sigma,
                                      roughness_by_slope, surface_residuals, surface_roughness)

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"
FB = 572.41 * 0.075  # the Kinect's f b (px m)


def _surface_depth(slope_u: float, noise_px: float, seed: int = 0, curvature: float = 0.0, base_px: float = 40.0,
                   h: int = 120, w: int = 160) -> np.ndarray:  # fmt: skip
    """Depth (m) of a surface whose disparity is base_px + slope_u (u - w/2) + curvature (v - h/2)^2, plus white
    disparity noise of ``noise_px``."""
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    disparity = base_px + slope_u * (u - w / 2) + curvature * (v - h / 2) ** 2
    disparity += np.random.default_rng(seed).normal(0.0, noise_px, size=disparity.shape)
    return FB / disparity


@pytest.mark.parametrize("slope", [0.0, 0.05, 0.12])
def test_a_noisy_slanted_surface_gives_its_noise_and_its_slope(slope):
    """White disparity noise of 0.08 px on a surface of known slope (and a curvature a plane fit would take for
    noise): the roughness is the noise (the fit's 6 parameters over 225 px take 1.3 % of it), in the slope's bin,
    and the fitted slope is the true one."""
    depth = _surface_depth(slope, 0.08, curvature=2e-4)
    residuals = surface_residuals(depth, FB)
    assert len(residuals.residual) > 2000
    assert np.median(np.abs(residuals.slope - slope)) < 0.01
    rows = roughness_by_slope(residuals)
    measured = [row for row in rows if row["roughness_px"] is not None]
    assert len(measured) == 1 and measured[0]["slope_px"][0] <= slope < measured[0]["slope_px"][1], rows
    assert measured[0]["roughness_px"] == pytest.approx(0.08 * np.sqrt(1 - 6 / 225), rel=0.05)


def test_flat_roughness_is_binned_by_depth_and_pooled_over_frames():
    """Two flat surfaces per frame, one at 0.55 m with 0.04 px of disparity noise and one at 1.5 m with 0.09 px (the
    same f b): each noise comes out in its own depth bin, pooled over two frames (each frame's pixels counted), the
    bins between them empty, and a slanted surface (slope 0.1) does not count as flat."""
    def frame(seed):
        near = _surface_depth(0.0, 0.04, seed=seed, base_px=FB / 0.55)
        far = _surface_depth(0.0, 0.09, seed=seed + 10, base_px=FB / 1.5)
        return np.concatenate([near, far], axis=1)

    one = flat_roughness_by_depth([surface_residuals(frame(0), FB)])
    rows = flat_roughness_by_depth([surface_residuals(frame(0), FB), surface_residuals(frame(1), FB)])
    by_bin = {tuple(row["depth_m"]): row for row in rows}
    assert by_bin[(0.5, 0.6)]["roughness_px"] == pytest.approx(0.04 * np.sqrt(1 - 6 / 225), rel=0.05)
    assert by_bin[(1.25, 1.6)]["roughness_px"] == pytest.approx(0.09 * np.sqrt(1 - 6 / 225), rel=0.05)
    assert by_bin[(0.5, 0.6)]["pixels"] == 2 * one[0]["pixels"] > 2000
    assert all(row["roughness_px"] is None and row["pixels"] == 0 for row in rows[1:5]), rows
    slanted = flat_roughness_by_depth([surface_residuals(_surface_depth(0.1, 0.04, base_px=FB / 0.55), FB)])
    assert slanted[0]["pixels"] == 0


def test_the_pool_keeps_a_bounded_uniform_sample_and_counts_every_residual():
    """A long folder streams: per bin at most ``cap`` residuals are kept, a uniform sample of all added (the robust
    sigma of 20 frames of 0.08 px noise then 20 of 0.04 px is their mix's, not the first or last frames'), every
    residual is counted, the same frames give the same sample, and without a cap the pool is exact."""
    rng = np.random.default_rng(5)
    frames = [[rng.normal(0.0, 0.04 if k >= 20 else 0.08, 5000).astype(np.float32), np.empty(0, np.float32)]
              for k in range(40)]  # fmt: skip
    exact = robust_sigma(np.concatenate([f[0] for f in frames]))

    def pooled(cap, seed=0):
        pool = FlatRoughnessPool(bins=(0.5, 1.0, 2.0), cap=cap, seed=seed)
        for per_bin in frames:
            pool.add(per_bin)
        return pool

    bounded = pooled(cap=20_000)
    rows = bounded.rows()
    assert rows[0]["pixels"] == 40 * 5000 and rows[1] == {"depth_m": [1.0, 2.0], "roughness_px": None, "pixels": 0}
    assert len(bounded._values[0]) == 20_000
    assert rows[0]["roughness_px"] == pytest.approx(exact, rel=0.02)
    assert pooled(cap=20_000).rows() == rows  # seeded: the same sample
    assert pooled(cap=None).rows()[0]["roughness_px"] == exact
    with pytest.raises(ValueError, match="bins"):
        bounded.add([np.zeros(3, np.float32)])


def test_windows_across_a_depth_edge_do_not_count():
    """A near board in front of a far one: the fits across the edge are dropped, so the roughness stays the noise."""
    depth = _surface_depth(0.0, 0.05, seed=1)
    depth[:, 80:] = _surface_depth(0.0, 0.05, seed=2, base_px=27.0)[:, 80:]  # 13 px of disparity further
    fit = local_quadratic_fit(FB / depth, np.ones(depth.shape, bool), stride=2)
    across = fit.fitted & (np.abs(np.arange(160) - 79.5) < 7)[None, :]  # windows that hold both boards
    assert across.sum() > 100 and (fit.window_rms[across] > 1.0).all()
    assert (fit.window_rms[fit.fitted & ~across] < 0.06).all()
    stats = surface_roughness(depth, FB)
    assert stats["flat_roughness_px"] == pytest.approx(0.05 * np.sqrt(1 - 6 / 225), rel=0.05)
    assert stats["slanted_roughness_px"] is None and stats["slant_roughness_ratio"] is None


def test_only_usable_pixels_enter_and_thin_windows_are_not_fitted():
    """Invalid pixels and pixels outside the region never enter a fit; a window under 90 % usable is not fitted."""
    depth = _surface_depth(0.0, 0.0)
    usable = np.ones(depth.shape, bool)
    usable[:, ::4] = False  # 75 % of every window
    fit = local_quadratic_fit(FB / depth, usable)
    assert not fit.fitted.any() and np.isnan(fit.residual).all()
    depth[50:70, 70:90] = 0.0  # a hole: the pixels near it are not fitted, the rest are exact
    region = np.zeros(depth.shape, bool)
    region[:, :100] = True
    residuals = surface_residuals(depth, FB, region=region)
    assert 0 < len(residuals.residual) < (100 * 120) / 4 and np.abs(residuals.residual).max() < 1e-9


def test_the_noise_grain_is_the_correlation_of_neighbours_along_rows_and_columns():
    """White noise has no grain (correlation 0 both ways, less the fit's own -1/225-ish); noise smoothed along the
    rows by [1, 2, 1] / 4 has the known correlation 2/3 between row neighbours and none between column ones."""
    import cv2

    white = surface_roughness(_surface_depth(0.0, 0.06, seed=3, h=240, w=320), FB)
    assert abs(white["noise_correlation_row"]) < 0.05 and abs(white["noise_correlation_column"]) < 0.05
    u, v = np.meshgrid(np.arange(320.0), np.arange(240.0))
    noise = cv2.filter2D(np.random.default_rng(4).normal(0.0, 0.1, (240, 320)), -1, np.array([[0.25, 0.5, 0.25]]))
    grained = surface_roughness(FB / (40.0 + 0.001 * u + noise), FB)
    assert grained["noise_correlation_row"] == pytest.approx(2 / 3, abs=0.06)
    assert abs(grained["noise_correlation_column"]) < 0.05


@pytest.mark.skipif(not (SHARED / "icbin_primesense_unpaired").is_dir(), reason="shared real data not present")
def test_real_primesense_depth_is_rougher_where_the_disparity_runs_steeply():
    """The nine real IC-BIN frames: about 0.05 px on surfaces facing the camera, about twice that at slopes of
    0.07-0.15 px per px (a board at 1 m turned by 50-65 deg). Nguyen 2012's 10-60 deg curve has no such rise."""
    import cv2

    rows = [surface_roughness(cv2.imread(str(p), cv2.IMREAD_UNCHANGED) / 1000.0, 550.0 * 0.075)
            for p in sorted((SHARED / "icbin_primesense_unpaired").glob("seq*/depth/*.png"))]  # fmt: skip
    assert len(rows) == 9
    flat = [row["flat_roughness_px"] for row in rows]
    ratios = [row["slant_roughness_ratio"] for row in rows]
    assert 0.04 <= min(flat) and max(flat) <= 0.07, flat
    assert min(ratios) >= 1.2 and 1.4 <= np.median(ratios) <= 2.0, ratios
