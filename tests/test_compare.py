"""ddsgen compare: the gap metric on rendered "real" data (identical vs perturbed sensor), the CLI,
and the BOP reader + ground-truth pose on the real LineMOD frame.

Small and fast: a Kinect-like preset scaled to 160x120 px (focal length / 4), 3 frames.
"""

from __future__ import annotations

import json
import textwrap
from pathlib import Path

import numpy as np
import pytest
import torch

from torch_threads import torch_threads
from ddsgen.cli import main
from ddsgen.realscan.gap import gap
from ddsgen.realscan.simulate import prepare_frames, simulate
from ddsgen.io.scanfolder import read_scan_folder
from ddsgen.preset import load_preset
from ddsgen.sensor.depth_sensor import DepthSensor

LINEMOD = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "linemod_bop"

SMALL_PRESET = textwrap.dedent(
    """\
    name: kinect_v1_small
    width_px: 160
    height_px: 120
    focal_px: 143.1025          # 572.41 / 4
    baseline_m: 0.075
    z_min_m: 0.4
    z_max_m: 4.0
    block_size_px: 9
    emitted_intensity: 1.5e6
    shadow_bias_m: 0.005
    softargmax_beta: 15.0
    subpixel_level: 2
    pattern: kinect_like_640.png
    band_rows: 120
    """
)
SCENES = textwrap.dedent(
    """\
    scenes:
      - name: table
        frames: 2
        objects:
          - {shape: box, size: [0.2, 0.15, 0.12], albedo: 0.6}
          - {shape: cylinder, radius: 0.06, height: 0.2, albedo: 0.6}
          - {shape: sphere, radius: 0.08, albedo: 0.6}
        clutter: {count: [2, 3], area: [0.5, 0.4]}
        ground: {size: [6, 6], albedo: 0.6}
        camera: {distance: [0.9, 1.6], elevation_deg: [35, 60], azimuth_deg: [-180, 180]}
    """
)


def write_presets(folder: Path) -> dict[str, Path]:
    """The small stock preset and a perturbed one (eta_c x3, noise x2, beta +40 %, baseline +3 mm)."""
    folder.mkdir(parents=True, exist_ok=True)
    stock = folder / "small.yaml"
    stock.write_text(SMALL_PRESET)
    perturbed = folder / "perturbed.yaml"
    perturbed.write_text(
        SMALL_PRESET.replace("emitted_intensity: 1.5e6", "emitted_intensity: 4.5e6")
        .replace("softargmax_beta: 15.0", "softargmax_beta: 21.0")
        .replace("baseline_m: 0.075", "baseline_m: 0.078")
        + "read_noise_std_counts: 20.8\n"
    )
    scenes = folder / "scenes.yaml"
    scenes.write_text(SCENES)
    return {"stock": stock, "perturbed": perturbed, "scenes": scenes}


def render(preset: Path, scenes: Path, out: Path, n: int, seed: int = 3) -> Path:
    from ddsgen.runner import render_dataset

    render_dataset(str(preset), str(scenes), n, str(out), workers=1, seed=seed, progress=False)
    return out


@pytest.fixture(scope="module")
def small(tmp_path_factory):
    with torch_threads(2):
        root = tmp_path_factory.mktemp("compare")
        paths = write_presets(root)
        paths["real"] = render(paths["stock"], paths["scenes"], root / "real", 3)
        yield paths


def test_identical_settings_at_noise_floor_perturbed_clearly_larger(small):
    stock = load_preset(small["stock"])
    frames = prepare_frames(stock, read_scan_folder(small["real"]))
    same = gap(DepthSensor(stock), frames)
    other = gap(DepthSensor(load_preset(small["perturbed"])), frames, noise_floor=False)
    print(f"identical: gap {same.gap:.2f} mm, noise floor {same.noise_floor:.2f} mm; perturbed: gap {other.gap:.2f} mm")
    # Identical settings: the simulation is another noise draw of the same sensor, so its gap is
    # the noise floor (the floor is itself one draw: allow 30 %).
    assert same.gap <= 1.3 * same.noise_floor + 0.5
    # eta_c x3 / noise x2 / beta +40 % / baseline +3 mm: clearly beyond the floor. The floor is what
    # no model can remove, so "clearly larger" is judged on the excess over it: the perturbed model's
    # excess is at least 3x that of the identical one (measured 3.1 vs 0.55 mm at 160 px).
    assert other.gap - same.noise_floor >= 3.0 * max(same.gap - same.noise_floor, 0.5)
    # Parts are there and consistent.
    parts = same.parts
    assert abs(parts["depth_mm"] + parts["gradient_mm"] + parts["validity_mm"] - same.gap) < 1e-2
    assert abs(sum(parts["confusion"].values()) - 1.0) < 1e-3
    assert parts["bins"]["depth_m"] and parts["bins"]["incidence_deg"] and parts["bins"]["radius"]
    # Modelled geometry is where the real depth is: rendered poses are exact, so the only
    # difference is the sensor's (1/4 px) disparity quantisation, ~+-20 mm at 1.3 m here.
    assert all(f.pose_error_mm < 25.0 for f in frames)


def test_noise_floor_is_what_a_perfect_model_scores_against_a_unit_it_does_not_know(small):
    """The floor is measured against another unit of the sensor (its own laser speckle and dot positions, fixed to
    the scene as on the device): a scan taken by a third unit, with the model's exact parameters, scores the floor,
    while a scan that shares the model's own speckle and dots scores far below it. A floor measured against a twin
    that shared them (as before) told the user that a perfect model had a large gap left to explain."""
    import dataclasses

    from ddsgen.realscan.simulate import sensor_unit
    from effects_geometry import small_preset

    device = small_preset(160, 120)  # kinect_v1 scaled down: speckle fixed to the scene, dots off the lattice
    assert device.speckle_fixed_to_scene and device.pattern_dot_jitter_px > 0
    frames = prepare_frames(device, read_scan_folder(small["real"]))
    sensor = DepthSensor(device)

    def taken_by(unit: int, seed: int):
        taken = []
        for frame in frames:
            with torch.no_grad(), sensor_unit(sensor, unit):
                scan = simulate(sensor, frame, seed)
            taken.append(dataclasses.replace(frame, real_depth=scan.depth, real_valid=scan.valid))
        return taken

    unknown_unit = gap(sensor, taken_by(3, 7))
    own_unit = gap(sensor, taken_by(0, 7), noise_floor=False)
    print(f"floor {unknown_unit.noise_floor:.2f} mm; gap to an unknown unit {unknown_unit.gap:.2f} mm, "
          f"to its own unit {own_unit.gap:.2f} mm")
    assert 0.7 * unknown_unit.noise_floor <= unknown_unit.gap <= 1.3 * unknown_unit.noise_floor
    assert own_unit.gap < 0.7 * unknown_unit.noise_floor


def test_floor_of_few_frames_averages_several_units(small):
    """One unit's floor on one frame scatters by tens of percent (the real cat's object region: 0.40-1.50 mm over
    eight units), so a comparison of few frames averages at least four unit draws: one frame gets four twins, each
    another unit with its own speckle and dots; four frames or more get one each."""
    from ddsgen.realscan.simulate import FLOOR_DRAWS, twin_draws
    from effects_geometry import small_preset

    assert FLOOR_DRAWS == 4
    assert [twin_draws(n) for n in (0, 1, 2, 3, 4, 9)] == [4, 4, 2, 2, 1, 1]
    device = small_preset(160, 120)  # speckle fixed to the scene, dots off the lattice: units differ
    frames = prepare_frames(device, read_scan_folder(small["real"]))
    sensor = DepthSensor(device)
    one = gap(sensor, frames[:1])
    draws = one.noise_floor_draws
    print("floor against each unit (mm):", [round(v, 2) for v in draws])
    assert len(draws) == 4 and len({round(v, 6) for v in draws}) == 4  # four different units, not one repeated
    assert one.noise_floor == pytest.approx(np.mean(draws))
    assert one.to_dict()["noise_floor_draws"] == [round(v, 4) for v in draws]
    # The first draw is the one-twin floor of before (unit 1), so a comparison of 4+ frames is unchanged.
    assert gap(sensor, frames[:1] * 4).noise_floor_draws == pytest.approx([draws[0]], rel=1e-6)


def test_compare_cli_writes_report_and_rejects_bad_input(small, tmp_path, capsys):
    report = tmp_path / "report"
    code = main(["compare", str(small["stock"]), str(small["real"]), "--report", str(report), "--quiet"])
    assert code == 0
    data = json.loads((report / "comparison.json").read_text())
    assert data["gap"] > 0 and data["noise_floor"] > 0 and len(data["frames"]) == 3
    assert {"depth_mm", "gradient_mm", "validity_mm", "bins", "confusion"} <= set(data["parts"])
    assert (report / "comparison_bins.png").stat().st_size > 1000
    assert (report / "comparison_residuals.png").stat().st_size > 1000
    assert "gap (all region)" in capsys.readouterr().out

    empty = tmp_path / "empty"
    empty.mkdir()
    assert main(["compare", str(small["stock"]), str(empty), "--report", str(tmp_path / "r2")]) == 2
    assert not (tmp_path / "r2").exists()
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("ddsgen: error:")


@pytest.fixture(scope="module")
def linemod():
    if not (LINEMOD / "test" / "000006" / "scene_gt.json").is_file():
        pytest.skip(f"real LineMOD data not found at {LINEMOD.resolve()}")
    return LINEMOD


def test_linemod_cat_lands_on_measured_depth(linemod):
    (scan,) = read_scan_folder(linemod)  # dataset root: BOP layout auto-detected
    assert scan.layout == "bop" and scan.objects[0].mesh_path.endswith("obj_000006.ply")
    preset = load_preset("kinect_v1")
    (frame,) = prepare_frames(preset, [scan], crop=True)
    obj = frame.geometry.hit & (frame.instance > 0) & frame.real_valid
    error_mm = (frame.real_depth[obj] - frame.geometry.clean_depth[obj]).abs() * 1000.0
    print(f"cat: {int(obj.sum())} px, median |real - model| = {float(error_mm.median()):.2f} mm")
    assert int(obj.sum()) > 1500  # the cat covers ~2,400 px at 1.05 m
    assert float(error_mm.median()) <= 5.0
    assert frame.pose_error_mm <= 5.0
    # Control: the same cat 20 mm further away does not land on the measured depth.
    import dataclasses

    moved = dataclasses.replace(scan.objects[0], cam_T_obj=scan.objects[0].cam_T_obj.copy())
    moved.cam_T_obj[2, 3] += 0.020
    (wrong,) = prepare_frames(preset, [dataclasses.replace(scan, objects=[moved], depth=scan.depth)], crop=True,
                              support_plane=False)  # fmt: skip
    assert wrong.pose_error_mm > 12.0
    # The RANSAC support plane is the table under the cat (roughly facing the camera, ~0.75-1.3 m).
    assert frame.plane is not None and frame.plane.inliers > 0.3 * frame.plane.candidates
    assert float(np.abs(frame.plane.normal[2])) > 0.5


# ---------------------------------------------------------------- what compare shows (issue 12)


def test_compare_save_sim_pictures_and_realism_statistics(small, tmp_path, capsys):
    import cv2

    from ddsgen.realscan.pictures import BAR_PX, GAP_PX, TOP_PX
    from ddsgen.io.exr import read_exr

    report, saved = tmp_path / "report", tmp_path / "sim"
    args = ["compare", str(small["stock"]), str(small["real"]), "--report", str(report), "--quiet"]
    assert main([*args, "--save-sim", str(saved)]) == 0
    out = capsys.readouterr().out
    assert "isolated dropouts / frame" in out and "depth step at 1 m (mm)" in out

    # The saved folder is a scan folder: the real frames' order, cameras and objects, readable again.
    real_frames, sim_frames = read_scan_folder(small["real"]), read_scan_folder(saved)
    assert [f.record["source"] for f in sim_frames] == [f.name for f in real_frames]
    assert not list(tmp_path.glob(".sim.*"))  # no temporary folder left
    for real, sim in zip(real_frames, sim_frames):
        assert sim.intrinsics == real.intrinsics
        assert [o.class_name for o in sim.objects] == [o.class_name for o in real.objects]
        np.testing.assert_allclose(sim.objects[0].cam_T_obj, real.objects[0].cam_T_obj, atol=1e-9)
        depth_exr = read_exr(saved / sim.record["depth_exr"])
        np.testing.assert_allclose(sim.depth, depth_exr, atol=0.0006)  # the PNG is the EXR in whole mm
        # the modelled objects sit where the real render put them: the clean depths agree on their pixels
        mask_real = cv2.imread(str(small["real"] / real.record["mask"]), cv2.IMREAD_UNCHANGED)
        mask_sim = cv2.imread(str(saved / sim.record["mask"]), cv2.IMREAD_UNCHANGED)
        both = (mask_real > 0) & (mask_real == mask_sim)
        assert both.sum() > 0.9 * (mask_real > 0).sum()
        clean_real, clean_sim = read_exr(small["real"] / real.record["clean"]), read_exr(saved / sim.record["clean"])
        assert np.abs(clean_real - clean_sim)[both].max() < 1e-4
    assert len(prepare_frames(load_preset(small["stock"]), sim_frames)) == 3  # compare/fit can read it again

    # Realism statistics: same sensor on both sides, so the same 1/4-px depth step, z^2 / (4 f b) at 1 m.
    data = json.loads((report / "comparison.json").read_text())
    realism = data["realism"]
    assert "modelled region only" in realism["scopes"]["sim.modelled"]
    assert len(realism["frames"]) == 3
    step_mm = 1000.0 / (4 * 143.1025 * 0.075)
    for scope in ("real.whole_frame", "real.region", "sim.region"):
        assert realism["aggregate"][scope]["depth_step_at_1m_mm"]["mean"] == pytest.approx(step_mm, rel=0.1), scope
    real_valid = realism["aggregate"]["real.region"]["valid_share"]["mean"]
    sim_valid = realism["aggregate"]["sim.region"]["valid_share"]["mean"]
    assert abs(real_valid - sim_valid) < 0.1
    # the real whole frame also counts what the compare region leaves out (far walls, the image's corners)
    assert realism["frames"][0]["real"]["whole_frame"]["pixels"] == 160 * 120
    assert realism["frames"][0]["real"]["region"]["pixels"] == data["frames"][0]["pixels"]
    # The noise where flat by depth, pooled over the three frames, real and simulated in the compare region.
    by_depth = realism["flat_roughness_by_depth"]
    assert [row["depth_m"] for row in by_depth["real"]] == [row["depth_m"] for row in by_depth["sim"]]
    assert sum(row["pixels"] for row in by_depth["real"]) > 0 and "flat roughness by depth" in out

    # Full-resolution side-by-side: one image pixel per picture pixel, invalid real depth black.
    picture = cv2.imread(str(report / "frames" / "000000.png"))[..., ::-1] / 255.0
    assert picture.shape[:2] == (120 + TOP_PX + BAR_PX, 3 * 160 + 4 * GAP_PX)
    real_panel = picture[TOP_PX : TOP_PX + 120, GAP_PX : GAP_PX + 160]
    real_depth = real_frames[0].depth
    inner = np.zeros_like(real_depth, bool)
    inner[2:-2, 2:-2] = True
    assert real_panel[inner & (real_depth == 0)].max() < 0.05  # black
    assert real_panel[inner & (real_depth > 0)].max(axis=-1).min() > 0.1  # coloured
    index = (report / "index.html").read_text()
    assert "frames/000000.png" in index and "comparison_bins.png" in index and "frames/000002.png" in index
    # The compare region's rule is stated in comparison.json and in the report.
    assert "support plane's real footprint" in data["region_rule"] and "unmodelled" in data["region_rule"]
    assert "support plane&#x27;s real footprint" in index

    # Saved frame i is the simulation of real frame i at the compare's seed (exactly); an existing
    # non-empty target is refused before any work.
    stock = load_preset(small["stock"])
    with torch.no_grad():
        again = simulate(DepthSensor(stock).eval(), prepare_frames(stock, real_frames)[1], 0)
    np.testing.assert_array_equal(read_exr(saved / "depth" / "000001.exr"), again.depth.numpy())
    assert main([*args[:-3], "--report", str(tmp_path / "r3"), "--save-sim", str(saved)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--save-sim: folder is not empty" in err[0]
    assert not (tmp_path / "r3").exists()


def test_full_frame_pastes_a_crop_back():
    from types import SimpleNamespace

    from ddsgen.realscan.realism import full_frame
    from ddsgen.preset import Intrinsics

    frame = SimpleNamespace(crop=(3, 2, 4, 5), full_intrinsics=Intrinsics(10, 8, 5.0, 5.0, 5.0, 4.0))
    crop = np.arange(20, dtype=np.float32).reshape(5, 4) + 1
    full = full_frame(crop, frame)
    assert full.shape == (8, 10) and full.sum() == crop.sum()
    np.testing.assert_array_equal(full[2:7, 3:7], crop)
    whole = np.ones((8, 10))
    assert full_frame(whole, frame) is whole


def test_compare_real_cat_cropped_statistics_on_whole_frames(linemod, tmp_path, capsys):
    """The real LineMOD cat with --crop: the real statistics are the whole 640x480 image's (those of
    shared/data/README.md), the sim's depth step is its preset's disparity quantum, the saved frame is full size."""
    from ddsgen.depth_statistics import realism_statistics
    from ddsgen.io.exr import read_exr

    report, saved = tmp_path / "report", tmp_path / "sim"
    assert main(["compare", "kinect_v1", str(linemod), "--crop", "--report", str(report), "--save-sim", str(saved),
                 "--quiet"]) == 0  # fmt: skip
    realism = json.loads((report / "comparison.json").read_text())["realism"]
    (frame,) = realism["frames"]
    (scan,) = read_scan_folder(linemod)
    whole = realism_statistics(scan.depth, resolution_m=0.001)
    assert frame["real"]["whole_frame"]["pixels"] == 640 * 480
    assert frame["real"]["whole_frame"]["isolated_dropouts"] == whole["isolated_dropouts"]
    assert 21 <= whole["isolated_dropouts"] <= 46  # README: 21-46 on the ten real frames
    assert frame["real"]["whole_frame"]["depth_step_at_1m_mm"] == pytest.approx(2.92, abs=0.02)  # 1/8 px
    assert frame["real"]["whole_frame"]["corner_valid_share"] < frame["real"]["whole_frame"]["valid_share"]
    preset = load_preset("kinect_v1")
    quantum_mm = 1000.0 / (2**preset.subpixel_level * preset.focal_px * preset.baseline_m)
    assert frame["sim"]["region"]["depth_step_at_1m_mm"] == pytest.approx(quantum_mm, rel=0.1)
    assert frame["sim"]["modelled"]["pixels"] < frame["real"]["whole_frame"]["pixels"] / 10  # the crop only
    # The cat's outline: the real sensor carries it about a pixel past the ray-cast silhouette and draws it ragged by
    # under a pixel; the simulation within half a pixel of both (docs/validation.md).
    real_edges, sim_edges = frame["edges"]["real"], frame["edges"]["sim"]
    assert real_edges["edge_rows"] > 40 and sim_edges["edge_rows"] > 40
    assert -0.5 < real_edges["edge_fattening_px"] < 2.0 and 0.3 < real_edges["edge_jitter_px"] < 1.5
    assert abs(sim_edges["edge_fattening_px"] - real_edges["edge_fattening_px"]) < 0.5
    assert abs(sim_edges["edge_jitter_px"] - real_edges["edge_jitter_px"]) < 0.5
    # Roughness in disparity where the surfaces face the camera (ddsgen.surface_roughness): real 0.061 px in the region,
    # 0.060 over the whole frame, whose slanted surfaces are 1.85x rougher; the simulation within 0.015 px.
    real_flat, sim_flat = frame["real"]["region"]["flat_roughness_px"], frame["sim"]["region"]["flat_roughness_px"]
    assert 0.045 < real_flat < 0.075 and abs(sim_flat - real_flat) < 0.015
    assert 1.4 < frame["real"]["whole_frame"]["slant_roughness_ratio"] < 2.3
    # The same per depth bin (here 1-1.25 m only: real 0.061 px on 495 pixels, simulated 0.057 on 440).
    by_depth = realism["flat_roughness_by_depth"]
    measured = [(real, sim) for real, sim in zip(by_depth["real"], by_depth["sim"])
                if real["roughness_px"] is not None and sim["roughness_px"] is not None]  # fmt: skip
    assert measured and all(abs(sim["roughness_px"] - real["roughness_px"]) < 0.015 for real, sim in measured)
    (sim,) = read_scan_folder(saved)
    depth = read_exr(saved / sim.record["depth_exr"])
    x0, y0, w, h = sim.record["crop"]
    assert depth.shape == (480, 640) and (depth > 0).sum() == (depth[y0 : y0 + h, x0 : x0 + w] > 0).sum() > 1000
    assert sim.objects[0].visible_fraction > 0.9 and sim.record["source"] == "000006/000000"


def test_crop_box_never_exceeds_the_image():
    """An object box plus margin taller than the image is clipped to it (the window's size is its arrays' size)."""
    from ddsgen.realscan.simulate import _crop_box

    instance = np.zeros((120, 160), np.uint16)
    instance[2:118, 40:60] = 1
    x0, y0, w, h = _crop_box(instance, margin=32, min_size=64)
    assert (y0, h) == (0, 120) and 0 <= x0 and x0 + w <= 160 and w == 20 + 64
    instance[:] = 1
    assert _crop_box(instance, margin=32, min_size=64) == (0, 0, 160, 120)


# ---------------------------------------------------------------- the compare region (issue 12)

FB = 572.41 * 0.075  # f b of the Kinect V1 (px m)


def test_unmodelled_shadow_has_the_projector_geometry():
    """An unmodelled box 0.6 m away in front of a modelled wall at 1 m shadows f b (1/0.6 - 1/1) = 28.6 px to its
    left (the projector is at +b); a surface behind the wall shadows nothing; widening moves only the far edge."""
    from ddsgen.realscan.region import disparity, unmodelled_shadow

    clean = np.full((3, 200), 1.0)
    real = clean.copy()
    real[:, 120:140] = 0.6  # unmodelled occluder
    real[:, 170:180] = 2.0  # unmodelled surface behind the wall (a hole in it): casts no shadow on it
    occluder = np.abs(disparity(real, FB) - disparity(clean, FB)) > 2.0
    shadow = unmodelled_shadow(disparity(real, FB), disparity(clean, FB), occluder, widen_px=0)
    first = int(np.ceil(120 - FB * (1 / 0.6 - 1.0)))  # 92: projector column u - d_wall reaches the box's 120 - d_box
    assert first == 92
    assert shadow[:, first:120].all() and not shadow[:, :first].any() and not shadow[:, 140:].any()
    widened = unmodelled_shadow(disparity(real, FB), disparity(clean, FB), occluder, widen_px=4)
    assert widened[:, first - 4 : 120].all() and not widened[:, : first - 4].any() and not widened[:, 140:].any()


def test_the_support_plane_is_the_one_the_objects_rest_on_not_the_largest():
    """Two planes in view, a table under the object and a larger floor 0.7 m below it: RANSAC alone takes the
    floor (more inliers); with the object's points it takes the table, whatever the seed."""
    from ddsgen.realscan.support_plane import fit_support_plane
    from ddsgen.preset import Intrinsics

    intr = Intrinsics(640, 480, 572.4, 572.4, 319.5, 239.5)  # the Kinect's: 0.5 px of disparity is ~2 % of z
    v, u = np.mgrid[0:480, 0:640].astype(np.float64)
    rays = np.stack([(u - intr.cx) / intr.fx, (v - intr.cy) / intr.fy, np.ones_like(u)], axis=-1)
    normal = np.array([0.0, -0.6, -0.8])  # planes seen from above at 37 deg, n.P + d = 0
    def depth_on(d):
        return -d / (rays @ normal)
    table, floor = depth_on(1.0), depth_on(1.7)
    depth = np.where(v < 180, table, floor).astype(np.float32)  # the floor fills more of the image
    obj = np.zeros((480, 640), bool)
    obj[80:120, 280:360] = True
    # the object's visible points: standing on the table (0-8 cm above it)
    heights = np.linspace(0.0, 0.08, obj.sum())
    points = (rays[obj] * table[obj, None]) + heights[:, None] * normal  # n.P + d = height: the camera side
    for seed in range(3):
        rng = np.random.default_rng(seed)
        largest = fit_support_plane(depth, intr, obj, 572.4 * 0.075, rng)
        assert abs(largest.offset - 1.7) < 0.02, largest
        rested = fit_support_plane(depth, intr, obj, 572.4 * 0.075, np.random.default_rng(seed), resting=points)
        assert abs(rested.offset - 1.0) < 0.02, rested


def test_the_cat_frames_support_plane_does_not_depend_on_the_seed(linemod):
    """The real cat frame holds the table (6209 inliers) and the floor 0.73 m below it (6150): before the objects
    chose the plane, seeds 1 and 2 modelled the floor and the real frame's isolated dropouts in the compare region
    went 12 -> 3."""
    from ddsgen.realscan.inputs import load_inputs

    offsets = []
    for seed in (0, 1, 2):
        _, _, _, frames = load_inputs("kinect_v1", str(linemod), seed=seed, progress=False)
        offsets.append(frames[0].plane.offset)
    assert max(offsets) - min(offsets) < 0.01 and abs(offsets[0] - 0.748) < 0.01, offsets


def test_plane_footprint_is_the_real_table_closed_and_filled():
    """The table's real extent: its on-plane pixels with their holes (a dark patch) filled, gaps narrower than a
    block closed, the posed objects with their modelled shadows (here at the table's edge) in; beyond the table's
    edge, where the real frame sees the floor, out; an invalid far part with no sign of another surface, in."""
    from ddsgen.realscan.region import plane_footprint
    from ddsgen.sensor.output_window import OutputWindow

    on_plane = np.zeros((100, 120), bool)
    on_plane[10:60, :] = True  # the table spans the view's width
    on_plane[20:30, 20:30] = False  # a dark patch on the table (no real depth)
    on_plane[30:55, 60:63] = False  # a 3 px crack, narrower than the block
    objects = np.zeros_like(on_plane)
    objects[40:70, 80:90] = True  # an object standing at the table's front edge
    on_plane[40:60, 70:80] = False  # its shadow on the table, to its left
    modelled = objects.copy()
    modelled[40:70, 70:80] = True  # the ray cast's shadow
    floor = np.zeros_like(on_plane)
    floor[80:95, 20:100] = True  # the floor seen beyond the front edge (rows 60-100 have no table depth)
    foot = plane_footprint(on_plane, modelled, floor, block_px=9)
    assert foot[10:60].all() and foot[objects].all()
    assert not foot[75:].any() and not foot[65:, :60].any()
    assert foot[:5].all()  # the far part (rows 0-10): invalid, no evidence that the table ends: a hole in it
    # A band of blind columns on the left (no real depth there) is taken to continue the table.
    blind = on_plane.copy()
    blind[:, :8] = False
    blind[:, 8:17] &= np.random.default_rng(0).random((100, 9)) < 0.3  # the real matcher's ramp beyond it
    foot = plane_footprint(blind, modelled, floor, block_px=9, window=OutputWindow(left=8))
    assert foot[10:60, :17].all() and not foot[75:, :17].any()
    # A registered device's right band and top rows: the table continues there too; the floor stays off it.
    blind = on_plane.copy()
    blind[:, -12:] = False
    blind[:6, :] = False
    foot = plane_footprint(blind, modelled, floor, block_px=9, window=OutputWindow(right=12, top=6))
    assert foot[:60, -21:].all() and not foot[75:, -21:].any()
    assert not plane_footprint(blind, modelled, floor, block_px=9)[10:60, -12:].any()


def test_comparison_region_keeps_what_the_scene_explains():
    """Real-valid plausible pixels always count; real-invalid pixels count on posed objects and the table's real
    extent (its holes, the object's shadow), not beyond the table's edge nor in an unmodelled object's shadow."""
    from ddsgen.realscan.region import comparison_region

    clean = np.full((100, 200), 1.0)  # the fitted support plane (fronto-parallel at 1 m) covers the image
    objects = np.zeros(clean.shape, bool)
    objects[30:50, 100:120] = True
    clean[objects] = 0.9
    real = clean.copy()
    real[70:, :] = 0.0  # beyond the table's front edge: nothing, or the floor, too dark to return depth ...
    real[85:95, 40:160] = 1.6  # ... except a lit strip of it
    real[30:50, 95:100] = 0.0  # the posed object's own shadow (modelled)
    real[10:20, 150:160] = 0.6  # an unmodelled object on the table ...
    real[10:20, 120:150] = 0.0  # ... and its shadow (28.6 px + half a block)
    real[55:60, 30:40] = 0.0  # a dark patch on the table
    real[40:45, 110:115] = 0.0  # a dark spot on the posed object
    shadow = np.zeros_like(objects)
    shadow[30:50, 93:100] = True  # its modelled shadow
    region = comparison_region(real, clean, clean > 0, objects, shadow, FB, 2.0, 9, has_plane=True)
    assert region[real > 0].sum() == (real > 0).sum() - 100 - 1200  # every valid pixel but the unmodelled ones
    assert region[30:50, 95:100].all() and region[55:60, 30:40].all() and region[40:45, 110:115].all()
    assert not region[75:].any() and not region[10:20, 125:150].any()
    # Without a support plane every hit real-invalid pixel counts except the unmodelled shadow.
    region = comparison_region(real, clean, clean > 0, objects, shadow, FB, 2.0, 9, has_plane=False)
    assert region[75:85].all() and not region[10:20, 125:150].any()
    # Without the floor's lit strip nothing says where the table ends: its invalid far part is a hole in it.
    real[85:95, 40:160] = 0.0
    region = comparison_region(real, clean, clean > 0, objects, shadow, FB, 2.0, 9, has_plane=True)
    assert region[70:].all()


def test_linemod_cat_region_leaves_the_floor_beyond_the_table_out(linemod):
    """On the real cat frame the fitted table plane continues past the real table's front edge (lower left: floor,
    the table's legs, a dark sleeve, no real depth): those pixels are not compared; the table and cat are."""
    (scan,) = read_scan_folder(linemod)
    (frame,) = prepare_frames(load_preset("kinect_v1"), [scan])
    region, real_valid = frame.region.numpy(), frame.real_valid.numpy()
    lower_left = region[400:, 20:160]
    assert lower_left.mean() < 0.05  # ~4 % of it is the far floor's specks the closing joins
    assert region[220:270, 220:540].mean() > 0.95  # the table in front of the objects
    assert (region & (frame.instance.numpy() > 0)).sum() > 1500  # the cat
    assert real_valid[region].mean() > 0.93  # was 0.87 when the plane's invisible part counted


def test_compare_draws_the_speckle_fixed_to_the_scene_as_render_does(small):
    """With speckle_fixed_to_scene, compare's simulation of a frame carries the speckle render would draw for that
    geometry: two noise seeds differ only by the detector noise (a few counts), not by the speckle (tens)."""
    fixed = load_preset(small["stock"]).replace(speckle_fixed_to_scene=True, speckle_grain_px=1.0)
    fresh = fixed.replace(speckle_fixed_to_scene=False)
    frame = prepare_frames(fixed, read_scan_folder(small["real"]))[0]
    lit = (frame.geometry.hit & ~frame.geometry.shadow).numpy()
    spread = {}
    for name, preset in (("fixed", fixed), ("fresh", fresh)):
        sensor = DepthSensor(preset).eval()
        with torch.no_grad():
            a, b = simulate(sensor, frame, 0).ir.numpy(), simulate(sensor, frame, 1).ir.numpy()
        spread[name] = float(np.std((a - b)[lit]))
    print(spread)
    assert spread["fixed"] < 0.5 * spread["fresh"]
    assert spread["fixed"] == pytest.approx(np.sqrt(2) * 10.4, rel=0.3)  # two draws of the read noise, 10.4 counts
    sensor = DepthSensor(fixed).eval()
    with torch.no_grad():
        render_noise = sensor.draw_noise([7, 0, 1], frame.geometry)  # any frame seed: the scene's speckle
        compare_noise = sensor.draw_noise(frame.noise_seed(0), frame.geometry)
    assert torch.equal(render_noise.speckle_unit, compare_noise.speckle_unit)


def test_a_real_folders_other_output_window_is_pointed_out():
    """Frames of a device registered to its RGB camera (a right band and top rows without depth in every
    frame) against a preset without them: one line naming the keys; none when the preset declares them or
    when only one frame is given (its empty border may be the scene's)."""
    from types import SimpleNamespace

    from ddsgen.realscan.inputs import output_window_hint
    from ddsgen.preset import load_preset

    preset = load_preset("kinect_v1_paper").replace(width_px=80, height_px=60, focal_px=71.5, focal_y_px=71.5,
                                                    cx_px=39.5, cy_px=29.5)  # fmt: skip
    rng = np.random.default_rng(0)
    scans = []
    for _ in range(3):
        depth = np.where(rng.random((60, 80)) < 0.9, 1.2, 0.0).astype(np.float32)
        depth[:, -9:] = 0.0
        depth[:4] = 0.0
        scans.append(SimpleNamespace(depth=depth))
    hint = output_window_hint(preset, scans)
    assert "output_right_border_px: 9" in hint and "output_top_border_px: 4" in hint and "left" not in hint
    assert output_window_hint(preset.replace(output_right_border_px=9, output_top_border_px=4), scans) is None
    assert output_window_hint(preset, scans[:1]) is None


def test_compare_leads_with_what_its_gap_is_made_of():
    """The first line says the gap is mostly scene the model lacks only when it is: local patches carry most of the
    excess, or the annotated objects alone are much closer than the whole region."""
    from ddsgen.realscan.gap import lead_lines
    from ddsgen.realscan.gap_report import GapReport

    def report(carried, objects_excess, region="all"):
        objects = {"gap": objects_excess + 0.4, "noise_floor": 0.4, "excess": objects_excess, "frames": 1}
        return GapReport(gap=9.6, noise_floor=0.2, frames=[], parts={}, region=region, local={"carried": carried},
                         objects=objects)  # fmt: skip

    mostly_scene = lead_lines(report(carried=0.68, objects_excess=0.29))
    assert len(mostly_scene) == 1 and "68 % of the excess" in mostly_scene[0] and "0.69 mm" in mostly_scene[0]
    assert "much closer" in lead_lines(report(carried=0.1, objects_excess=1.0))[0]  # 1.0 of 9.4 mm excess
    assert lead_lines(report(carried=0.1, objects_excess=9.0)) == []  # the objects are as far off: the sensor
    assert lead_lines(report(carried=0.9, objects_excess=0.2, region="objects")) == []


def test_real_cat_compare_gives_the_objects_only_figure_first(linemod, tmp_path, capsys):
    """On the real cat most of the whole region's gap is scene the model lacks: compare says so before the figures,
    with the gap of the cat's own pixels, which is what --region objects measures."""
    whole, objects = tmp_path / "whole", tmp_path / "objects"
    assert main(["compare", "kinect_v1", str(linemod), "--report", str(whole), "--quiet"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[1].startswith("most of this gap is not the sensor")
    assert main(["compare", "kinect_v1", str(linemod), "--report", str(objects), "--quiet", "--region", "objects"]) == 0
    only = json.loads((whole / "comparison.json").read_text())["objects_only"]
    measured = json.loads((objects / "comparison.json").read_text())
    assert (only["gap"], only["noise_floor"]) == (measured["gap"], measured["noise_floor"])
    assert f"{only['gap']:.2f} mm" in lines[1]


def test_a_rendered_folder_is_simulated_whole_and_its_preset_sits_at_the_noise_floor(tmp_path):
    """A ddsgen render holds what its manifest does not list (distractors, the table, the floor, walls); run.json
    names the scene list and seed that make them again, so compare simulates every surface of every frame: the
    preset that rendered the folder is at the noise floor on each of 16 default-scene frames, and the frames get no
    support plane fitted by RANSAC (the rendered one is modelled)."""
    out = tmp_path / "render"
    assert main(["render", "kinect_v1", "-n", "16", "--out", str(out), "--workers", "2", "--seed", "3", "--quiet"]) == 0
    scans = read_scan_folder(out)
    assert all(s.rendered is not None and not s.rendered.missing for s in scans)
    frames = prepare_frames(load_preset("kinect_v1"), scans)
    assert all(f.plane is None for f in frames)
    report = gap(DepthSensor(load_preset("kinect_v1")), frames, seed=1)
    excess = [f["gap"] - f["noise_floor"] for f in report.frames]
    print("excess per frame (mm):", [round(e, 2) for e in excess])
    assert max(excess) <= 0.1


def test_a_render_whose_scene_list_changed_is_not_simulated_whole(tmp_path):
    """The scene list named in run.json is used only while it is the one the folder was rendered from."""
    from ddsgen.io.scanfolder import read_scan_folder as read

    scenes = tmp_path / "scenes.yaml"
    scenes.write_text(SCENES)
    out = tmp_path / "render"
    preset = write_presets(tmp_path)["stock"]
    assert main(["render", str(preset), "--scenes", str(scenes), "-n", "2", "--out", str(out), "--quiet"]) == 0
    assert all(s.rendered is not None and not s.rendered.missing for s in read(out))
    scenes.write_text(SCENES.replace("albedo: 0.6", "albedo: 0.5"))
    assert all("has changed" in s.rendered.missing for s in read(out))
    scenes.unlink()
    assert all("is gone" in s.rendered.missing for s in read(out))
