"""Hole, validity and quantisation statistics (ddsgen.depth_statistics) on made-up and real frames."""

from pathlib import Path

import numpy as np
import pytest

from ddsgen.depth_jumps import holes_at_depth_jumps, narrow_band_slits, wide_band_holes
from ddsgen.depth_statistics import (blind_border_bands, corner_valid_share, depth_edges, depth_step_at_1m,
                                     isolated_dropout_orientation, isolated_dropouts, isolated_dropouts_by_rim,
                                     radial_valid_profile, realism_statistics)

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"


def test_isolated_dropouts_count_small_components_only():
    valid = np.ones((100, 100), bool)
    valid[10, 10] = False  # 1 px speck
    valid[50:53, 50:53] = False  # 9 px
    valid[70:90, 0:40] = False  # a 800 px hole: clustered, not isolated
    count, share = isolated_dropouts(valid)
    assert count == 2
    assert share == pytest.approx(10 / 810)
    # A region that sees only the big hole counts no isolated dropout.
    region = np.zeros_like(valid)
    region[60:100, :] = True
    assert isolated_dropouts(valid, region) == (0, 0.0)


def test_isolated_dropouts_mean_size_is_over_whole_components():
    valid = np.ones((100, 100), bool)
    valid[10, 10] = False  # 1 px
    valid[50:53, 50:53] = False  # 9 px
    valid[70:90, 0:40] = False  # 800 px: clustered, not counted
    assert realism_statistics(np.where(valid, 1.0, 0.0))["isolated_dropout_mean_px"] == pytest.approx(5.0)
    assert realism_statistics(np.ones((50, 50)))["isolated_dropout_mean_px"] is None


def test_the_share_off_the_blind_border_leaves_the_border_bands_out_of_the_invalid_pixels():
    valid = np.ones((100, 120), bool)
    valid[:, -10:] = False  # a registration border: 10 blind columns on the right ...
    valid[:3, :] = False  # ... and 3 rows at the top
    valid[40, 40] = valid[40, 41] = valid[41, 40] = valid[41, 41] = False  # a 4 px isolated dropout
    valid[60:65, 20:26] = False  # a 30 px hole: not isolated
    valid[50, :30] = False  # a line across from the left edge: not a band (other rows of those columns are valid)
    bands = blind_border_bands(valid)
    assert bands[:, -10:].all() and bands[:3].all() and bands.sum() == 100 * 10 + 3 * 110
    s = realism_statistics(np.where(valid, 1.0, 0.0))
    assert s["isolated_dropout_share"] == pytest.approx(4 / (1330 + 4 + 30 + 30))
    assert s["isolated_dropout_share_off_border"] == pytest.approx(4 / (4 + 30 + 30))
    assert blind_border_bands(np.zeros((5, 6), bool)).all() and not blind_border_bands(np.ones((5, 6), bool)).any()


def test_corner_valid_share_sees_only_the_corners():
    valid = np.ones((120, 160), bool)
    valid[:20, :20] = False
    corner, whole = corner_valid_share(valid)
    assert whole == pytest.approx(1 - 400 / (120 * 160))
    assert corner < whole - 0.05  # the hole sits in a corner
    valid[:20, :20] = True
    valid[50:70, 70:90] = False  # same hole at the centre: corners untouched
    assert corner_valid_share(valid)[0] == 1.0


def test_inside_the_output_window_a_devices_border_bands_are_not_corner_loss():
    """A device that never fills its 10 rightmost columns and 3 top rows (IC-BIN's device leaves 33-39 and 10-11 at
    640 x 480): over the whole image its corners look emptier, inside its window they are whole; a hole inside the
    window still counts."""
    valid = np.ones((120, 160), bool)
    valid[:, -10:] = False
    valid[:3] = False
    corner, whole = corner_valid_share(valid)
    assert corner < whole - 0.1
    assert corner_valid_share(valid, in_window=True) == (1.0, 1.0)
    assert radial_valid_profile(valid, in_window=True) == [1.0] * 5 and radial_valid_profile(valid)[-1] < 0.8
    valid[3:20, :20] = False  # a hole in the top-left corner, inside the window
    corner, whole = corner_valid_share(valid, in_window=True)
    assert corner < whole - 0.05


@pytest.mark.parametrize("n_sub, resolution", [(3, 0.0), (3, 0.001), (2, 0.001)])
def test_depth_step_of_a_quantised_ramp(n_sub, resolution):
    """A ramp 0.7-1.5 m quantised to 2^-n_sub px of disparity (f 572.41 px, b 75 mm) -> z^2/(2^n f b) at 1 m."""
    fb = 572.41 * 0.075
    z = np.linspace(0.7, 1.5, 200 * 300).reshape(200, 300)
    d = np.round(fb / z * 2**n_sub) / 2**n_sub
    depth = fb / d
    if resolution:
        depth = np.round(depth / resolution) * resolution  # millimetre PNG
    expected = 1.0 / (2**n_sub * fb)
    assert depth_step_at_1m(depth, resolution_m=resolution) == pytest.approx(expected, rel=0.03)


def box_on_a_wall(hole_left_px: int, hole_right_px: int, rows_with_holes: int = 60) -> np.ndarray:
    """(100, 120) m: a wall at 1.2 m, a box at 0.8 m over columns 40-79, holes beside the box on some rows."""
    depth = np.full((100, 120), 1.2)
    depth[20:80, 40:80] = 0.8
    depth[20 : 20 + rows_with_holes, 40 - hole_left_px : 40] = 0.0
    depth[20 : 20 + rows_with_holes, 80 : 80 + hole_right_px] = 0.0
    return depth


def test_holes_at_depth_jumps_tell_the_shadow_side_from_the_other():
    """A projector-shadow band left of the box: every left jump has a hole, no right one; a hole-free box has none;
    mirrored, the sides swap; holes on half the rows give half the share."""
    left, right = holes_at_depth_jumps(box_on_a_wall(12, 0))
    assert (left, right) == (1.0, 0.0)
    assert holes_at_depth_jumps(box_on_a_wall(0, 0)) == (0.0, 0.0)
    assert holes_at_depth_jumps(box_on_a_wall(12, 0)[:, ::-1]) == (0.0, 1.0)
    assert holes_at_depth_jumps(box_on_a_wall(3, 2, rows_with_holes=30)) == (0.5, 0.5)
    # Small steps (a 2 % slope break) and a region without the box are no jumps.
    ramp = np.full((50, 80), 1.0)
    ramp[:, 40:] = 1.02
    assert holes_at_depth_jumps(ramp) == (None, None)
    region = np.zeros((100, 120), bool)
    region[85:, :] = True
    assert holes_at_depth_jumps(box_on_a_wall(12, 0), region) == (None, None)


@pytest.mark.skipif(not (SHARED / "icbin_primesense_unpaired").is_dir(), reason="../shared/data is absent")
def test_real_primesense_frames_have_clustered_holes_and_eighth_pixel_steps():
    import cv2

    files = sorted((SHARED / "icbin_primesense_unpaired").glob("seq*/depth/*.png"))
    assert files
    for path in files:
        depth = cv2.imread(str(path), cv2.IMREAD_UNCHANGED).astype(np.float64) / 1000.0
        s = realism_statistics(depth)
        assert 15 <= s["isolated_dropouts"] <= 60, path
        assert s["isolated_dropout_share"] < 0.01, path
        assert s["corner_valid_share"] < s["valid_share"] - 0.1, path
        assert s["depth_step_at_1m_mm"] == pytest.approx(2.92, rel=0.03), path
        # Most depth jumps have no hole between the surfaces, on either side (measured 0.09-0.58 left, 0.21-0.49
        # right): the device fills most of its geometric projector shadow.
        assert s["jump_holes_left"] < 0.65 and s["jump_holes_right"] < 0.55, path
        # Their isolated dropouts are few for the edges they have (measured 5.3-11.0 per 1000 edge px, cat included).
        assert 4 <= s["isolated_dropouts_per_1000_edge_px"] <= 12, path
        # Few of them lie inside one surface (measured 0.05-0.30): the device fills those.
        assert s["isolated_one_surface_share"] <= 0.35, path
        # And they are small: 1-2 px holes dominate (mean size measured 2.8-4.6 px per frame).
        assert 2.0 <= s["isolated_dropout_mean_px"] <= 5.5, path
        # A registration border: 33-39 blind columns on the right, 10-11 rows at the top and bottom (~30,000 px).
        # Off it the same isolated dropouts hold 0.27-3.97 % of the invalid pixels (median 1.18 %).
        bands = blind_border_bands(depth > 0)
        assert 33 <= bands[240, ::-1].argmin() <= 39 and 10 <= bands[:, 320].argmin() <= 11, path
        assert s["isolated_dropout_share"] < s["isolated_dropout_share_off_border"] <= 0.045, path


def test_wide_bands_are_counted_right_of_near_surfaces_on_vertical_edges_only():
    # A board at 0.8 m on the left, a wall at 1.6 m on the right: band f b_r (1/0.8 - 1/1.6) = 9.7 px.
    depth = np.full((40, 120), 1.6)
    depth[:, :60] = 0.8
    assert wide_band_holes(depth) == (0, 36)  # rows 2-37 (two rows up and down must show the edge)
    open_band = depth.copy()
    open_band[:, 60:69] = 0.0
    assert wide_band_holes(open_band) == (36, 36)
    assert realism_statistics(open_band)["wide_band_hole_share"] == 1.0
    # The same hole with the near surface on the right (a projector shadow's side) is not a band.
    assert wide_band_holes(open_band[:, ::-1]) == (0, 0)
    # A horizontal edge (board above the wall) and a small band (board at 1.4 m: 1.4 px) are not counted.
    assert wide_band_holes(open_band.T.copy()) == (0, 0)
    near_far = np.where(depth < 1.0, 1.4, 1.6)
    assert wide_band_holes(near_far) == (0, 0)
    assert realism_statistics(near_far)["wide_band_hole_share"] is None


@pytest.mark.skipif(not (SHARED / "icbin_primesense_unpaired").is_dir(), reason="../shared/data is absent")
def test_real_registered_frames_keep_wide_registration_bands_open():
    """Measured: IC-BIN 694 of 708 (per frame 0.94-1.00), the LineMOD cat 100 of 108."""
    import cv2

    files = sorted((SHARED / "icbin_primesense_unpaired").glob("seq*/depth/*.png"))
    files.append(SHARED / "linemod_bop" / "test" / "000006" / "depth" / "000000.png")
    counts = np.array([wide_band_holes(cv2.imread(str(p), cv2.IMREAD_UNCHANGED).astype(np.float64) / 1000.0)
                       for p in files])  # fmt: skip
    assert counts[:, 1].sum() >= 500
    assert counts[:, 0].sum() >= 0.85 * counts[:, 1].sum()
    assert counts[-1, 0] >= 0.8 * counts[-1, 1]  # the cat


def test_narrow_registration_bands_count_the_rows_left_as_a_one_or_two_pixel_slit():
    # A board at 1.0 m on the left, a wall at 1.6 m: band f b_r (1/1.0 - 1/1.6) = 5.8 px, a narrow one.
    depth = np.full((40, 120), 1.6)
    depth[:, :60] = 1.0
    assert narrow_band_slits(depth) == (0, 36)  # rows 2-37, all closed
    slit = depth.copy()
    slit[5:15, 60] = 0.0  # 10 rows with a 1-px slit, 10 with a 2-px one, 5 with a 3-px hole (not a slit)
    slit[20:30, 60:62] = 0.0
    slit[32:37, 60:63] = 0.0
    assert narrow_band_slits(slit) == (20, 36)
    assert realism_statistics(slit)["narrow_band_slit_share"] == pytest.approx(20 / 36)
    assert wide_band_holes(slit) == (0, 0)  # 5.8 px is not a wide band
    # On the other side of the near surface (a projector shadow's) and for a wide band it is not counted.
    assert narrow_band_slits(slit[:, ::-1]) == (0, 0)
    wide = np.where(depth < 1.2, 0.8, 1.6)  # 9.7 px
    assert narrow_band_slits(wide) == (0, 0) and realism_statistics(wide)["narrow_band_slit_share"] is None


@pytest.mark.skipif(not (SHARED / "tum_rgbd_frame_open3d").is_dir(), reason="../shared/data is absent")
def test_real_registered_frames_leave_some_narrow_bands_as_a_slit():
    """Three devices: IC-BIN 277 of 1212 pooled (0.23; per frame 0-0.30), the LineMOD cat 17 of 116
    (0.15), TUM 15 of 104 (0.14). Closing every band up to 4 px, the forward map's fill gives the default renders
    0.03 (43 of 1268, 16 frames); OpenNI's map without any fill 0.36 (docs/validation.md)."""
    import cv2

    files = sorted((SHARED / "icbin_primesense_unpaired").glob("seq*/depth/*.png"))
    files.append(SHARED / "linemod_bop" / "test" / "000006" / "depth" / "000000.png")
    depths = [cv2.imread(str(p), cv2.IMREAD_UNCHANGED).astype(np.float64) / 1000.0 for p in files]
    depths.append(cv2.imread(str(SHARED / "tum_rgbd_frame_open3d" / "TUM_depth.png"),
                             cv2.IMREAD_UNCHANGED).astype(np.float64) / 5000.0)  # fmt: skip
    counts = np.array([narrow_band_slits(depth) for depth in depths])
    icbin, cat, tum = counts[:-2].sum(0), counts[-2], counts[-1]
    for slits, jumps in (icbin, cat, tum):
        assert jumps >= 100 and 0.10 <= slits / jumps <= 0.30, (slits, jumps)


def test_isolated_dropouts_are_told_vertical_or_horizontal_by_their_bounding_box():
    valid = np.ones((40, 60), bool)
    valid[2:8, 3] = False  # 1 x 6: vertical
    valid[10:12, 10:14] = False  # 4 x 2: horizontal (twice as wide as tall)
    valid[20, 20:29] = False  # 9 x 1: horizontal
    valid[30, 40] = False  # a single pixel: neither
    valid[30:33, 50:53] = False  # 3 x 3: neither
    valid[5:10, 40:43] = False  # 3 x 5: neither (not twice as tall)
    assert isolated_dropout_orientation(valid) == (1, 2)
    assert realism_statistics(np.where(valid, 1.0, 0.0))["isolated_vertical_share"] == pytest.approx(1 / 3)
    # A component of 20 px or more is no isolated dropout; a region keeps the components touching it.
    valid[0:20, 56] = False
    assert isolated_dropout_orientation(valid) == (1, 2)
    left = np.zeros_like(valid)
    left[:, :8] = True
    assert isolated_dropout_orientation(valid, left) == (1, 0)
    assert realism_statistics(np.ones((20, 20)))["isolated_vertical_share"] is None


@pytest.mark.skipif(not all((SHARED / f).is_dir() for f in ("icbin_primesense_unpaired", "linemod_bop",
                                                             "tum_rgbd_frame_open3d")), reason="../shared/data is absent")
def test_real_frames_have_vertical_and_horizontal_isolated_dropouts_about_equally():
    """Measured: IC-BIN 61 vertical of 105 elongated (0.58; per frame 0.31-0.86), the cat 6 of 12, TUM 5 of 9."""
    import cv2

    files = sorted((SHARED / "icbin_primesense_unpaired").glob("seq*/depth/*.png"))
    files += [SHARED / "linemod_bop" / "test" / "000006" / "depth" / "000000.png",
              SHARED / "tum_rgbd_frame_open3d" / "TUM_depth.png"]  # fmt: skip
    counts = np.array([isolated_dropout_orientation(cv2.imread(str(p), cv2.IMREAD_UNCHANGED) > 0) for p in files])
    vertical, horizontal = counts.sum(axis=0)
    assert vertical + horizontal >= 100
    assert 0.45 <= vertical / (vertical + horizontal) <= 0.7


@pytest.mark.skipif(not (SHARED / "tum_rgbd_frame_open3d").is_dir(), reason="../shared/data is absent")
def test_a_real_kinect_frame_of_another_scene_and_depth_convention_reads_like_the_others():
    """The TUM RGB-D frame (Kinect V1, an office at 1.5-9 m, depth in 1/5000 m) was tuned on by nothing: read in
    metres, its statistics fall in the ranges of the IC-BIN frames above (measured: 42 isolated dropouts holding
    0.17 % of the invalid pixels, steps of 2.92 mm at 1 m, 8.5 per 1000 edge px, corners 0.50 against 0.81)."""
    import cv2

    depth = cv2.imread(str(SHARED / "tum_rgbd_frame_open3d" / "TUM_depth.png"), cv2.IMREAD_UNCHANGED) / 5000.0
    s = realism_statistics(depth)
    assert 15 <= s["isolated_dropouts"] <= 60 and s["isolated_dropout_share"] < 0.01
    assert s["corner_valid_share"] < s["valid_share"] - 0.1
    assert s["depth_step_at_1m_mm"] == pytest.approx(2.92, rel=0.03)  # the 1/8-px quantum, read from 1.5-9 m
    assert 4 <= s["isolated_dropouts_per_1000_edge_px"] <= 12
    assert s["isolated_one_surface_share"] <= 0.35  # measured 0.33 (14 of 42)


def test_isolated_dropouts_are_split_by_whether_their_rim_is_one_surface():
    """A 2-px hole in a wall at 1 m (rim disparities equal) is inside one surface; a 2-px hole on the edge of a
    board at 0.8 m before it (rim 43 and 54 px) is at a depth edge, and a hole at 1 m beside a 1.02 m surface (0.8
    px apart) still one surface. Holes outside the region and large holes do not count."""
    depth = np.full((60, 80), 1.0)
    depth[:, 60:] = 0.8
    depth[10, 20:22] = 0.0  # inside the wall
    depth[30, 59:61] = 0.0  # on the board's edge
    depth[40:, 30:40] = 1.02  # a slightly farther patch (0.8 px of disparity)
    depth[45, 29:31] = 0.0  # on that patch's border
    depth[50:58, 0:10] = 0.0  # 80 px: not isolated
    assert isolated_dropouts_by_rim(depth) == (2, 1)
    region = np.zeros(depth.shape, bool)
    region[25:, :] = True
    assert isolated_dropouts_by_rim(depth, region) == (1, 1)
    assert realism_statistics(depth)["isolated_one_surface_share"] == pytest.approx(2 / 3)
    assert realism_statistics(np.full((20, 20), 1.0))["isolated_one_surface_share"] is None


def test_depth_edges_follow_jumps_through_holes_and_count_dropouts_per_edge_length():
    # A wall at 1.0 m, a board at 0.8 m over its right half: one vertical edge, 100 rows long.
    depth = np.full((100, 200), 1.0)
    depth[:, 100:] = 0.8
    assert depth_edges(depth).sum() == 100 and depth_edges(depth)[:, 100].all()
    # A 5-px-wide shadow left of the board: the jump is still one edge pixel per row, inside the hole.
    shadowed = depth.copy()
    shadowed[:, 95:100] = 0.0
    edges = depth_edges(shadowed)
    assert edges.sum() == 100 and (edges.argmax(axis=1) >= 95).all() and (edges.argmax(axis=1) <= 100).all()
    # Five 1-px dropouts along the edge, one on the flat wall: 6 isolated dropouts per 100 edge px.
    ragged = depth.copy()
    ragged[[10, 30, 50, 70, 90], 100] = 0.0
    ragged[50, 20] = 0.0
    assert realism_statistics(ragged)["isolated_dropouts_per_1000_edge_px"] == pytest.approx(60.0)
    # A slanted plane has no edge (1 % depth change per pixel is a surface, not a jump): the statistic is undefined.
    ramp = np.tile(1.0 + 0.01 * np.arange(200), (100, 1))
    assert not depth_edges(ramp).any() and realism_statistics(ramp)["isolated_dropouts_per_1000_edge_px"] is None


@pytest.mark.skipif(not (SHARED / "icbin_primesense_unpaired").is_dir(), reason="../shared/data is absent")
def test_real_frames_outlines_are_ragged_by_seven_tenths_of_a_pixel():
    """The near surfaces' left and right outlines wander from row to row (ddsgen.silhouette_edges.outline_jitter):
    measured 0.63-0.77 px on the nine IC-BIN frames, 0.67 on TUM's, 0.71 on the LineMOD cat's (a ray-cast depth
    image's outlines: 0.31-0.48 px, the pixel grid and the shapes' curvature)."""
    import cv2

    from ddsgen.silhouette_edges import outline_jitter

    frames = [(path, 1e-3) for path in sorted((SHARED / "icbin_primesense_unpaired").glob("seq*/depth/*.png"))]
    frames += [(SHARED / "tum_rgbd_frame_open3d" / "TUM_depth.png", 2e-4),
               (SHARED / "linemod_bop" / "test" / "000006" / "depth" / "000000.png", 1e-3)]  # fmt: skip
    for path, unit in frames:
        outline = outline_jitter(cv2.imread(str(path), cv2.IMREAD_UNCHANGED) * unit)
        assert outline["outline_rows"] >= 300, path
        assert 0.55 <= outline["outline_jitter_px"] <= 0.85, (path, outline)
