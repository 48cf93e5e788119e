"""Frames of the built-in scene list rendered with kinect_v1 (seed RENDER_SEED, not a seed the preset was tuned on),
against the range of the real frames (tests/realframes.py: IC-BIN, the LineMOD cat, TUM, the raw NYU frame).

Every bound is the real frames' range, measured here on the frames themselves; a bound the renders miss today stays
as a strict xfail with the measured values. The tune / check split of the real frames: docs/validation.md."""

import numpy as np
import pytest

from ddsgen.depth_jumps import narrow_band_slits, wide_band_holes
from ddsgen.depth_statistics import (
    corner_valid_share,
    isolated_dropout_orientation,
    isolated_dropouts_by_rim,
    normalised_radius,
    radial_valid_profile,
    realism_statistics,
)
from ddsgen.silhouette_edges import outline_jitter
from tests.realframes import REGISTERED, SHARED, real_frames

pytestmark = pytest.mark.skipif(not (SHARED / "icbin_primesense_unpaired").is_dir(), reason="../shared/data is absent")

#: f b (px m) of the rendered frames (kinect_v1: fx 572.41 px, b 7.5 cm).
RENDER_FB = 572.41 * 0.075
#: The renders' seed: kinect_v1 was tuned on seeds 0 and 3 of the built-in list.
RENDER_SEED = 7


@pytest.fixture(scope="module")
def default_frames(tmp_path_factory) -> list[np.ndarray]:
    """Depth (m) of the first four frames of the built-in scene list with kinect_v1, seed RENDER_SEED."""
    import cv2

    from ddsgen.runner import render_dataset

    out = tmp_path_factory.mktemp("default_frames")
    preset = __import__("pathlib").Path(__file__).resolve().parents[1] / "presets" / "kinect_v1.yaml"
    render_dataset(str(preset), None, 4, out, workers=1, seed=RENDER_SEED, progress=False)
    return [cv2.imread(str(p), cv2.IMREAD_UNCHANGED).astype(np.float64) / 1000.0
            for p in sorted((out / "depth").glob("*.png"))]  # fmt: skip


@pytest.fixture(scope="module")
def real() -> dict[str, dict]:
    """Name -> the statistics of one real frame (realism_statistics plus the counts the tests below use)."""
    rows = {}
    for name, (depth, fb) in real_frames().items():
        row = realism_statistics(depth, disparity_fb=fb)
        row["inside"], row["at_edge"] = isolated_dropouts_by_rim(depth)
        row["slits"], row["narrow_jumps"] = narrow_band_slits(depth)
        row["wide_kept"], row["wide_jumps"] = wide_band_holes(depth)
        row["vertical"], row["horizontal"] = isolated_dropout_orientation(depth > 0)
        row["outline_jitter_px"] = outline_jitter(depth)["outline_jitter_px"]
        row["radial_profile"] = radial_valid_profile(depth > 0)
        row["window_radial_profile"] = radial_valid_profile(depth > 0, in_window=True)
        corner, whole = corner_valid_share(depth > 0, in_window=True)
        row["window_whole_minus_corner"] = whole - corner
        rows[name] = row
    return rows


def real_range(real: dict[str, dict], value, names=None) -> tuple[float, float]:
    """(min, max) of value(row) over the real frames named (all by default) where it is measured."""
    values = [value(real[name]) for name in (names or real)]
    values = [v for v in values if v is not None]
    return min(values), max(values)


def test_rendered_frames_have_few_isolated_dropouts_inside_one_surface(default_frames, real):
    """Share of the isolated dropouts that sit inside one surface rather than at a depth edge, pooled over the four
    renders, within the registered real frames' range (per frame 0.05-0.33; the raw NYU frame, 0.52, is left out:
    registration is what moves dropouts off the surfaces' insides). Measured: 29 of 138 (0.21)."""
    low, high = real_range(real, lambda r: r["inside"] / (r["inside"] + r["at_edge"]), REGISTERED)
    inside, at_edge = np.sum([isolated_dropouts_by_rim(depth) for depth in default_frames], axis=0)
    assert at_edge >= 40
    assert low <= inside / (inside + at_edge) <= high, (inside, at_edge, low, high)


def test_rendered_frames_have_as_many_isolated_dropouts_per_edge_as_real_ones_on_average(default_frames, real):
    """Isolated dropouts per 1000 px of depth edge, the mean of the four renders, within the real frames' range
    (5.3-11.0). Measured: 11.2, 9.7, 4.8, 9.4 (mean 8.7)."""
    low, high = real_range(real, lambda r: r["isolated_dropouts_per_1000_edge_px"])
    per_edge = [realism_statistics(depth)["isolated_dropouts_per_1000_edge_px"] for depth in default_frames]
    assert low <= np.mean(per_edge) <= high, (per_edge, low, high)


@pytest.mark.xfail(strict=True, reason="measured 11.2, 9.7, 4.8, 9.4 against real 5.3-11.0: a sparse frame (2) has"
                   " few edges and the dropouts of a busy one (0) are a little too many")  # fmt: skip
def test_rendered_frames_have_as_many_isolated_dropouts_per_edge_as_real_ones_on_every_frame(default_frames, real):
    """As above, every frame within the real frames' range."""
    low, high = real_range(real, lambda r: r["isolated_dropouts_per_1000_edge_px"])
    per_edge = [realism_statistics(depth)["isolated_dropouts_per_1000_edge_px"] for depth in default_frames]
    assert all(low <= value <= high for value in per_edge), (per_edge, low, high)


def test_rendered_frames_keep_wide_registration_bands_open_like_real_ones(default_frames, real):
    """Share of the bands of 6 px and more left open, pooled, at least the registered real frames' least (0.92 on
    frames with >= 20 such bands; the raw NYU frame has no registration bands). Measured: 540 of 541."""
    low, _ = real_range(real, lambda r: r["wide_kept"] / r["wide_jumps"] if r["wide_jumps"] >= 20 else None,
                        REGISTERED)  # fmt: skip
    kept, jumps = np.sum([wide_band_holes(depth) for depth in default_frames], axis=0)
    assert jumps >= 100
    assert kept >= low * jumps, (kept, jumps, low)


@pytest.mark.xfail(strict=True, reason="measured 4 of 449 (0.01) against real 0.10-0.30: the forward map's row fill"
                   " closes every band up to 4 px; the slits are a per-row effect the map does not have")  # fmt: skip
def test_rendered_frames_leave_narrow_registration_bands_as_a_slit_like_real_ones(default_frames, real):
    """Real registered frames leave a 1-2 px slit at 10-30 % of the rows crossing a 3-6 px band (frames with >= 50
    such rows); pooled over the four renders the share must lie within that range."""
    low, high = real_range(real, lambda r: r["slits"] / r["narrow_jumps"] if r["narrow_jumps"] >= 50 else None,
                           REGISTERED)  # fmt: skip
    slits, jumps = np.sum([narrow_band_slits(depth) for depth in default_frames], axis=0)
    assert jumps >= 50
    assert low <= slits / jumps <= high, (slits, jumps, low, high)


def test_rendered_frames_have_vertical_and_horizontal_isolated_dropouts_like_real_ones(default_frames, real):
    """Share of the elongated isolated dropouts that are vertical, pooled over the renders, within the real frames'
    range (0.31-0.86 per frame with >= 9 elongated dropouts). Measured: 22 of 46 (0.48)."""
    low, high = real_range(real, lambda r: r["vertical"] / (r["vertical"] + r["horizontal"])
                           if r["vertical"] + r["horizontal"] >= 9 else None)  # fmt: skip
    vertical, horizontal = np.sum([isolated_dropout_orientation(depth > 0) for depth in default_frames], axis=0)
    assert vertical + horizontal >= 20
    assert low <= vertical / (vertical + horizontal) <= high, (vertical, horizontal, low, high)


@pytest.mark.xfail(strict=True, reason="measured 0.701, 0.703, 0.632, 0.644 px against the registered real frames'"
                   " 0.633-0.765: frame 2 is 0.001 px too smooth")  # fmt: skip
def test_rendered_frames_outlines_are_as_ragged_as_real_ones(default_frames, real):
    """Outline jitter of every render within the registered real frames' range (0.633-0.765 px; the raw NYU frame,
    0.585, is left out: registration's forward map adds its own raggedness)."""
    low, high = real_range(real, lambda r: r["outline_jitter_px"], REGISTERED)
    for depth in default_frames:
        outline = outline_jitter(depth)
        assert outline["outline_rows"] >= 300
        assert low <= outline["outline_jitter_px"] <= high, (outline, low, high)


@pytest.mark.xfail(strict=True, reason="measured 6.7, 6.9, 6.9, 6.6 px against real 2.5-4.6: fragments of projector"
                   " shadows and registration bands along slanted edges, 3-6 px wide (docs/validation.md)")  # fmt: skip
def test_rendered_frames_have_isolated_dropouts_as_small_as_real_ones(default_frames, real):
    """Mean isolated-dropout size of every render within the real frames' range (2.5-4.6 px)."""
    low, high = real_range(real, lambda r: r["isolated_dropout_mean_px"])
    sizes = [realism_statistics(depth)["isolated_dropout_mean_px"] for depth in default_frames]
    assert all(low <= size <= high for size in sizes), (sizes, low, high)


def test_rendered_frames_are_as_rough_as_real_ones_where_flat_and_where_slanted(default_frames, real):
    """Roughness in disparity (ddsgen.surface_roughness) and its grain: the median of the four renders within the
    real frames' range (flat 0.048-0.065 px; slanted / flat 1.28-3.58; correlation between row neighbours
    0.50-0.67, between column neighbours 0.34-0.56, rows at least 0.05 above columns as on every real frame).
    Measured: flat 0.060, slanted / flat 2.19, row 0.60, column 0.37."""
    rows = [realism_statistics(depth, disparity_fb=RENDER_FB) for depth in default_frames]
    assert realism_statistics(default_frames[0])["flat_roughness_px"] is None  # without f b: not measured
    for key in ("flat_roughness_px", "slant_roughness_ratio", "noise_correlation_row", "noise_correlation_column"):
        low, high = real_range(real, lambda r: r[key])
        assert low <= float(np.median([row[key] for row in rows])) <= high, (key, low, high, rows)
    gap, _ = real_range(real, lambda r: r["noise_correlation_row"] - r["noise_correlation_column"])
    assert all(row["noise_correlation_row"] - row["noise_correlation_column"] >= gap for row in rows), (gap, rows)


@pytest.mark.xfail(strict=True, reason="measured flat roughness 0.064, 0.066, 0.057, 0.054 px against real"
                   " 0.048-0.065: frame 1 is 0.001 px rougher")  # fmt: skip
def test_every_rendered_frame_is_as_rough_as_real_ones_where_flat(default_frames, real):
    """The flat roughness of every render within the real frames' range."""
    low, high = real_range(real, lambda r: r["flat_roughness_px"])
    values = [realism_statistics(depth, disparity_fb=RENDER_FB)["flat_roughness_px"] for depth in default_frames]
    assert all(low <= value <= high for value in values), (values, low, high)


def test_rendered_frames_are_as_rough_as_real_ones_at_every_depth(default_frames):
    """The disparity noise against distance, where flat, judged by the real frames (ddsgen.surface_roughness
    .flat_roughness_by_depth; IC-BIN with a Carmine's nominal f b, the cat with LineMOD's): real 0.051-0.064 px in
    the bins of DEPTH_BINS_M (0.5-2.2 m), flat with depth. Per bin the renders' / the real roughness within
    0.7-1.4x and 0.85-1.2x at the median. At 0.5-0.7 m the real device is far quieter than Nguyen 2012's curve
    (sigma_z f b / z^2, 0.176 px at 0.55 m): the renders are judged by the real frames there, not by Nguyen
    (docs/validation.md; measured at 0.6-0.7 m: real 0.064 px, renders 0.069 px, Nguyen 0.134 px)."""
    from ddsgen.study.noise import nguyen_sigma_px
    from ddsgen.surface_roughness import flat_roughness_by_depth, surface_residuals
    from tests.realframes import real_frames as frames

    real_residuals = [surface_residuals(depth, fb) for name, (depth, fb) in frames().items()
                      if name.startswith("icbin") or name == "linemod_cat"]  # fmt: skip
    real_rows = flat_roughness_by_depth(real_residuals)
    sim_rows = flat_roughness_by_depth([surface_residuals(depth, RENDER_FB) for depth in default_frames])
    ratios = [sim_row["roughness_px"] / real_row["roughness_px"] for real_row, sim_row in zip(real_rows, sim_rows)
              if min(real_row["pixels"], sim_row["pixels"]) >= 2000]  # fmt: skip
    assert len(ratios) >= 6 and all(0.7 <= r <= 1.4 for r in ratios), (ratios, real_rows, sim_rows)
    assert 0.85 <= float(np.median(ratios)) <= 1.2, (ratios, real_rows, sim_rows)
    near = [(real_row, sim_row) for real_row, sim_row in zip(real_rows[:2], sim_rows[:2])
            if min(real_row["pixels"], sim_row["pixels"]) >= 2000]  # fmt: skip
    assert near, (real_rows, sim_rows)
    for real_row, sim_row in near:
        nguyen_px = float(nguyen_sigma_px(np.mean(real_row["depth_m"]), RENDER_FB))
        # The real frames sit below half of Nguyen's curve; the renders are judged by them (the ratios above).
        assert real_row["roughness_px"] < 0.5 * nguyen_px, (real_row, sim_row)


def test_rendered_frames_lose_validity_towards_the_corners_like_real_ones(default_frames, real):
    """Validity by image radius inside each frame's output window (ddsgen.depth_statistics.radial_valid_profile's
    ``in_window``: the border bands a device never fills are its window, measured on their own; the IC-BIN device's,
    33-39 px right and 10-11 px top and bottom, cut through the corners and are most of what those frames lose there
    over the whole image). Every render is less valid beyond 0.7 of the half-diagonal than over its window by an amount
    within the real frames' range (0.01-0.21), and the renders' mean ring profile lies within the real frames' range
    ring by ring."""
    low, high = real_range(real, lambda r: r["window_whole_minus_corner"])
    for depth in default_frames:
        corner, whole = corner_valid_share(depth > 0, in_window=True)
        assert low <= whole - corner <= high, (whole, corner, low, high)
    profiles = np.array([radial_valid_profile(depth > 0, in_window=True) for depth in default_frames])
    real_profiles = np.array([r["window_radial_profile"] for r in real.values()])
    mean = profiles.mean(axis=0)
    low, high = real_profiles.min(axis=0), real_profiles.max(axis=0)
    assert np.all(low <= mean) and np.all(mean <= high), (mean, real_profiles)
