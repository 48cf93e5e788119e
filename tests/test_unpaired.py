"""Unpaired fit (issue 17): plain depth folders, scene-independent patch features, the fit."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from torch_threads import torch_threads
from ddsgen.errors import InputError
from ddsgen.fit.unpaired.features import NOISE_BIN_PX, distance_terms, frame_features, pool
from ddsgen.realscan.realfolder import read_depth_folder, round_like

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
FB = 572.41 * 0.075  # f b of kinect_v1 (px m)
H, W = 120, 160


def _plane_depth(z0: float, tilt_u: float, tilt_v: float, sigma_px: float = 0.0, step_px: float = 0.0,
                 seed: int = 0) -> np.ndarray:  # fmt: skip
    """(H, W) depth of a plane (inverse depth affine in u, v) seen through disparity noise
    ``sigma_px`` and a disparity lattice ``step_px`` (0 = none)."""
    v, u = np.mgrid[0:H, 0:W].astype(float)
    disparity = FB / z0 + tilt_u * (u - W / 2) + tilt_v * (v - H / 2)
    disparity = disparity + np.random.default_rng(seed).normal(0, sigma_px, disparity.shape)
    if step_px:
        disparity = np.round(disparity / step_px) * step_px
    return (FB / disparity).astype(np.float32)


# ---- the real folder --------------------------------------------------------------------------
def test_read_depth_folder_reads_png_and_exr_and_prefers_depth_subfolders(tmp_path):
    from ddsgen.io.exr import write_exr

    depth_mm = np.full((H, W), 1234, np.uint16)
    depth_mm[0, 0] = 0
    (tmp_path / "seq" / "depth").mkdir(parents=True)
    (tmp_path / "seq" / "rgb").mkdir()
    cv2.imwrite(str(tmp_path / "seq" / "depth" / "0.png"), depth_mm)
    write_exr(tmp_path / "seq" / "depth" / "1.exr", np.full((H, W), 2.5, np.float32))
    cv2.imwrite(str(tmp_path / "seq" / "rgb" / "0.png"), np.zeros((H, W, 3), np.uint8))  # not depth: skipped
    frames = read_depth_folder(tmp_path, depth_scale=0.0005)
    assert [f.name for f in frames] == ["seq/depth/0.png", "seq/depth/1.exr"]
    assert frames[0].depth[1, 1] == pytest.approx(0.617) and frames[0].depth[0, 0] == 0
    assert frames[0].resolution_m == 0.0005 and frames[1].resolution_m == 0.0
    assert frames[1].depth.mean() == pytest.approx(2.5)
    assert round_like(np.array([1.23449]), 0.001)[0] == pytest.approx(1.234)


def test_a_frame_written_as_png_and_exr_is_read_once(tmp_path):
    """A ddsgen render's depth/ holds every frame twice (16-bit PNG and EXR): one frame each, the EXR, so that no
    frame is counted twice or lands on both sides of a held-out split."""
    from ddsgen.io.exr import write_exr

    for name in ("000000", "000001"):
        cv2.imwrite(str(tmp_path / f"{name}.png"), np.full((H, W), 1234, np.uint16))
        write_exr(tmp_path / f"{name}.exr", np.full((H, W), 1.2345, np.float32))
    cv2.imwrite(str(tmp_path / "000002.png"), np.full((H, W), 1500, np.uint16))  # PNG alone: read
    frames = read_depth_folder(tmp_path)
    assert [f.name for f in frames] == ["000000.exr", "000001.exr", "000002.png"]
    assert frames[0].resolution_m == 0.0 and frames[0].depth.mean() == pytest.approx(1.2345)


def test_read_depth_folder_refuses_bad_input(tmp_path):
    with pytest.raises(InputError, match="no depth images"):
        read_depth_folder(tmp_path)
    cv2.imwrite(str(tmp_path / "a.png"), np.full((H, W), 9, np.uint8))  # 8-bit: not a depth image
    with pytest.raises(InputError, match="a.png: depth PNG must be"):
        read_depth_folder(tmp_path)


def test_cli_unpaired_bad_file_is_one_line_exit_2_and_writes_nothing(tmp_path, capsys):
    from ddsgen.cli import main

    real = tmp_path / "real"
    real.mkdir()
    (real / "0.png").write_bytes(b"not a png")
    out = tmp_path / "fitted.yaml"
    assert main(["fit", "kinect_v1", str(real), "--unpaired", "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert "0.png: cannot read depth PNG" in err and len(err.splitlines()) == 1
    assert not out.exists() and not (tmp_path / "fitted_report").exists()
    # A parameter the unpaired fit does not search (a paired fit's name) is named before anything is read.
    assert main(["fit", "kinect_v1", str(real), "--unpaired", "--out", str(out), "--quiet", "--params", "beta"]) == 2
    err = capsys.readouterr().err.strip()
    assert "--params: 'beta' is not fitted by --unpaired" in err and "row_smoothing_weight" in err
    assert len(err.splitlines()) == 1 and not out.exists()


# ---- features ---------------------------------------------------------------------------------
def test_noise_texture_does_not_depend_on_the_plane_pose_but_on_the_noise():
    """Second differences of f b / z vanish on any plane: two planes of other poses and depths
    (same depth bin) with the same disparity noise have the same feature histogram; twice the
    noise does not."""
    flat = frame_features(_plane_depth(1.0, 0.0, 0.0, 0.1, seed=1), FB)
    tilted = frame_features(_plane_depth(0.9, 0.08, -0.05, 0.1, seed=2), FB)
    noisier = frame_features(_plane_depth(1.0, 0.0, 0.0, 0.2, seed=3), FB)
    assert distance_terms(pool([tilted]), pool([flat]))["noise"] < 0.01
    pose_effect = distance_terms(pool([tilted]), pool([flat]))["noise"]
    assert distance_terms(pool([noisier]), pool([flat]))["noise"] > max(0.05, 10 * pose_effect)
    clean = frame_features(_plane_depth(1.0, 0.1, 0.05), FB)["noise"]
    assert clean[:, :, 0].sum() == clean.sum()  # no noise: every second difference is ~0


def _row_filtered_plane(z0: float, tilt_v: float, sigma_px: float, weight: float, seed: int) -> np.ndarray:
    """(H, W) depth of a plane whose white disparity noise is averaged [w, 1 - 2w, w] along the rows."""
    v, u = np.mgrid[0:H, 0:W].astype(float)
    noise = np.random.default_rng(seed).normal(0, sigma_px, (H, W + 2))
    noise = weight * noise[:, :-2] + (1 - 2 * weight) * noise[:, 1:-1] + weight * noise[:, 2:]
    return FB / (FB / z0 + tilt_v * (v - H / 2) + noise)


def test_grain_is_the_row_filter_of_the_noise_and_not_its_amplitude():
    """The grain feature's correlations of flat-surface residuals with the next pixel in the row and in the column:
    white disparity noise averaged [w, 1 - 2w, w] along the rows correlates 2w(1 - 2w) / (2w^2 + (1 - 2w)^2) along
    them (0 for w = 0, 0.545 for w = 0.2) and 0 down the columns, at any amplitude and on a tilted plane; the
    grain term tells w = 0.2 from w = 0.1, not from twice the noise."""
    from ddsgen.fit.unpaired.features import grain_correlations

    def correlations(weight, sigma_px=0.05, tilt_v=0.0, seed=0):
        features = [frame_features(_row_filtered_plane(1.2, tilt_v, sigma_px, weight, seed + k), FB) for k in range(3)]
        return pool(features), grain_correlations(pool(features)["grain"])

    # The local quadratic fits absorb a little of the noise (6 coefficients over 225 px): residuals correlate
    # slightly less than the noise itself.
    white, (row, column) = correlations(0.0)
    assert abs(row) < 0.06 and abs(column) < 0.06
    grained, (row, column) = correlations(0.2)
    assert row == pytest.approx(0.545, abs=0.04) and abs(column) < 0.06
    louder, loud = correlations(0.2, sigma_px=0.1, tilt_v=0.05, seed=10)
    assert np.allclose(loud, (row, column), atol=0.04)
    assert distance_terms(louder, grained)["grain"] < 0.003
    assert distance_terms(correlations(0.1)[0], grained)["grain"] > 0.02
    assert distance_terms(white, grained)["grain"] > 0.2


def test_quantised_disparity_shows_as_a_lattice_of_second_differences():
    """A disparity lattice of 1/8 px puts every |second difference| on a multiple of 1/8 px
    (every 4th bin of 1/32 px); the matching lattice distance is small, another lattice's large."""
    eighth = frame_features(_plane_depth(1.0, 0.03, 0.0, 0.15, step_px=1 / 8), FB)
    hist = eighth["noise"][0].sum(axis=0)[:-1]
    on_lattice = hist[:: round((1 / 8) / NOISE_BIN_PX)].sum()
    assert on_lattice == hist.sum()
    again = frame_features(_plane_depth(1.0, -0.02, 0.01, 0.15, step_px=1 / 8, seed=4), FB)
    quarter = frame_features(_plane_depth(1.0, -0.02, 0.01, 0.15, step_px=1 / 4, seed=4), FB)
    assert distance_terms(pool([again]), pool([eighth]))["noise"] < 0.02
    assert distance_terms(pool([quarter]), pool([eighth]))["noise"] > 0.2


def test_holes_are_counted_by_size_and_by_the_depth_of_their_rim():
    depth = _plane_depth(1.0, 0.0, 0.0)
    depth[:, W // 2:] = _plane_depth(2.0, 0.0, 0.0)[:, W // 2:]
    rng = np.random.default_rng(0)
    ys = rng.choice(np.arange(10, H - 10, 4), 12, replace=False)
    xs = rng.choice(np.arange(10, W // 2 - 10, 4), 12)
    depth[ys, xs] = 0  # 12 single-pixel dropouts on the 1 m half
    depth[40:50, W // 2 + 20:W // 2 + 30] = 0  # a 100-px hole on the 2 m half: not an isolated dropout
    features = frame_features(depth, FB)
    # (interior / edge, depth bin 0.4-0.8-1.2-1.8-4 m, size class 1, 2-3, 4-7, 8-19, 20-79, 80-319, ...)
    holes = features["holes"]
    assert holes[0, 1, 0] == 12 and holes[0, 3, 5] == 100 and holes.sum() == 112
    step = depth.copy()
    step[60:64, W // 2 - 2:W // 2 + 2] = 0  # a 16-px hole on the 1 m / 2 m edge: the rim spans 21 px of disparity
    assert frame_features(step, FB)["holes"][1].sum() == 16
    assert features["valid"].sum() == (depth > 0).sum()
    assert distance_terms(pool([features]), pool([features]))["total"] == 0.0
    fewer = depth.copy()
    fewer[ys[:6], xs[:6]] = 1.0
    # half the 1-px holes at 1 m
    assert distance_terms(pool([frame_features(fewer, FB)]), pool([features]))["holes"] > 0.02


def test_real_icbin_folder_is_read_and_its_lattice_is_one_eighth_px():
    folder = DATA / "icbin_primesense_unpaired"
    if not folder.is_dir():
        pytest.skip(f"real data absent: {folder}")
    frames = read_depth_folder(folder)
    assert len(frames) == 9 and all("/depth/" in f.name for f in frames)
    pooled = pool([frame_features(f.depth, FB) for f in frames])
    hist = pooled["noise"][0, 1, :17].astype(float)  # 0.8-1.2 m, |second difference| up to 0.5 px
    eighths = hist[::4].sum() + hist[1::4].sum() + hist[3::4].sum()  # within a bin of k/8 (mm rounding)
    assert eighths / hist.sum() > 0.85


# ---- the fit ----------------------------------------------------------------------------------
HIDDEN = {"subpixel_level": 3, "emitted_intensity": 5e6, "softargmax_beta": 30.0, "min_confidence": 0.2}


def _endless_ground(data: dict) -> dict:
    """A scene list's scenes on an endless ground, no table edge: the scenes these tests were measured on (the
    built-in list has stood its objects on a table above a floor). Frames of an endless ground
    against fit scenes with table edges tip the window-model choice: scene content the tests do not study. (The
    table's stray depths in a registered device's bands no longer mislead the window reading: see
    test_a_registered_device_window_is_measured_on_table_scenes_despite_stray_depths.)"""
    for scene in data["scenes"]:
        scene["ground"] = {"size": [5.0, 5.0], "albedo": [0.4, 0.7]}
        scene.pop("floor", None)
        scene.pop("distractors", None)  # (these tests were measured without them)
        # ... with the clutter of a room-range scene list (more objects)
        wall = scene["name"] == "against_wall"
        scene["clutter"] = {"count": [2, 5] if wall else [3, 7], "area": [0.6, 0.4] if wall else [0.6, 0.6],
                            "min_gap": 0.005}
    return data


def _scene_list(classes: tuple[str, ...], distance: list[float], wall: bool):
    from ddsgen.scene.default_scenes import default_scene_list_dict
    from ddsgen.scene.scenelist import scene_list_from_dict

    data = default_scene_list_dict()
    pool_ = [o for o in data["scenes"][0]["objects"] if o["class"] in classes]
    data["scenes"] = [s for s in data["scenes"] if (s["name"] == "against_wall") == wall]
    for scene in data["scenes"]:
        scene["objects"], scene["camera"]["distance"] = pool_, distance
    return scene_list_from_dict(_endless_ground(data))


def _real_like_frames(device, n_frames: int = 8, seed: int = 11) -> list:
    """Frames a hidden ``device`` renders of scene list A (boxes, cans, mugs at 0.7-1.4 m), rounded like a
    millimetre PNG: the "real" folder of the hidden-device tests."""
    from ddsgen.realscan.realfolder import RealDepthFrame
    from ddsgen.fit.unpaired.search import cast_scenes, render_depths

    scenes_a = _scene_list(("box", "can", "mug"), [0.7, 1.4], wall=False)
    depths = render_depths(device, cast_scenes(device, scenes_a, n_frames, seed=seed), seed=seed)
    return [RealDepthFrame(f"{i}.png", round_like(d, 0.001), 0.001) for i, d in enumerate(depths)]


@pytest.fixture(scope="module")
def hidden_device():
    """(stock preset at 160x120, real-like frames of a hidden device on scene list A)."""
    from ddsgen.fit.unpaired.search import camera_for
    from ddsgen.preset import load_preset

    pytest.importorskip("torch")
    with torch_threads(1):
        # The paper's sensor: at the device preset's signal-to-noise ratio eta_c is not identifiable from depth
        # (measured: 4.5e7 fitted for a hidden 5e6), which is a limit of unpaired fitting, not of this test's subject.
        stock = camera_for(load_preset("kinect_v1_paper"), W, H)
        yield stock, _real_like_frames(stock.replace(**HIDDEN))


def _fit(stock, real, scene_list):
    from ddsgen.fit.unpaired.search import cast_scenes, fit_unpaired

    return fit_unpaired(stock, real, cast_scenes(stock, scene_list, 6, seed=3), seed=0, bootstrap=40, keys=tuple(HIDDEN),
                        progress=False)  # fmt: skip


def _assert_near_hidden(result):
    after = result.after
    assert after["subpixel_level"] == HIDDEN["subpixel_level"]  # the disparity lattice: exact
    # SNR and confidence threshold trade off in the hole statistics (a lower SNR with a lower threshold makes the same
    # holes), so eta is weakly identified: where its minimum lands moves with details of the fit scenes (trimesh 5's
    # capsule tessellation alone moved it from 3.2e6 to 1.4e6 for a hidden 5e6). What the fit must get right is its
    # claim: the hidden eta inside the reported 5-95 % interval, and that interval marked as open-ended when it is.
    eta = result.bootstrap["emitted_intensity"]["joint"]
    assert eta["p05"] <= HIDDEN["emitted_intensity"]
    assert HIDDEN["emitted_intensity"] <= eta["p95"] or eta["lower_bound"]
    assert abs(after["min_confidence"] - HIDDEN["min_confidence"]) < 0.08


def test_unpaired_fit_recovers_a_hidden_device_from_other_scenes(hidden_device):
    """Targets rendered on scene list A, fit on the built-in default list: the stock preset
    (n_sub 2, eta 1.5e6, confidence 0.15) moves to the hidden device's lattice and SNR."""
    from ddsgen.scene.scenelist import load_scene_list

    stock, real = hidden_device
    result = _fit(stock, real, load_scene_list(None))
    assert result.distance_after["total"] < 0.5 * result.distance_before["total"]
    _assert_near_hidden(result)
    assert all(result.uncertainty[k] >= 0 for k in HIDDEN) and result.uncertainty["emitted_intensity"] > 0


@pytest.mark.slow
def test_unpaired_fit_does_not_follow_scene_content(hidden_device):
    """Same hidden device, a different fit scene list (a wall, round objects): same values
    within the tolerances above."""
    stock, real = hidden_device
    result = _fit(stock, real, _scene_list(("ball", "ring", "cone", "bracket"), [0.8, 1.6], wall=True))
    _assert_near_hidden(result)


def test_cli_unpaired_writes_preset_and_report(hidden_device, tmp_path, capsys):
    """The command end to end (the fit itself is tested above: only the lattice is fitted here, ``--params
    subpixel_level``, to keep it fast)."""
    from ddsgen.cli import main
    from ddsgen.io.png import write_depth_png
    from ddsgen.preset import load_preset, save_preset

    stock, real = hidden_device
    for frame in real[:4]:  # as a device registered to its RGB camera writes them: a band without depth at the right
        write_depth_png(tmp_path / "real" / "depth" / frame.name, np.where(np.arange(W) < W - 10, frame.depth, 0.0))
    save_preset(stock, tmp_path / "stock.yaml")
    out = tmp_path / "out" / "fitted.yaml"
    assert main(["fit", str(tmp_path / "stock.yaml"), str(tmp_path / "real"), "--unpaired", "--out", str(out),
                 "--quiet", "--report", str(tmp_path / "report"), "--params", "subpixel_level"]) == 0  # fmt: skip
    fitted = load_preset(out)
    assert list(json.loads((tmp_path / "report" / "unpaired_report.json").read_text())["after"]) == ["subpixel_level"]
    assert fitted.subpixel_level == HIDDEN["subpixel_level"] and fitted.width_px == W
    # The output window is measured from the folder: the 10-column band, nothing at the top or bottom.
    assert (fitted.output_right_border_px, fitted.output_top_border_px, fitted.output_bottom_border_px) == (10, 0, 0)
    assert stock.output_right_border_px == 0
    printed = capsys.readouterr().out
    assert ("+-" in printed or "known within a factor" in printed) and "output window" in printed
    assert ">=" not in printed and "not identifiable from unpaired depth" in printed  # spreads in plain words
    for name in ("distributions.png", "patches.png", "frames.png", "profiles.png", "unpaired_report.json"):
        assert (tmp_path / "report" / name).stat().st_size > 1000


def test_unpaired_fit_recovers_the_device_fall_off_and_hole_filling(set_torch_threads):
    """The device keys: a hidden kinect_v1 with a steeper beam fall-off (cos^12, stock cos^4) and
    no hole filling (stock fills holes below 8 px), targets on scene list A, fit on the built-in
    list. The fall-off is found from validity by image radius alone, the hole filling from the
    hole-size histogram (1-px holes exist only without it). Unregistered: a registered device's dense
    splat closes 1-px holes itself, and then 0, 2 and 4 px of filling give the same frames (measured:
    a flat profile, 0.03303 at all three). At a low IR signal (eta 5e5), where the beam's fall-off
    costs dots in the corners, and on fit scenes of one type (a tabletop with other objects and
    distances than list A): on the built-in list the two halves of the fit scenes are a tabletop and
    a wall, whose validity by radius differs more (5.4e-4, scaled) than the fall-off's whole range
    moves it at this size (160x120, 6 fit frames), and the fit rightly keeps the stock's value."""
    from ddsgen.fit.unpaired.search import camera_for, cast_scenes, fit_unpaired
    from ddsgen.preset import load_preset

    pytest.importorskip("torch")
    set_torch_threads(1)
    # Without the narrow fill (cleanup_fill_width_px), which closes 1-px holes along rows and columns whatever the
    # hole fill does, as the dense splat does (below).
    stock = camera_for(load_preset("kinect_v1"), W, H).replace(registration_ir_offset_m=0.0, registration_shift_px=0.0,
                                                               emitted_intensity=5.0e5,
                                                               cleanup_fill_width_px=0)  # fmt: skip
    hidden = {"projector_falloff_exponent": 12.0, "cleanup_hole_px": 0}
    real = _real_like_frames(stock.replace(**hidden), n_frames=24)
    tabletop = _scene_list(("ball", "ring", "cone", "bracket", "box"), [0.8, 1.5], wall=False)
    result = fit_unpaired(stock, real, cast_scenes(stock, tabletop, 6, seed=3), seed=0, bootstrap=40,
                          keys=tuple(hidden), progress=False)  # fmt: skip
    assert result.after["cleanup_hole_px"] == 0
    falloff, sigma = result.after["projector_falloff_exponent"], result.uncertainty["projector_falloff_exponent"]
    # The value moves from the stock's 4 to within 3 of the hidden 12, and the reported spread covers the rest. (At
    # 160x120 over 8 real frames the radius term varies by 2e-4 over the whole range, so a resample of the frames
    # moves its minimum by several units: measured sigma 5.5, from the bootstrap over the whole range.) 24 real
    # frames, not 8: with 8, two of five (real, fit) seed pairs recovered it (11/3, 11/4; the stock's 4.0 in two,
    # 8.5 in one), and a redraw of the speckle (seeded by a hash of the cast geometry) turned this test's
    # pair from 10.6 to 4.0. With 24: four of five (10.8-13.2, sigma 1.6-2.9; 13/5 stays at 4.0).
    assert abs(falloff - 12.0) < 3.0 and abs(falloff - 12.0) <= 2 * sigma
    assert not result.bootstrap["projector_falloff_exponent"]["scene_content"]["kept_input_value"]
    assert result.distance_after["radius"] < 0.5 * result.distance_before["radius"]


def test_unpaired_fit_recovers_the_device_smoothing_along_its_rows(set_torch_threads):
    """A hidden kinect_v1 that averages its disparity [0.2, 0.6, 0.2] along the rows (row_smoothing_weight), targets
    on scene list A, fit from the same device without it (w = 0) on the built-in list: the search on the grain (the
    flat noise's correlation with the next pixel in the row and in the column) finds w. Measured with four (real,
    fit) seed pairs: 0.148-0.218, each within its reported spread (0.014-0.058)."""
    from ddsgen.fit.unpaired.search import camera_for, cast_scenes, fit_unpaired
    from ddsgen.preset import load_preset
    from ddsgen.scene.scenelist import load_scene_list

    pytest.importorskip("torch")
    set_torch_threads(1)
    stock = camera_for(load_preset("kinect_v1"), W, H).replace(row_smoothing_weight=0.0)
    real = _real_like_frames(stock.replace(row_smoothing_weight=0.2))
    result = fit_unpaired(stock, real, cast_scenes(stock, load_scene_list(None), 6, seed=3), seed=0, bootstrap=40,
                          keys=("row_smoothing_weight",), progress=False)  # fmt: skip
    weight = result.after["row_smoothing_weight"]
    assert abs(weight - 0.2) < 0.06 and abs(weight - 0.2) <= 2 * result.uncertainty["row_smoothing_weight"]
    assert not result.bootstrap["row_smoothing_weight"]["scene_content"]["kept_input_value"]
    assert result.distance_after["grain"] < 0.3 * result.distance_before["grain"]


def test_joint_uncertainty_sees_a_trade_off_that_the_profiles_do_not():
    """A distance flat along a diagonal (two keys that trade off, as SNR against fall-off): each 1-D profile
    is sharp, the joint spread is wide along the valley; for independent keys both agree."""
    from ddsgen.fit.unpaired.joint import joint_uncertainty, quadratic_minimum
    from ddsgen.fit.unpaired.parameters import UnpairedParameter

    params = [UnpairedParameter("a", 0.0, 10.0, log=False, grid=11), UnpairedParameter("b", 0.0, 10.0, log=False,
                                                                                          grid=11)]  # fmt: skip
    fitted = {"a": 5.0, "b": 5.0}
    rng = np.random.default_rng(0)
    resamples = [rng.normal(0.0, 0.02, 2) for _ in range(200)]  # each resample tilts the surface a little

    def valley(v, tilt):  # sharp across the diagonal, nearly flat along it
        u, w = v["a"] - 5.0, v["b"] - 5.0
        return 4.0 * (u - w) ** 2 + 0.05 * (u + w) ** 2 + tilt[0] * u + tilt[1] * w

    def bowl(v, tilt):
        u, w = v["a"] - 5.0, v["b"] - 5.0
        return 2.0 * u**2 + 2.0 * w**2 + tilt[0] * u + tilt[1] * w

    joint_valley = joint_uncertainty(params, fitted, valley, resamples)
    joint_bowl = joint_uncertainty(params, fitted, bowl, resamples)
    # The 1-D profile's spread: vertex of 4 (1.05) u^2 + t u -> std of t / 8.1 = 0.0025.
    conditional = np.std([t[0] / (2 * 4.05) for t in resamples])
    assert joint_valley["a"]["std"] > 10 * conditional and joint_valley["b"]["std"] > 10 * conditional
    assert joint_bowl["a"]["std"] == pytest.approx(np.std([t[0] / 4.0 for t in resamples]), rel=0.05)
    assert not joint_bowl["a"]["lower_bound"]
    # A saddle has no minimum along its falling direction: that key is clipped to the limit, never a confident
    # value; the other, curved upward, keeps its vertex.
    x = np.array([[0, 0], [1, 0], [-1, 0], [0, 1], [0, -1], [1, 1], [1, -1]], float)
    x_min, clipped = quadratic_minimum(x, (x[:, 0] - 0.5) ** 2 - x[:, 1] ** 2 + 0.1 * x[:, 1], limit=4.0)
    assert clipped.tolist() == [False, True] and x_min == pytest.approx([0.5, -4.0])  # slope +0.1: downhill is -x1


def test_a_key_the_frames_do_not_constrain_does_not_unsettle_an_independent_one():
    """Two keys, one flat (as the SNR at a high SNR: the distance hardly moves with it) and one in a sharp bowl of
    its own (as the row smoothing on the grain): only the flat key's spread is a lower bound; the bowl's is its own
    (the minimum of 2 u^2 + t u: std of t / 4)."""
    from ddsgen.fit.unpaired.joint import joint_uncertainty
    from ddsgen.fit.unpaired.parameters import UnpairedParameter

    params = [UnpairedParameter("flat", 0.0, 10.0, log=False, grid=11), UnpairedParameter("sharp", 0.0, 10.0,
                                                                                          log=False, grid=11)]  # fmt: skip
    rng = np.random.default_rng(1)
    resamples = [rng.normal(0.0, 0.02, 2) for _ in range(200)]

    def distance(v, tilt):
        u, w = v["sharp"] - 5.0, v["flat"] - 5.0
        return 2.0 * u**2 + tilt[0] * u + tilt[1] * w - 1e-4 * w**2

    joint = joint_uncertainty(params, {"flat": 5.0, "sharp": 5.0}, distance, resamples)
    assert joint["flat"]["lower_bound"] and joint["flat"]["clipped"] == 1.0
    assert not joint["sharp"]["lower_bound"] and joint["sharp"]["clipped"] == 0.0
    assert joint["sharp"]["std"] == pytest.approx(np.std([t[0] / 4.0 for t in resamples]), rel=0.05)


# ---- the device's window, registered or not -------------------------------------------------------
@pytest.fixture(scope="module")
def registered_device():
    """kinect_v1 (registered to its RGB camera) at 320x240 with an IR-frame window, 6 frames on scene list A."""
    from ddsgen.realscan.realfolder import RealDepthFrame
    from ddsgen.fit.unpaired.search import camera_for, cast_scenes, render_depths
    from ddsgen.preset import load_preset

    pytest.importorskip("torch")
    with torch_threads(1):
        stock = camera_for(load_preset("kinect_v1"), 320, 240)
        window = {"output_left_border_px": 12, "output_right_border_px": 9, "output_top_border_px": 6,
                  "output_bottom_border_px": 3}  # fmt: skip
        device = stock.replace(**window)
        scenes = _scene_list(("box", "can", "mug"), [0.6, 1.3], wall=False)
        depths = render_depths(device, cast_scenes(device, scenes, 6, seed=21), seed=21)
        yield stock, window, [RealDepthFrame(f"{i}.png", round_like(d, 0.001), 0.001) for i, d in enumerate(depths)]


def test_a_registered_device_window_is_measured_in_its_ir_frame(registered_device):
    """The registered output's left band narrows with depth (L + s - f b_r / Z): measured in the output image it
    is neither the IR frame's band nor one width; mapped back into the IR frame every side is the device's."""
    from ddsgen.sensor.output_window import OutputWindow, measure_device_window, measure_output_window

    stock, window, real = registered_device
    depths = [f.depth for f in real]
    assert stock.registration_shift_px == pytest.approx(17.4 / 2)  # the shift scales with the image
    assert measure_device_window(depths, stock) == OutputWindow(12, 9, 6, 3)
    in_output = measure_output_window([d > 0 for d in depths])
    assert in_output.left != 12  # what the registration does to the band
    first = [np.flatnonzero(row)[0] for d in depths for row in d[20:-20] > 0 if row.any()]
    assert np.ptp(np.percentile(first, [10, 90])) >= 1  # and it is not one width


def test_a_registered_device_window_is_measured_on_table_scenes_despite_stray_depths(set_torch_threads):
    """On a table above a floor, a nearer surface's depth on a farther pixel maps a few pixels into the IR
    frame's bands (2-3.5 % of a band column against 88 % inside): they must not end the band (they read the
    right band 9 as 5 under the 1 % rule alone). Rendered with the registration mapped back by the ray-cast
    geometry, which shows the matcher's carry one band further on and so makes such pixels (the forward map, the
    device's and kinect_v1's, makes few: 0.09 %); real frames may have them for other reasons."""
    from ddsgen.fit.unpaired.search import camera_for, cast_scenes, render_depths
    from ddsgen.preset import load_preset
    from ddsgen.scene.default_scenes import default_scene_list_dict
    from ddsgen.scene.scenelist import scene_list_from_dict
    from ddsgen.sensor.output_window import OutputWindow, measure_device_window
    from ddsgen.sensor.registration import ir_frame_validity

    pytest.importorskip("torch")
    set_torch_threads(1)
    stock = camera_for(load_preset("kinect_v1").replace(registration_forward_gap_px=0), 320, 240)
    device = stock.replace(output_left_border_px=12, output_right_border_px=9, output_top_border_px=6,
                           output_bottom_border_px=3)  # fmt: skip
    data = default_scene_list_dict()  # the built-in table scenes, not _endless_ground's
    data["scenes"] = [s for s in data["scenes"] if s["name"] != "against_wall"]
    for scene in data["scenes"]:
        scene["objects"] = [o for o in scene["objects"] if o["class"] in ("box", "can", "mug")]
        scene["camera"]["distance"] = [0.6, 1.3]
    depths = [round_like(d, 0.001) for d in
              render_depths(device, cast_scenes(device, scene_list_from_dict(data), 6, seed=21), seed=21)]  # fmt: skip
    band = np.mean([ir_frame_validity(d, stock)[:, -9:] for d in depths])
    assert 0.002 < band < 0.04  # the stray pixels this test is about are there
    assert measure_device_window(depths, stock) == OutputWindow(12, 9, 6, 3)


def test_the_fit_reads_registered_frames_with_the_registration_and_plain_frames_without(registered_device):
    """Model choice by measurement: frames of the registered device are closer to the registered reading;
    the same device without registration (the window as its own output's) is closer to the plain one."""
    from ddsgen.fit.unpaired.device_window import UNREGISTERED, choose_window_model
    from ddsgen.realscan.realfolder import RealDepthFrame
    from ddsgen.fit.unpaired.search import cast_scenes, render_depths
    from ddsgen.scene.default_scenes import default_scene_list_dict
    from ddsgen.scene.scenelist import scene_list_from_dict

    stock, window, real = registered_device
    scenes = scene_list_from_dict(_endless_ground(default_scene_list_dict()))
    chosen, candidates = choose_window_model(stock, real, scenes, 4, seed=0)
    assert [m.name for m in candidates] == ["unregistered", "registered"]
    assert chosen.name == "registered" and chosen.window.as_keys() == window
    plain = stock.replace(**UNREGISTERED, **window)
    scenes_a = _scene_list(("box", "can", "mug"), [0.6, 1.3], wall=False)
    depths = render_depths(plain, cast_scenes(plain, scenes_a, 6, seed=21), seed=21)
    plain_real = [RealDepthFrame(f"{i}.png", round_like(d, 0.001), 0.001) for i, d in enumerate(depths)]
    chosen, candidates = choose_window_model(stock, plain_real, scenes, 4, seed=0)
    assert chosen.name == "unregistered" and chosen.window.as_keys() == window
    assert candidates[0].distance < candidates[1].distance


def test_a_reading_the_held_out_frames_do_not_confirm_is_not_written_nor_fitted_under(registered_device, tmp_path,
                                                                                       monkeypatch, capsys):  # fmt: skip
    """The fit frames of a registered device made to choose the unregistered reading (as they did on a hidden device):
    the keys are fitted under both readings, the held-out sequence does not confirm the unregistered one beyond its
    spread, so the preset keeps the device's registration and the values fitted under it, and the terminal says so."""
    from ddsgen.cli import main
    from ddsgen.fit.unpaired import run
    from ddsgen.io.png import write_depth_png
    from ddsgen.preset import load_preset, save_preset

    stock, window, real = registered_device
    for i, frame in enumerate(real):
        write_depth_png(tmp_path / "real" / f"seq{i % 2 + 1}" / frame.name, frame.depth)
    save_preset(stock, tmp_path / "stock.yaml")
    real_choice, real_fit = run.choose_window_model, run.fit_unpaired
    fitted_under = []

    def wrong_reading(*args, **kwargs):
        chosen, candidates = real_choice(*args, **kwargs)
        return next(m for m in candidates if m.name == "unregistered"), candidates

    def recording_fit(camera, *args, **kwargs):
        fitted_under.append(camera.registration_ir_offset_m)
        return real_fit(camera, *args, **kwargs)

    monkeypatch.setattr(run, "choose_window_model", wrong_reading)
    monkeypatch.setattr(run, "fit_unpaired", recording_fit)
    out = tmp_path / "fitted.yaml"
    assert main(["fit", str(tmp_path / "stock.yaml"), str(tmp_path / "real"), "--unpaired", "--out", str(out),
                 "--quiet", "--report", str(tmp_path / "report"), "--params", "subpixel_level"]) == 0  # fmt: skip
    assert fitted_under == [0.0, stock.registration_ir_offset_m]  # the fit frames' reading, then the input's
    report = json.loads((tmp_path / "report" / "unpaired_report.json").read_text())
    judged = report["output_window"]["judged"]
    assert judged["fit_choice"] == "unregistered" and judged["chosen"] == "registered"
    assert judged["groups"]["total"] != "closer"
    written = load_preset(str(out))
    assert written.registration_ir_offset_m == stock.registration_ir_offset_m
    assert written.registration_shift_px == pytest.approx(stock.registration_shift_px)
    assert "did not confirm it beyond the spread" in capsys.readouterr().out


def test_the_reading_can_be_given_instead_of_measured(registered_device):
    """--registration registered / unregistered: one candidate, no measurement; registered needs a registered
    preset (one clear line)."""
    from ddsgen.fit.unpaired.device_window import UNREGISTERED, choose_window_model
    from ddsgen.scene.scenelist import load_scene_list

    stock, window, real = registered_device
    scenes = load_scene_list(None)
    chosen, candidates = choose_window_model(stock, real, scenes, 2, seed=0, reading="unregistered")
    assert [m.name for m in candidates] == ["unregistered"] and chosen.distance is None
    assert chosen.registration_keys == UNREGISTERED
    chosen, candidates = choose_window_model(stock, real, scenes, 2, seed=0, reading="registered")
    assert [m.name for m in candidates] == ["registered"] and chosen.window.as_keys() == window
    with pytest.raises(InputError, match="--registration registered: the preset .* writes unregistered depth"):
        choose_window_model(stock.replace(**UNREGISTERED), real, scenes, 2, seed=0, reading="registered")


def test_cli_registration_unregistered_fits_unregistered_but_reports_the_stock_as_it_is(registered_device, tmp_path):
    """--registration unregistered with the registered kinect_v1: the fitted preset has the registration off and the
    frames' own window; the report's stock column is still the stock preset, registered, on its own ray casts (only
    the lattice is fitted, to keep it fast)."""
    from ddsgen.cli import main
    from ddsgen.depth_statistics import realism_statistics
    from ddsgen.fit.unpaired.run import DEFAULT_SIM_FRAMES
    from ddsgen.fit.unpaired.search import cast_scenes, render_depths
    from ddsgen.io.png import write_depth_png
    from ddsgen.preset import load_preset, save_preset
    from ddsgen.scene.scenelist import load_scene_list
    from ddsgen.sensor.output_window import measure_output_window

    stock, window, real = registered_device
    for frame in real:
        write_depth_png(tmp_path / "real" / frame.name, frame.depth)
    save_preset(stock, tmp_path / "stock.yaml")
    out = tmp_path / "fitted.yaml"
    assert main(["fit", str(tmp_path / "stock.yaml"), str(tmp_path / "real"), "--unpaired", "--registration",
                 "unregistered", "--out", str(out), "--quiet", "--report", str(tmp_path / "report"),
                 "--params", "subpixel_level"]) == 0  # fmt: skip
    fitted = load_preset(out)
    report = json.loads((tmp_path / "report" / "unpaired_report.json").read_text())
    assert report["written"] == "fitted", report["held_out"]
    assert fitted.registration_ir_offset_m == 0 and fitted.registration_shift_px == 0
    # The window is measured on the frames the fit sees (the held-out ones judge it).
    seen = set(report["held_out"]["fit_frames"])
    own = measure_output_window([f.depth > 0 for f in real if f.name in seen]).as_keys()
    assert {key: getattr(fitted, key) for key in own} == own
    assert report["output_window"]["model"] == "unregistered"
    # The preset says what changed, from what, and on what held-out evidence, group by group.
    header = [line for line in out.read_text().splitlines() if line.startswith("#")]
    reading = next(line for line in header if "depth registration: unregistered" in line)
    window_values = tuple(own.values())
    assert reading.endswith(f"{tuple(getattr(stock, key) for key in own)} -> {window_values}")
    groups = next(line for line in header if line.startswith("# by feature group:"))
    assert all(f"{group} " in groups for group in ("noise", "holes", "radius", "grain")) and "+-" in groups
    depths = render_depths(stock, cast_scenes(stock, load_scene_list(None), DEFAULT_SIM_FRAMES, 0), 1)
    isolated = np.median([realism_statistics(round_like(d, 0.001))["isolated_dropouts"] for d in depths])
    assert report["realism_statistics"]["stock"]["isolated_dropouts"] == isolated
    # The noise where flat by depth, pooled over the frames, real and rendered, in the same bins.
    real_rows = report["realism_statistics"]["real"]["flat_roughness_by_depth"]
    stock_rows = report["realism_statistics"]["stock"]["flat_roughness_by_depth"]
    assert [row["depth_m"] for row in real_rows] == [row["depth_m"] for row in stock_rows]
    assert sum(row["pixels"] for row in real_rows) > 0 and sum(row["pixels"] for row in stock_rows) > 0


def test_unpaired_fit_reports_a_fall_off_the_frames_cannot_see_as_undetermined(set_torch_threads):
    """At a high IR signal (eta 5e7) the beam's fall-off darkens the corners without losing a dot:
    validity by radius does not move (hidden-device draw 1: 9 % of a tiny term over 0-16). The fit
    must not claim a value there: the hidden cos^8 lies within its reported 2 sigma, which spans the
    range, and the key is flagged as weakly identified (a bootstrap of +-1/2 step around the minimum
    reported 16 +- 2.5 for a hidden 7)."""
    from ddsgen.fit.unpaired.search import camera_for, cast_scenes, fit_unpaired
    from ddsgen.preset import load_preset
    from ddsgen.scene.scenelist import load_scene_list

    pytest.importorskip("torch")
    set_torch_threads(1)
    stock = camera_for(load_preset("kinect_v1"), W, H).replace(registration_ir_offset_m=0.0, registration_shift_px=0.0,
                                                               emitted_intensity=5.0e7)  # fmt: skip
    real = _real_like_frames(stock.replace(projector_falloff_exponent=8.0))
    result = fit_unpaired(stock, real, cast_scenes(stock, load_scene_list(None), 6, seed=3), seed=0, bootstrap=40,
                          keys=("projector_falloff_exponent",), progress=False)  # fmt: skip
    falloff, sigma = result.after["projector_falloff_exponent"], result.uncertainty["projector_falloff_exponent"]
    spread = result.bootstrap["projector_falloff_exponent"]
    assert abs(falloff - 8.0) <= 2 * sigma and sigma >= 4.0
    assert spread["lower_bound"]
    # ... and the input's cos^4 is kept: nothing in the frames asks for another value
    assert spread["scene_content"]["kept_input_value"] and falloff == 4.0
