"""refine writes nothing worse: held-out acceptance, the one-sided data term, identifiability, dataset names,
and the validation scenes of tests/refine_validation.py (a fast subset; bench/bench_refine.py runs them all)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from ddsgen.cli import main
from ddsgen.preset import Intrinsics, load_preset
from ddsgen.raycast import cast
from ddsgen.scene import shapes
from ddsgen.scene.sampling import FrameScene, PlacedObject
from ddsgen.scene_gradients import RefinableScene, RefineSettings
from ddsgen.scene_gradients.acceptance import (accept_parts, block_cells, block_difference_noise, heldout_blocks,
                                               pixel_cost)
from ddsgen.scene_gradients.poses import axis_angle_to_matrix
from ddsgen.scene_gradients.refine import _View
from ddsgen.sensor.depth_sensor import DepthSensor
from ddsgen.sensor.geometry import SensorGeometry
from refine_validation import LINEMOD, PACKED_REPORT_SEEDS, REPORT_SEEDS, run, summary


def pose(rotvec=(0.0, 0.0, 0.0), t=(0.0, 0.0, 0.0)) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = axis_angle_to_matrix(torch.tensor(rotvec, dtype=torch.float64)).numpy()
    T[:3, 3] = t
    return T


def window() -> Intrinsics:
    full = load_preset("kinect_v1").intrinsics
    return Intrinsics(120, 100, full.fx, full.fy, full.cx - 260, full.cy - 190)


def one_object_scene(mesh, T) -> FrameScene:
    plane = PlacedObject(0, "plane", "plane:2x2", shapes.plane_mesh(2.0, 2.0), pose((-0.9, 0, 0), (0, 0.1, 0.78)), 0.6)
    return FrameScene([PlacedObject(1, "thing", "shape:thing", mesh, T, 0.6)], [plane], np.eye(4), 0, 0)


def test_the_held_out_blocks_alternate_cover_half_and_follow_the_seed():
    a = heldout_blocks(60, 80, 6, seed=0, view=0)
    assert 0.4 < float(a.float().mean()) < 0.6
    # within a block all alike; the next block along a row or column is the other colour
    ys, xs = np.nonzero(a.numpy())
    y, x = int(ys[len(ys) // 2]), int(xs[len(xs) // 2])
    assert bool(a[y, x]) and any(not bool(a[y, x + d]) for d in range(1, 13) if x + d < 80)
    assert torch.equal(a, heldout_blocks(60, 80, 6, seed=0, view=0))
    assert not all(torch.equal(a, heldout_blocks(60, 80, 6, seed=s, view=0)) for s in range(1, 6))


def test_an_occluder_costs_the_same_wherever_the_object_is_and_absence_costs_more():
    """A real surface 5 cm in front of the model costs the fixed charge whatever the simulated depth; a model
    surface in front of a farther real one (the object is not there) costs the cap, more than the charge."""
    real = torch.tensor([[0.75, 0.75, 0.90, 0.80]])
    clean = torch.tensor([[0.80, 0.80, 0.80, 0.80]])
    depth_a, depth_b = clean + 0.002, clean - 0.004
    valid = torch.ones_like(real, dtype=torch.bool)
    cost_a, defined = pixel_cost(depth_a, valid, clean, real, 0.015, 0.025, 4.0)
    cost_b, _ = pixel_cost(depth_b, valid, clean, real, 0.015, 0.025, 4.0)
    assert bool(defined.all())
    assert float(cost_a[0, 0]) == float(cost_b[0, 0]) == pytest.approx(0.015)  # occluded: a charge, pose-blind
    assert float(cost_a[0, 2]) == pytest.approx(0.025)  # absence: the cap, more than the charge
    assert float(cost_a[0, 3]) == pytest.approx(0.002, abs=1e-6) and float(cost_b[0, 3]) == pytest.approx(0.004, abs=1e-6)


def _box_views(correction_sign: float):
    """A box 0.7 m away seen at a corner; its start is 2 deg / 5 mm off the truth; the correction set is the exact
    way back (sign +1) or the same step the wrong way (-1). Returns (sensor, view, truth pose)."""
    intr = window()
    box = shapes.make_shape("box", {"size": (0.07, 0.055, 0.045)})
    truth_T = pose((-0.6, 0.7, 0.0), (0.0, 0.0, 0.7))
    sensor = DepthSensor(load_preset("kinect_v1_paper"), intrinsics=intr)
    with torch.no_grad():
        real = sensor(SensorGeometry.from_hits(cast(one_object_scene(box, truth_T), intr, 0.075, 0.005)), seed=3).depth
    start_T = truth_T.copy()
    start_T[:3, 3] += (0.003, -0.002, 0.0035)
    scene = RefinableScene(one_object_scene(box, start_T), intr, 0.075, 0.005)
    s = RefineSettings(edge_weight=0.0)
    view = _View(0, scene, real, s)
    with torch.no_grad():
        scene.poses.translation[0] = torch.tensor(truth_T[:3, 3] - start_T[:3, 3]) * correction_sign
    return sensor, view, truth_T


@pytest.mark.parametrize("sign, kept", [(1.0, True), (-1.0, False)])
def test_a_refined_pose_is_kept_only_if_held_out_pixels_find_it_better(sign, kept):
    sensor, view, truth_T = _box_views(sign)
    decisions = accept_parts(sensor, [view], 0.015, 0.025)
    decision = decisions[0][0]
    assert decision.kept is kept and decision.pixels > 50
    moved = view.scene.poses.matrices()[0]
    if kept:
        assert np.abs(moved[:3, 3] - truth_T[:3, 3]).max() < 1e-9
        assert decision.heldout_refined_mm < decision.heldout_start_mm
    else:  # the start pose, exactly
        assert float(view.scene.poses.translation.detach()[0].abs().max()) == 0.0
        assert decision.heldout_refined_mm >= decision.heldout_start_mm


def test_a_sphere_leaves_its_turns_undetermined_and_they_stay_at_the_start():
    """Depth and outline of a sphere do not change when it turns about its centre: the curvature says so, the
    three rotations are reported undetermined (the translations determined), and a refinement leaves them at 0."""
    from ddsgen.scene_gradients import refine_poses

    intr = window()
    ball = shapes.make_shape("sphere", {"radius": (0.04,)})
    truth_T = pose((0.0, 0.0, 0.0), (0.0, 0.0, 0.7))
    sensor = DepthSensor(load_preset("kinect_v1_paper"), intrinsics=intr)
    with torch.no_grad():
        real = sensor(SensorGeometry.from_hits(cast(one_object_scene(ball, truth_T), intr, 0.075, 0.005)), seed=3).depth
    start_T = pose((0.05, 0.0, 0.0), (0.004, 0.0, 0.7))
    scene = RefinableScene(one_object_scene(ball, start_T), intr, 0.075, 0.005)
    result = refine_poses(sensor, scene, real, RefineSettings(steps=20))
    (identified,) = result.identifiability
    assert identified.undetermined_axes() == ["rotation x", "rotation y", "rotation z"]
    assert float(scene.poses.rotation.detach()[0].abs().max()) < 1e-9


def test_a_box_seen_at_a_corner_has_all_six_directions_determined():
    sensor, view, _ = _box_views(1.0)
    with torch.no_grad():
        view.scene.poses.translation.zero_()
    from ddsgen.realscan.simulate import frame_camera

    view.recast()
    with frame_camera(sensor, view.scene.intrinsics):
        view.assess(sensor)
    (identified,) = view.identifiability
    assert identified.determined.all(), identified.as_dict()


@pytest.mark.skipif(not LINEMOD.is_dir(), reason="shared LineMOD frame not available")
def test_the_cat_from_its_published_pose_is_not_written_worse(tmp_path, capsys):
    """On the shared cat the optimiser's poses raise the gap (5.44 -> ~5.5 mm): the published pose is kept,
    its entry written as published, and the lines name the cat by its obj_id and say why."""
    import json

    out = tmp_path / "refined"
    assert main(["refine", "kinect_v1", str(LINEMOD), "--out", str(out), "--threads", "1", "--quiet"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert any(line.startswith("000006/000000 obj_id 6 (") and "visible" in line for line in lines), lines
    assert not any("object 1" in line for line in lines)
    report = json.loads((out / "report" / "refine_report.json").read_text())["frames"][0]
    assert report["gap_after_mm"] <= report["gap_before_mm"]
    if report["kept_start"]:
        assert "start kept" in report["objects"][0]["decision"]
        source = json.loads((LINEMOD / "test" / "000006" / "scene_gt.json").read_text())
        assert json.loads((out / "test" / "000006" / "scene_gt.json").read_text()) == source


@pytest.mark.skipif(not LINEMOD.is_dir(), reason="shared LineMOD meshes not available")
def test_validation_scene_objects_come_back_and_none_ends_worse():
    """The first report scene of tests/refine_validation.py (4 LineMOD objects, 2 unannotated distractors, an
    occluder, the independent sensor): from 3 deg / 8 mm every object ends no worse than it started, most
    well within 1.5 deg / 2 mm."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        rows = run(REPORT_SEEDS[:1], RefineSettings(), verbose=False)
    finally:
        torch.set_num_threads(threads)
    result = summary(rows)
    print(result, [(r["obj_id"], round(r["deg"], 2), round(r["mm"], 2)) for r in rows])
    assert result["worse"] == 0.0
    assert result["deg"] <= 1.5 and result["mm"] <= 2.0


@pytest.mark.skipif(not LINEMOD.is_dir(), reason="shared LineMOD meshes not available")
def test_packed_validation_scene_moves_no_object_more_than_a_degree_or_two_mm_away():
    """The first packed report scene of tests/refine_validation.py (4 LineMOD objects resting on the table, touching
    and hiding each other, beside an unannotated object and a large box the refined scene lacks): no object ends more
    than 1 deg / 2 mm worse than its start (the issue's bound on real cluttered frames), one hidden all but a fifth
    keeps its start rotation, and the objects seen at least one half come back within 2 deg / 1 mm."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        rows = run(PACKED_REPORT_SEEDS[:1], RefineSettings(), verbose=False, layout="packed")
    finally:
        torch.set_num_threads(threads)
    print([(r["obj_id"], round(r["visible"], 2), round(r["deg"], 2), round(r["mm"], 2)) for r in rows])
    for r in rows:
        assert r["deg"] <= r["start_deg"] + 1.0 and r["mm"] <= r["start_mm"] + 2.0, r
        if r["visible"] < 0.3:
            assert r["deg"] == pytest.approx(r["start_deg"], abs=1e-6), r
        if r["visible"] >= 0.5:
            assert r["deg"] < 2.0 and r["mm"] < 1.0, r


@pytest.mark.parametrize("bar", [False, True])
def test_the_visible_fraction_is_estimated_from_what_lies_in_front_of_the_model(bar):
    """A bar the scene lacks, 10 cm in front of half the box: the estimate drops to about the half left in view;
    without it the whole box is seen."""
    from ddsgen.realscan.simulate import frame_camera

    intr = window()
    box = shapes.make_shape("box", {"size": (0.07, 0.055, 0.045)})
    truth_T = pose((-0.6, 0.7, 0.0), (0.0, 0.0, 0.7))
    occluder = PlacedObject(9, "bar", "shape:box", shapes.make_shape("box", {"size": (0.04, 0.2, 0.01)}),
                            pose((0.0, 0.0, 0.0), (0.02, 0.0, 0.6)), 0.6)  # fmt: skip
    measured = one_object_scene(box, truth_T)
    if bar:
        measured = dataclasses.replace(measured, objects=measured.objects + [occluder])
    sensor = DepthSensor(load_preset("kinect_v1_paper"), intrinsics=intr)
    with torch.no_grad():
        real = sensor(SensorGeometry.from_hits(cast(measured, intr, 0.075, 0.005)), seed=3).depth
    view = _View(0, RefinableScene(one_object_scene(box, truth_T), intr, 0.075, 0.005), real, RefineSettings())
    view.recast()
    with frame_camera(sensor, intr):
        view.assess(sensor)
    (seen,) = view.visible_fraction
    if bar:
        assert 0.2 < seen < 0.8
    else:
        assert seen > 0.95


def test_the_turn_noise_comes_from_neighbouring_blocks_and_a_smooth_change_does_not_raise_it():
    """A turn makes one side of a part better and the other worse: a smooth ramp of per-pixel differences. The
    noise of the summed difference comes from neighbouring held-out blocks, so the ramp leaves it at the noise
    of the pixels, where the spread over all pixels (or blocks) counts the ramp as noise."""
    height, width, sigma = 120, 320, 0.002
    heldout = heldout_blocks(height, width, 6, seed=1, view=0)
    cells = block_cells(height, width, 6, seed=1, view=0)[heldout]
    xs = torch.arange(width, dtype=torch.float64).expand(height, width)[heldout]
    ramp = (xs / width - 0.5) * 0.008  # -4 .. +4 mm across the part
    noise = torch.from_numpy(np.random.default_rng(5).normal(0.0, sigma, size=int(heldout.sum())))
    pixels = int(heldout.sum())
    white = sigma * pixels**0.5  # the sum's standard deviation: independent pixels
    assert block_difference_noise([noise], [cells]) == pytest.approx(white, rel=0.15)
    assert block_difference_noise([ramp + noise], [cells]) == pytest.approx(white, rel=0.15)
    assert float((ramp + noise).std()) * pixels**0.5 > 1.4 * white  # the pixel spread: inflated by the ramp
    assert block_difference_noise([noise[:1]], [cells[:1]]) is None  # one block: no pair to compare


def _turned_box_views(rotvec, translation, true_turn: bool):
    """A box 0.7 m away seen at a corner, its correction set to (``rotvec`` rad, ``translation`` m). The real depth
    is taken at the corrected pose (``true_turn``) or at the start moved by the translation alone (the turn is
    not there). Returns (sensor, view)."""
    intr = window()
    box = shapes.make_shape("box", {"size": (0.07, 0.055, 0.045)})
    scene = RefinableScene(one_object_scene(box, pose((-0.6, 0.7, 0.0), (0.0, 0.0, 0.7))), intr, 0.075, 0.005)
    poses = scene.poses
    with torch.no_grad():
        poses.translation[0] = torch.tensor(translation, dtype=torch.float64)
        if true_turn:
            poses.rotation[0] = torch.tensor(rotvec, dtype=torch.float64)
        truth_T = poses.matrices()[0]
    sensor = DepthSensor(load_preset("kinect_v1_paper"), intrinsics=intr)
    with torch.no_grad():
        real = sensor(SensorGeometry.from_hits(cast(one_object_scene(box, truth_T), intr, 0.075, 0.005)), seed=3).depth
    view = _View(0, scene, real, RefineSettings(edge_weight=0.0))
    with torch.no_grad():
        poses.rotation[0] = torch.tensor(rotvec, dtype=torch.float64)
    return sensor, view


@pytest.mark.parametrize("degrees, true_turn", [(3.6, True), (0.6, False)])
def test_a_turn_is_taken_only_where_held_out_pixels_show_it_beyond_noise(degrees, true_turn):
    """A 3.6 deg turn that is really there is taken with the translation; a 0.6 deg turn on a box that did not
    turn (its refined translation right) is dropped: the translation is kept with the start rotation. (A rule
    that dropped a turn only if it made the held-out cost clearly worse kept the 0.6 deg one.)"""
    axis = np.array((0.012, -0.015, 0.008))
    rotvec, translation = tuple(axis / np.linalg.norm(axis) * np.radians(degrees)), (0.003, -0.002, 0.0035)
    sensor, view = _turned_box_views(rotvec, translation, true_turn)
    (decision,) = accept_parts(sensor, [view], 0.015, 0.025)[0][:1]
    assert decision.kept and decision.pixels > 50
    assert decision.translation_only is (not true_turn)
    rotation = view.scene.poses.rotation.detach()[0].numpy()
    np.testing.assert_allclose(rotation, rotvec if true_turn else 0.0, atol=1e-12)
    np.testing.assert_allclose(view.scene.poses.translation.detach()[0].numpy(), translation, atol=1e-12)


def test_the_outline_behind_clutter_the_scene_lacks_does_not_pull():
    """A bar the scene lacks, 10 cm in front of the box's right half: the real edges there are the bar's, so the
    box's outline points under the bar are left out (its left half keeps them); without the bar all are kept."""
    from ddsgen.realscan.simulate import frame_camera

    intr = window()
    box = shapes.make_shape("box", {"size": (0.07, 0.055, 0.045)})
    truth_T = pose((-0.6, 0.7, 0.0), (0.0, 0.0, 0.7))
    occluder = PlacedObject(9, "bar", "shape:box", shapes.make_shape("box", {"size": (0.05, 0.2, 0.01)}),
                            pose((0.0, 0.0, 0.0), (0.03, 0.0, 0.6)), 0.6)  # fmt: skip
    sensor = DepthSensor(load_preset("kinect_v1_paper"), intrinsics=intr)
    counts = {}
    for bar in (False, True):
        measured = one_object_scene(box, truth_T)
        if bar:
            measured = dataclasses.replace(measured, objects=measured.objects + [occluder])
        with torch.no_grad():
            real = sensor(SensorGeometry.from_hits(cast(measured, intr, 0.075, 0.005)), seed=3).depth
        view = _View(0, RefinableScene(one_object_scene(box, truth_T), intr, 0.075, 0.005), real, RefineSettings())
        with frame_camera(sensor, intr):
            view.recast()
        X = view.outline.points.numpy() @ truth_T[:3, :3].T + truth_T[:3, 3]
        u = intr.fx * X[:, 0] / X[:, 2] + intr.cx
        counts[bar] = (int((u < intr.cx).sum()), int((u > intr.cx + intr.fx * 0.012 / 0.6).sum()))
        if bar:  # none where the bar stands in front of the box (its image columns, with a pixel of slack)
            left, right = (intr.fx * np.array([0.005, 0.055]) / 0.6 + intr.cx)
            assert not np.any((u > left + 1) & (u < right - 1) & (X[:, 2] > 0.62))
    assert counts[False][1] > 20 and counts[True][1] < counts[False][1] / 2
    assert counts[True][0] >= 0.8 * counts[False][0]  # the left half's outline is seen and kept
