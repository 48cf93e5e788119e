"""Frames of the built-in scene list rendered with kinect_v1, against the statistics of real PrimeSense frames
(holes, registration bands, outlines, roughness; ddsgen.depth_statistics, ddsgen.surface_roughness)."""

from pathlib import Path

import numpy as np
import pytest

from ddsgen.depth_jumps import narrow_band_slits, wide_band_holes
from ddsgen.depth_statistics import isolated_dropout_orientation, isolated_dropouts_by_rim, realism_statistics

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"
#: f b (px m) of the rendered frames (kinect_v1: fx 572.41 px, b 7.5 cm).
RENDER_FB = 572.41 * 0.075


@pytest.fixture(scope="module")
def default_frames(tmp_path_factory) -> list[np.ndarray]:
    """Depth (m) of the first four frames of the built-in scene list with kinect_v1, seed 0."""
    import cv2

    from ddsgen.runner import render_dataset

    out = tmp_path_factory.mktemp("default_frames")
    preset = Path(__file__).resolve().parents[1] / "presets" / "kinect_v1.yaml"
    render_dataset(str(preset), None, 4, out, workers=1, seed=0, progress=False)
    return [cv2.imread(str(p), cv2.IMREAD_UNCHANGED).astype(np.float64) / 1000.0
            for p in sorted((out / "depth").glob("*.png"))]  # fmt: skip


def test_rendered_frames_have_few_isolated_dropouts_inside_one_surface(default_frames):
    """Like the real frames (18 % of their isolated dropouts, 71 of 386, per frame 0.05-0.33), most of the
    renders' isolated dropouts sit at depth edges: the registration no longer draws its band inside the near
    surface (measured on these four frames: 24 of 132 mapped forward, kinect_v1 since session 35; mapped back by the
    geometry 17 of 156 with session 33's band fill, 159 of 301 without)."""
    inside, at_edge = np.sum([isolated_dropouts_by_rim(depth) for depth in default_frames], axis=0)
    assert at_edge >= 40
    assert inside / (inside + at_edge) <= 0.35


def test_rendered_frames_have_as_few_isolated_dropouts_per_edge_as_real_ones(default_frames):
    """Per 1000 px of depth edge, the renders' isolated dropouts stay near the real frames' 5.3-11.0 (10 real
    frames; TUM 8.5): on average over these four frames at most the real maximum, and no frame beyond 16. Measured
    (session 39, primary rays by the C raster): 11.3, 5.6, 12.2, 7.2 (mean 9.1); over 16 frames 3.0-15.3, median
    7.0. The same frames cast by Embree alone: 10.0, 6.0, 11.4, 5.4; 16 frames 4.3-15.1, median 7.6. The speckle
    is seeded by a hash of the cast geometry, so a change of its last bits redraws it: one frame's value moves by
    a few units, which is why a bound per frame at the real maximum was too tight. Failed (strict xfail) until
    session 34 moved the built-in list to tabletop range: with sparse far scenes frame 2 had 13.4, its edge holes
    on little edge."""
    per_edge = [realism_statistics(depth)["isolated_dropouts_per_1000_edge_px"] for depth in default_frames]
    assert np.mean(per_edge) <= 11.0 and max(per_edge) <= 16.0, per_edge


def test_rendered_frames_keep_wide_registration_bands_open_like_real_ones(default_frames):
    """Real registered frames keep bands of 6 px and more open (IC-BIN 694 of 708). Measured on these four frames:
    525 of 526, mapped forward by the measured depth (kinect_v1 since session 35); mapped back by the ray-cast
    geometry 8 of 460 (a strict xfail until then: the matcher's carry showed one band further on and closed it)."""
    kept, jumps = np.sum([wide_band_holes(depth) for depth in default_frames], axis=0)
    assert jumps >= 100
    assert kept >= 0.85 * jumps


@pytest.mark.xfail(strict=True, reason="the forward map's row fill closes every band up to 4 px (session 48)")
def test_rendered_frames_leave_narrow_registration_bands_as_a_slit_like_real_ones(default_frames):
    """Real devices leave a 1-2 px slit at 14-23 % of the rows crossing a 3-6 px band (three devices). The renders
    close them, or leave the whole band: measured on these four frames 20 of 641 (0.03). A fill of 3 px instead of 4
    reaches 0.20 on 16 frames but closes only 14 % of the 4-6 px bands (real 43-70 %): the slits are a per-row
    effect the map does not have (docs/validation.md)."""
    slits, jumps = np.sum([narrow_band_slits(depth) for depth in default_frames], axis=0)
    assert jumps >= 50
    assert slits >= 0.10 * jumps


def test_rendered_frames_have_vertical_and_horizontal_isolated_dropouts_like_real_ones(default_frames):
    """Real frames: 0.58 of the elongated isolated dropouts vertical (pooled). Measured on these four frames: 36 of 53
    (0.68; 16 frames 0.63). Mapped back by the geometry: 46 of 51 (slivers beside near surfaces); forward without
    the fill across rows: 14 of 51 (dashes along near-horizontal edges)."""
    vertical, horizontal = np.sum([isolated_dropout_orientation(depth > 0) for depth in default_frames], axis=0)
    assert vertical + horizontal >= 20
    assert 0.4 <= vertical / (vertical + horizontal) <= 0.75


def test_rendered_frames_outlines_are_as_ragged_as_real_ones(default_frames):
    """Within the real frames' band above: measured on these four frames 0.66-0.72 px (16 frames 0.62-0.77, median
    0.68; the paper preset's 0.72-0.83; the frames' own ray-cast depth 0.31-0.48)."""
    from ddsgen.silhouette_edges import outline_jitter

    for depth in default_frames:
        outline = outline_jitter(depth)
        assert outline["outline_rows"] >= 300
        assert 0.55 <= outline["outline_jitter_px"] <= 0.85, outline


@pytest.mark.xfail(strict=True, reason="session 38: the renders' isolated dropouts are 1.6x the real ones' size")
def test_rendered_frames_have_isolated_dropouts_as_small_as_real_ones(default_frames):
    """Real frames: mean isolated-dropout size 2.8-4.6 px per frame (IC-BIN; the cat 3.7, TUM 2.5), 1-2 px holes
    most common. Measured on these four frames: 4.8, 6.8, 6.7, 7.1 px (48 frames: median 6.1, 2.5-10.7): fragments of
    projector shadows and registration bands along slanted edges, 3-6 px wide and 2-4 rows tall (docs/validation.md,
    "The size of the isolated dropouts"). Strict: it fails loudly once the renders get there."""
    sizes = [realism_statistics(depth)["isolated_dropout_mean_px"] for depth in default_frames]
    assert np.median(sizes) <= 5.0, sizes



def test_rendered_frames_are_as_rough_as_real_ones_where_flat_and_where_slanted(default_frames):
    """Roughness in disparity and its grain (ddsgen.surface_roughness) on the renders, against the real frames'
    (IC-BIN 0.048-0.066 px where flat, slanted / flat 1.28-1.72, median 1.56; the LineMOD cat 0.060 and 1.85). The
    paper preset's renders are 0.069-0.102 px where flat and rise 1.06-1.64x (docs/validation.md)."""
    rows = [realism_statistics(depth, disparity_fb=RENDER_FB) for depth in default_frames]
    assert all(0.045 <= row["flat_roughness_px"] <= 0.075 for row in rows), rows
    assert 1.3 <= float(np.median([row["slant_roughness_ratio"] for row in rows])) <= 2.0, rows
    assert realism_statistics(default_frames[0])["flat_roughness_px"] is None  # without f b: not measured
    # The noise's grain: real frames 0.53-0.67 between row neighbours, 0.34-0.56 between column neighbours (the
    # device smooths along its rows, row_smoothing_weight; without it the renders were 0.43 / 0.43).
    row = float(np.median([r["noise_correlation_row"] for r in rows]))
    column = float(np.median([r["noise_correlation_column"] for r in rows]))
    assert 0.53 <= row <= 0.70 and 0.28 <= column <= 0.56 and row > column + 0.1, rows


@pytest.mark.skipif(not (SHARED / "icbin_primesense_unpaired").is_dir(), reason="../shared/data is absent")
def test_rendered_frames_are_as_rough_as_real_ones_at_every_depth(default_frames):
    """The disparity noise against distance, where flat, judged by real frames (ddsgen.surface_roughness
    .flat_roughness_by_depth; IC-BIN with a Carmine's nominal f b, the cat with LineMOD's). Measured in the bins of
    DEPTH_BINS_M (0.5-2.2 m): real 0.062, 0.064, 0.051, 0.051, 0.052, 0.056, 0.055 px, flat with depth; these four
    frames 0.061, 0.059, 0.061, 0.061, 0.063, 0.059, 0.055 (16 frames 0.053-0.063); the paper preset's 0.097-0.102.
    Nguyen 2012's sigma_z read as disparity (sigma_z f b / z^2) rises to 0.176 px at 0.55 m, 2.8x the real frames'
    roughness there: the near-range points of `ddsgen study noise` are judged against these frames too
    (docs/validation.md)."""
    import cv2

    from ddsgen.study.noise import nguyen_sigma_px
    from ddsgen.surface_roughness import flat_roughness_by_depth, surface_residuals

    def residuals(path, fb):
        return surface_residuals(cv2.imread(str(path), cv2.IMREAD_UNCHANGED) / 1000.0, fb)

    icbin = sorted((SHARED / "icbin_primesense_unpaired").glob("seq*/depth/*.png"))
    real = [residuals(path, 550.0 * 0.075) for path in icbin]
    real.append(residuals(SHARED / "linemod_bop" / "test" / "000006" / "depth" / "000000.png", RENDER_FB))
    real_rows = flat_roughness_by_depth(real)
    sim_rows = flat_roughness_by_depth([surface_residuals(depth, RENDER_FB) for depth in default_frames])
    ratios = [sim_row["roughness_px"] / real_row["roughness_px"] for real_row, sim_row in zip(real_rows, sim_rows)
              if min(real_row["pixels"], sim_row["pixels"]) >= 2000]  # fmt: skip
    # Per bin within 0.7-1.4x, and 0.85-1.2x at the median (measured on these four frames 0.94-1.22, median 1.06;
    # on other blocks of four of the first 16 frames 0.88-1.30, medians 1.01-1.16).
    assert len(ratios) >= 6 and all(0.7 <= r <= 1.4 for r in ratios), (ratios, real_rows, sim_rows)
    assert 0.85 <= float(np.median(ratios)) <= 1.2, (ratios, real_rows, sim_rows)
    # At 0.5-0.7 m the real device is far quieter than Nguyen's curve, and so are the renders.
    for real_row, sim_row in zip(real_rows[:2], sim_rows[:2]):
        assert real_row["roughness_px"] is not None and sim_row["roughness_px"] is not None, (real_rows, sim_rows)
        nguyen_px = float(nguyen_sigma_px(np.mean(real_row["depth_m"]), RENDER_FB))
        assert real_row["roughness_px"] < 0.5 * nguyen_px and sim_row["roughness_px"] < 0.5 * nguyen_px
