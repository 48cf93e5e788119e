"""Refining a static scene seen in several frames (issue 16): one correction per object, in the object's
own frame, moves it alike in every view; several views average what one frame's noise leaves; the
CLI finds a folder's static scenes and writes poses that agree between their frames."""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest
import torch

from ddsgen.cli import main
from ddsgen.errors import InputError
from ddsgen.preset import Intrinsics, load_preset
from ddsgen.raycast import cast
from ddsgen.scene import shapes
from ddsgen.scene.sampling import FrameScene, PlacedObject
from ddsgen.scene_gradients import RefinableScene, RefineSettings, refine_poses
from ddsgen.scene_gradients.poses import SharedObjectCorrections, axis_angle_to_matrix, perturb_pose, pose_difference
from ddsgen.scene_gradients.static_scene import refine_static_scene
from ddsgen.sensor.depth_sensor import DepthSensor
from ddsgen.sensor.geometry import SensorGeometry
from tiny_inputs import tiny_preset_yaml, tiny_scenes_yaml, written_inputs


def rotation(rx=0.0, ry=0.0, rz=0.0) -> np.ndarray:
    return axis_angle_to_matrix(torch.tensor([rx, ry, rz], dtype=torch.float64)).numpy()


def pose(R=np.eye(3), t=(0.0, 0.0, 0.0)) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


def orbit(azimuth_deg: float, elevation_deg: float, centre=(0.0, 0.0, 0.72)) -> np.ndarray:
    """world_T_cam of a camera turned about ``centre`` (world = the first camera's frame)."""
    R = rotation(math.radians(elevation_deg), math.radians(azimuth_deg))
    centre = np.asarray(centre)
    return pose(R, centre - R @ centre)


def box_on_table(world_T_cam=np.eye(4)) -> FrameScene:
    """A box seen at a corner 0.7 m away (three faces: its whole pose shows in depth) on a tilted plane."""
    box = shapes.make_shape("box", {"size": (0.07, 0.055, 0.045)})
    objects = [PlacedObject(1, "box", "shape:box", box, pose(rotation(-0.6, 0.7), (0.0, 0.0, 0.7)), 0.6)]
    plane = PlacedObject(0, "plane", "plane:2x2", shapes.plane_mesh(2.0, 2.0), pose(rotation(-0.9), (0, 0.1, 0.78)), 0.6)
    return FrameScene(objects, [plane], np.asarray(world_T_cam, dtype=np.float64), 0, 0)


def window(width: int = 120, height: int = 100) -> Intrinsics:
    full = load_preset("kinect_v1").intrinsics
    return Intrinsics(width, height, full.fx, full.fy, full.cx - (640 - width) // 2, full.cy - (480 - height) // 2)


def world_pose(scene: RefinableScene, k: int) -> np.ndarray:
    return np.asarray(scene.scene.world_T_cam) @ scene.poses.matrices()[k]


def test_a_shared_correction_moves_the_object_alike_in_every_view():
    intr = window()
    views = [RefinableScene(box_on_table(orbit(az, el)), intr, 0.075, 0.005) for az, el in [(0, 0), (12, -5), (-9, 8)]]
    shared = SharedObjectCorrections(1)
    for view in views:
        view.poses.share_objects(shared)
    with torch.no_grad():
        shared.rotation.copy_(torch.tensor([[0.03, -0.02, 0.05]], dtype=torch.float64))
        shared.translation.copy_(torch.tensor([[0.004, -0.003, 0.002]], dtype=torch.float64))
        for view in views:  # the support plane's own correction stays each view's
            view.poses.rotation[1] = torch.tensor([0.01, 0.0, 0.0], dtype=torch.float64)
    moved = [world_pose(v, 0) for v in views]
    before = views[0].scene.objects[0].world_T_obj
    deg, mm = pose_difference(before, moved[0])
    assert deg == pytest.approx(math.degrees(math.sqrt(0.03**2 + 0.02**2 + 0.05**2)), rel=1e-6)  # a rotation about the box's centre,
    assert 1.0 < mm < 10.0  # plus a translation: the centre moves by exactly |tau| = 5.4 mm
    for other in moved[1:]:
        np.testing.assert_allclose(other, moved[0], atol=1e-12)  # one world pose whichever view it is read from
    centre_obj = views[0].scene.objects[0].mesh.bounds.mean(0)
    centre_before = before[:3, :3] @ centre_obj + before[:3, 3]
    centre_after = moved[0][:3, :3] @ centre_obj + moved[0][:3, 3]
    assert np.linalg.norm(centre_after - centre_before) * 1000 == pytest.approx(math.sqrt(16 + 9 + 4), rel=1e-9)
    # the plane's correction (camera axes, per view) moved each view's plane differently
    planes = [world_pose(v, 1) for v in views]
    assert pose_difference(planes[0], planes[1])[0] > 0.1


def _views(truth_world_T_obj, start_world_T_obj, cameras, seed):
    """(sensor, RefinableScenes at the start pose, real depth of each view at the true pose)."""
    intr = window()
    sensor = DepthSensor(load_preset("kinect_v1_paper"), intrinsics=intr)
    scenes, reals = [], []
    for v, world_T_cam in enumerate(cameras):
        truth = box_on_table(world_T_cam)
        truth.objects[0] = dataclasses.replace(truth.objects[0], world_T_obj=truth_world_T_obj)
        with torch.no_grad():
            reals.append(sensor(SensorGeometry.from_hits(cast(truth, intr, 0.075, 0.005)), seed=seed * 10 + v).depth)
        start = dataclasses.replace(truth, objects=[dataclasses.replace(truth.objects[0], world_T_obj=start_world_T_obj)])
        scenes.append(RefinableScene(start, intr, 0.075, 0.005))
    return sensor, scenes, reals


CAMERAS = [orbit(0, 0), orbit(10, -4), orbit(-8, 6), orbit(4, 9)]


def test_static_scene_refinement_recovers_the_pose_and_averages_the_views_noise():
    truth = box_on_table().objects[0]
    centre = truth.world_T_obj[:3, :3] @ truth.mesh.bounds.mean(0) + truth.world_T_obj[:3, 3]
    start = perturb_pose(truth.world_T_obj, centre, 3.0, 10.0, np.random.default_rng(4))
    sensor, scenes, reals = _views(truth.world_T_obj, start, CAMERAS, seed=1)
    results = refine_static_scene(sensor, scenes, reals, RefineSettings(steps=80, edge_weight=0.0))
    deg, mm = pose_difference(world_pose(scenes[0], 0), truth.world_T_obj)
    # From 3 deg / 10 mm (measured 0.28 deg / 0.12 mm; each view alone: 0.31-1.48 deg, 0.21-0.24 mm).
    assert deg < 0.6 and mm < 1.0, (deg, mm)
    assert all(r.gap_after_mm < 0.5 * r.gap_before_mm for r in results)
    # Started at the truth, the estimate wanders by what the frames' noise allows: four views of the
    # scene leave less of it than one (several noise draws, so that no lucky draw decides; measured over
    # seeds 2-8: four views 0.06-0.25 deg, the first view alone 0.22-0.70 deg). No hold-out: the optimiser's own
    # estimate (the acceptance would keep the true start, which no noise-level gain displaces).
    settings = RefineSettings(steps=40, edge_weight=0.0, holdout_block_px=0)
    single, joint = [], []
    for seed in (2, 3, 4):
        sensor, scenes, reals = _views(truth.world_T_obj, truth.world_T_obj, CAMERAS, seed)
        refine_static_scene(sensor, scenes, reals, settings)
        joint.append(pose_difference(world_pose(scenes[0], 0), truth.world_T_obj))
        sensor, scenes, reals = _views(truth.world_T_obj, truth.world_T_obj, CAMERAS[:1], seed)
        refine_poses(sensor, scenes[0], reals[0], settings)
        single.append(pose_difference(world_pose(scenes[0], 0), truth.world_T_obj))
    assert np.mean([d for d, _ in joint]) < 0.6 * np.mean([d for d, _ in single]), (joint, single)


def test_static_scene_refinement_needs_the_same_objects_in_every_view():
    intr = window()
    first = RefinableScene(box_on_table(), intr, 0.075, 0.005)
    scene = box_on_table()
    other = dataclasses.replace(scene, objects=[dataclasses.replace(scene.objects[0],
                                                                    mesh=shapes.make_shape("box", {"size": (0.05,) * 3}))])
    with pytest.raises(ValueError, match="view 1"):
        refine_static_scene(DepthSensor(load_preset("kinect_v1_paper"), intrinsics=intr),
                            [first, RefinableScene(other, intr, 0.075, 0.005)], [np.zeros((100, 120), np.float32)] * 2)


# ------------------------------------------------------------------------------------------ CLI

@pytest.fixture(scope="module")
def two_static_scenes(tmp_path_factory):
    """Six frames: two layouts, each seen from three camera poses. Returns (preset path, scans folder)."""
    from ddsgen.runner import render_dataset

    root = tmp_path_factory.mktemp("static")
    with written_inputs(root, tiny_preset_yaml(160, 120), tiny_scenes_yaml(frames=3, clutter=(2, 3))) as paths:
        render_dataset(paths[0], paths[1], 6, str(root / "scans"), workers=1, seed=3, progress=False)
    return paths[0], root / "scans"


def _shifted_copy(scans, out, shift_m):
    """A copy of a rendered folder whose objects' annotated poses are moved by ``shift_m`` (world frame, m) in every
    frame alike (a static scene's annotation off by one translation)."""
    import shutil

    shutil.copytree(scans, out)
    lines = []
    for line in (out / "manifest.jsonl").read_text().splitlines():
        record = json.loads(line)
        world_T_cam = np.asarray(record["world_T_cam"], dtype=np.float64)
        shift = np.eye(4)
        shift[:3, 3] = shift_m
        for obj in record["objects"]:
            moved = np.linalg.inv(world_T_cam) @ shift @ world_T_cam @ np.asarray(obj["cam_T_obj"], dtype=np.float64)
            obj["cam_T_obj"] = moved.tolist()
        lines.append(json.dumps(record))
    (out / "manifest.jsonl").write_text("\n".join(lines) + "\n")
    return out


def test_refine_cli_static_scene_writes_one_world_pose_per_object_and_scene(two_static_scenes, tmp_path):
    from ddsgen.io.scanfolder import read_scan_folder
    from ddsgen.scene_gradients.scan import static_scenes

    preset, rendered = two_static_scenes
    scans = _shifted_copy(rendered, tmp_path / "scans", (0.006, 0.0, 0.0))
    frames = read_scan_folder(scans)
    assert [[f.frame for f in group] for _, group in static_scenes(frames)] == [[0, 1, 2], [3, 4, 5]]
    out = tmp_path / "refined"
    # Two of each scene's three frames simulated; the correction they find moves the third one too. The annotated
    # poses are 6 mm off (the same world shift in every frame), so a correction lowers every frame's gap; the held-out
    # acceptance is off here, this checks the sharing.
    assert main(["refine", preset, str(scans), "--out", str(out), "--steps", "3", "--static-scene", "--static-views",
                 "2", "--holdout-block-px", "0", "--quiet"]) == 0  # fmt: skip
    report = json.loads((out / "report" / "refine_report.json").read_text())
    assert [f["frame"].split("/")[1] for f in report["frames"]] == ["000000", "000002", "000003", "000005"]
    refined = read_scan_folder(out)
    moved = 0
    for group in ([refined[0], refined[1], refined[2]], [refined[3], refined[4], refined[5]]):
        for k in range(len(group[0].objects)):
            world = [f.world_T_cam @ f.objects[k].cam_T_obj for f in group]
            for other in world[1:]:
                np.testing.assert_allclose(other, world[0], atol=2e-6)  # manifests hold poses to ~1e-7
            source = frames[group[0].frame].world_T_cam @ frames[group[0].frame].objects[k].cam_T_obj
            moved += pose_difference(source, world[0])[1] > 0.01
    assert moved > 0
    # Without --static-scene every frame moves its objects its own way.
    single = tmp_path / "single"
    assert main(["refine", preset, str(scans), "--out", str(single), "--steps", "3", "--holdout-block-px", "0",
                 "--quiet"]) == 0  # fmt: skip
    apart = read_scan_folder(single)
    world = [f.world_T_cam @ f.objects[0].cam_T_obj for f in apart]  # a frame whose gap does not fall keeps its start
    assert any(pose_difference(world[i], world[j])[1] > 0.01 for i, j in ((0, 1), (0, 2), (1, 2), (3, 4), (3, 5), (4, 5)))


def test_a_static_scene_whose_frames_list_other_objects_is_refused_with_one_line(two_static_scenes):
    from ddsgen.io.scanfolder import read_scan_folder
    from ddsgen.scene_gradients.scan import refine_static_scan

    preset, scans = two_static_scenes
    frames = read_scan_folder(scans)[:2]
    frames[1].objects = frames[1].objects[1:]
    with pytest.raises(InputError, match="same objects in the same order"):
        refine_static_scan(load_preset(preset), frames)
    never = scans.parent / "never"
    assert main(["refine", preset, str(scans), "--out", str(never), "--static-scene", "--static-views", "0"]) == 2
    assert not never.exists()


def test_fit_refine_poses_static_scene_moves_each_object_alike_in_every_frame_of_its_scene(two_static_scenes, tmp_path):
    preset, scans = two_static_scenes
    refused = tmp_path / "refused.yaml"
    assert main(["fit", preset, str(scans), "--out", str(refused), "--static-scene", "--quiet"]) == 2
    assert not refused.exists()
    out = tmp_path / "fitted.yaml"
    assert main(["fit", preset, str(scans), "--out", str(out), "--params", "beta", "--steps", "2", "--refine-poses",
                 "--pose-steps", "3", "--static-scene", "--static-views", "2", "--quiet"]) == 0  # fmt: skip
    refinement = json.loads((tmp_path / "fitted_report" / "fit_report.json").read_text())["pose_refinement"]
    assert refinement["static_scene"] and refinement["static_views"] == 2 and len(refinement["rounds"]) == 2
    for changes in refinement["rounds"]:
        assert [c["frame"].split("/")[-1] for c in changes] == [f"{k:06d}" for k in range(6)]
        for scene in (changes[:3], changes[3:]):  # the frame not simulated (--static-views 2) moves alike too
            for k in range(len(scene[0]["objects"])):
                # From the exact rendered poses a 3-step move is kept only where held-out pixels favour it (the
                # CLI test above checks, with the acceptance off, that a kept move is shared): moved or not, alike.
                moved = [(c["objects"][k]["rotation_deg"], c["objects"][k]["translation_mm"]) for c in scene]
                for other in moved[1:]:
                    assert other == pytest.approx(moved[0], abs=1e-3)
