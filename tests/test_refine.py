"""Scene gradients (issue 16): triangle ids from the ray cast, hits recomputed from posed triangles,
gradients through the sensor checked against finite differences, pose refinement that recovers known
poses despite an unmodelled occluder, the refine CLI and its writers."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from torch_threads import torch_threads
from ddsgen.cli import main
from ddsgen.preset import Intrinsics, load_preset
from ddsgen.raycast import cast
from ddsgen.scene import shapes
from ddsgen.scene.sampling import FrameScene, PlacedObject
from ddsgen.scene_gradients import RefinableScene, RefineSettings, posed_geometry, refine_poses, render_depth
from ddsgen.scene_gradients.poses import axis_angle_to_matrix, perturb_pose, pose_difference
from ddsgen.sensor.depth_sensor import DepthSensor
from ddsgen.sensor.geometry import SensorGeometry

from refine_validation import LINEMOD  # noqa: E402  (the shared data, found from a checkout or a worktree)


def rotation(rx: float = 0.0, ry: float = 0.0) -> np.ndarray:
    return axis_angle_to_matrix(torch.tensor([rx, 0.0, 0.0], dtype=torch.float64)).numpy() @ axis_angle_to_matrix(
        torch.tensor([0.0, ry, 0.0], dtype=torch.float64)).numpy()  # fmt: skip


def pose(R=np.eye(3), t=(0.0, 0.0, 0.0)) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


def crop_camera(width: int = 120, height: int = 100) -> Intrinsics:
    """A window at the centre of kinect_v1's 640x480 image: full-resolution depth steps, few pixels."""
    full = load_preset("kinect_v1").intrinsics
    return Intrinsics(width, height, full.fx, full.fy, full.cx - (640 - width) // 2, full.cy - (480 - height) // 2)


def box_scene(extra=()) -> FrameScene:
    """A box seen at a corner (three faces: every pose parameter is observable in depth) 0.7 m away in
    front of a tilted support plane, plus ``extra`` objects."""
    box = shapes.make_shape("box", {"size": (0.07, 0.055, 0.045)})
    objects = [PlacedObject(1, "box", "shape:box", box, pose(rotation(-0.6, 0.7), (0.0, 0.0, 0.7)), 0.6)]
    plane = PlacedObject(0, "plane", "plane:2x2", shapes.plane_mesh(2.0, 2.0), pose(rotation(-0.9), (0, 0.1, 0.78)), 0.6)
    return FrameScene(objects + list(extra), [plane], np.eye(4), 0, 0)


def sensor_for(intr: Intrinsics) -> DepthSensor:
    # The paper's sensor: these tests check the gradient mechanism and the loop. With the device preset
    # (clean-up selection, read+shot noise) measured: finite differences within 11 % (test bound 10 %) and
    # recovery 0.72 deg (bound 0.6) -- the device's discrete clean-up makes the loss rougher in the pose.
    return DepthSensor(load_preset("kinect_v1_paper"), intrinsics=intr)


def test_the_depth_loss_counts_depth_only_where_the_sensor_resolves_it():
    """A wall at 2 m beside one at 6 m, the simulation at the clean depth. Beyond the resolved depth (kinect_v1:
    one 1/8-px quantum is 50 mm at 4.14 m, 105 mm at 6 m) the real depth is one quantum level or another whatever
    the pose, so a 20 mm error there moves neither the loss nor the compared pixels; on the near wall it does."""
    from ddsgen.realscan.losses import resolved_depth_m
    from ddsgen.scene_gradients.refine import robust_depth_loss

    preset = load_preset("kinect_v1")
    limit = resolved_depth_m(preset.focal_px * preset.baseline_m, preset.subpixel_step_px)
    assert limit == pytest.approx(4.14, abs=0.01)
    clean = torch.full((10, 20), 2.0)
    clean[:, 10:] = 6.0
    valid = torch.ones_like(clean, dtype=torch.bool)
    far_error, near_error = clean.clone(), clean.clone()
    far_error[:, 10:] += 0.02
    near_error[:, :10] += 0.02
    exact, mask = robust_depth_loss(clean, valid, clean, clean, 0.025, 0.003, limit)
    far, far_mask = robust_depth_loss(clean, valid, clean, far_error, 0.025, 0.003, limit)
    near, _ = robust_depth_loss(clean, valid, clean, near_error, 0.025, 0.003, limit)
    unlimited, all_mask = robust_depth_loss(clean, valid, clean, far_error, 0.025, 0.003)
    assert int(mask.sum()) == int(far_mask.sum()) == 100 and not bool(mask[:, 10:].any())
    assert float(exact) == float(far) == 0.0
    assert float(near) == pytest.approx(0.02 - 0.0015, rel=1e-4)  # Huber, linear beyond 3 mm: |r| - delta/2
    assert int(all_mask.sum()) == 200 and float(unlimited) == pytest.approx(0.5 * (0.02 - 0.0015), rel=1e-4)


# ------------------------------------------------------------------------------------------ ray cast ids


def test_triangle_ids_and_barycentrics_rebuild_the_hit_points():
    intr = crop_camera()
    scene = box_scene()
    hits = cast(scene, intr, 0.075, 0.005)
    parts = scene.objects + scene.background
    assert set(np.unique(hits.owner)) <= {-1, 0, 1}
    for k, part in enumerate(parts):
        sel = hits.owner == k
        assert sel.sum() > 200
        if k == 1:  # the plane is cast analytically: face 0, whose plane holds every hit
            vertices = np.asarray(part.mesh.vertices)[np.asarray(part.mesh.faces)[0]] @ part.world_T_obj[:3, :3].T
            normal = np.cross(vertices[1] - vertices[0], vertices[2] - vertices[0])
            offset = normal @ (vertices[0] + part.world_T_obj[:3, 3])
            assert (hits.triangle[sel] == 0).all()
            assert np.abs(hits.points[sel] @ normal - offset).max() < 1e-5 * np.linalg.norm(normal)
            continue
        faces = np.asarray(part.mesh.faces)[hits.triangle[sel]]
        vertices = np.asarray(part.mesh.vertices) @ part.world_T_obj[:3, :3].T + part.world_T_obj[:3, 3]
        u, v = hits.barycentric[sel, 0], hits.barycentric[sel, 1]
        rebuilt = ((1 - u - v)[:, None] * vertices[faces[:, 0]] + u[:, None] * vertices[faces[:, 1]]
                   + v[:, None] * vertices[faces[:, 2]])  # fmt: skip
        assert np.abs(rebuilt - hits.points[sel]).max() < 2e-5  # m
        assert (u >= -1e-4).all() and (v >= -1e-4).all() and (u + v <= 1 + 1e-4).all()
    assert (hits.triangle[hits.owner < 0] == -1).all()


def test_posed_hits_reproduce_the_cast_and_follow_a_move_like_a_recast():
    intr = crop_camera()
    scene = RefinableScene(box_scene(), intr, 0.075, 0.005)
    tensors = scene.cast()
    R, t = scene.poses()
    geometry = posed_geometry(tensors, R, t, scene.poses.albedo)
    hits = cast(scene.current_scene(), intr, 0.075, 0.005)
    assert torch.allclose(geometry.clean_depth, torch.from_numpy(hits.depth), atol=2e-6)
    assert torch.allclose(geometry.normals, torch.from_numpy(hits.normals), atol=1e-4)
    # Move the bracket 4 mm away and tilt it 1 degree: on pixels that keep their triangle, the recomputed
    # depth equals a fresh ray cast's (exact, not a linearisation).
    with torch.no_grad():
        scene.poses.translation[0, 2] = 0.004
        scene.poses.rotation[0, 0] = math.radians(1.0)
    R, t = scene.poses()
    moved = posed_geometry(tensors, R, t, scene.poses.albedo).clean_depth
    recast = cast(scene.current_scene(), intr, 0.075, 0.005)
    same = (recast.owner == 0) & (hits.owner == 0) & (hits.triangle == recast.triangle)
    assert same.sum() > 500
    assert np.abs(moved.detach().numpy()[same] - recast.depth[same]).max() < 1e-5
    assert np.abs(moved.detach().numpy()[same] - hits.depth[same]).mean() > 2e-3  # it did move


def test_the_ir_margin_strip_is_cast_and_posed_with_the_scene():
    """The strip the IR camera sees beyond the right edge follows the poses as the image does: posed, it
    equals a fresh ray cast of the columns right of the image."""
    from ddsgen.sensor.ir_margin import margin_intrinsics

    intr = crop_camera()
    scene = RefinableScene(box_scene(), intr, 0.075, 0.005, ir_margin_px=4)
    tensors = scene.cast()
    assert tensors.shape == (intr.height, intr.width) and tensors.ir_margin.shape == (intr.height, 4)
    before = cast(scene.current_scene(), margin_intrinsics(intr, 4), 0.075, 0.005).depth
    with torch.no_grad():
        scene.poses.translation[1, 2] = 0.004  # the support plane, which the strip sees, 4 mm away
    R, t = scene.poses()
    geometry = posed_geometry(tensors, R, t, scene.poses.albedo)
    assert geometry.with_ir_margin().shape == (intr.height, intr.width + 4)
    recast = cast(scene.current_scene(), margin_intrinsics(intr, 4), 0.075, 0.005)
    same = recast.hit & tensors.ir_margin.hit.numpy()
    assert same.mean() > 0.9
    moved = geometry.ir_margin.clean_depth.detach().numpy()
    assert np.abs(moved[same] - recast.depth[same]).max() < 1e-5
    assert np.abs(moved[same] - before[same]).mean() > 2e-3  # it did move


# ------------------------------------------------------------------------------------------ gradients


def test_pose_and_albedo_gradients_through_the_sensor_match_finite_differences():
    """d(mean simulated depth of the object)/d(pose) and d(mean IR)/d(pose, albedo): autograd vs central
    differences, through the IR image and the matcher (quantise=False: the rounding's straight-through
    gradients are by design not derivatives). Steps move disparities by ~0.02 px, small against the
    soft-argmax spread; pixels valid at the start only (an invalid pixel's depth is not smooth)."""
    intr = crop_camera(72, 64)
    scene = RefinableScene(box_scene(), intr, 0.075, 0.005)
    tensors = scene.cast()
    sensor = sensor_for(intr)
    for p in sensor.parameters():
        p.requires_grad_(False)
    noise = sensor.draw_noise(3)

    def render():
        R, t = scene.poses()
        return render_depth(sensor, tensors, R, t, scene.poses.albedo, noise=noise, quantise=False)

    with torch.no_grad():
        on_object = render().valid & (tensors.instance > 0)
    assert on_object.sum() > 500
    depth_of_object = lambda: render().raw_depth[on_object].mean()  # noqa: E731
    mean_ir = lambda: render().ir.mean()  # noqa: E731
    poses = scene.poses
    checks = [(depth_of_object, poses.translation, (0, 2), 2e-4), (depth_of_object, poses.translation, (0, 0), 2e-4),
              (depth_of_object, poses.rotation, (0, 1), 3e-3), (mean_ir, poses.log_albedo, (0,), 1e-2)]  # fmt: skip
    gradients = {}
    for loss, param, index, h in checks:
        param.grad = None
        loss().backward()
        analytic = float(param.grad[index])
        with torch.no_grad():
            param[index] += h
            up = float(loss())
            param[index] -= 2 * h
            down = float(loss())
            param[index] += h
        numeric = (up - down) / (2 * h)
        assert analytic == pytest.approx(numeric, rel=0.1), (loss, index, analytic, numeric)
        gradients[(loss, index)] = analytic
    # Physics: moving the object 1 mm away makes its depth ~1 mm larger (the window also sees some plane).
    assert 0.9 < gradients[(depth_of_object, (0, 2))] < 1.2
    assert gradients[(mean_ir, (0,))] > 0  # brighter surface, brighter image


# ------------------------------------------------------------------------------------------ refinement


def test_refinement_recovers_a_known_pose_despite_an_unmodelled_occluder():
    intr = crop_camera()
    occluder = PlacedObject(2, "ball", "shape:sphere", shapes.make_shape("sphere", {"radius": (0.015,)}),
                            pose(t=(0.025, 0.015, 0.6)), 0.6)  # fmt: skip
    truth = box_scene([occluder])
    sensor = sensor_for(intr)
    with torch.no_grad():
        real = sensor(SensorGeometry.from_hits(cast(truth, intr, 0.075, 0.005)), seed=11).depth
    model = box_scene()
    true_pose = model.objects[0].world_T_obj
    centre = true_pose[:3, :3] @ model.objects[0].mesh.bounds.mean(0) + true_pose[:3, 3]
    start = perturb_pose(true_pose, centre, 3.0, 10.0, np.random.default_rng(4))
    model.objects[0] = dataclasses.replace(model.objects[0], world_T_obj=start)
    scene = RefinableScene(model, intr, 0.075, 0.005)
    # Without the edge term: the simulated sensor's outlines are eroded (invalidated rims), so sim-vs-sim
    # they pull (measured 1.99 deg with it); real Kinect outlines follow the surface (the cat), where it helps.
    result = refine_poses(sensor, scene, real, RefineSettings(steps=40, edge_weight=0.0))
    deg, mm = pose_difference(result.refined[0], true_pose)
    assert deg < 0.6 and mm < 1.0, (deg, mm)  # from 3 deg / 10 mm (measured: 0.26 deg, 0.24 mm)
    assert result.gap_after_mm < 0.5 * result.gap_before_mm


# ------------------------------------------------------------------------------------------ depth-edge term


def face_on_box_scene(dx_m: float = 0.0) -> FrameScene:
    """A box facing the camera squarely 0.7 m away on a plane 0.8 m away: depth cannot see it slide sideways."""
    box = shapes.make_shape("box", {"size": (0.05, 0.04, 0.03)})
    objects = [PlacedObject(1, "box", "shape:box", box, pose(t=(dx_m, 0.0, 0.7)), 0.6)]
    plane = PlacedObject(0, "plane", "plane:2x2", shapes.plane_mesh(2.0, 2.0), pose(t=(0.0, 0.0, 0.8)), 0.6)
    return FrameScene(objects, [plane], np.eye(4), 0, 0)


def test_real_edges_are_the_near_side_of_depth_jumps_and_truncated():
    from ddsgen.scene_gradients.edges import real_edge_distance

    depth = np.full((40, 60), 0.8, dtype=np.float32)
    depth[10:30, 15:35] = 0.7  # an object 10 cm in front
    depth[10:30, 35:40] = 0.705  # a ledge 5 mm behind it: no occluding edge between them
    depth[10:30, 8:15] = 0.0  # its projector shadow: a hole between it and the plane
    depth[0, :] = 0.0  # an invalid row on the plane: no nearer surface there, no edge
    distance = real_edge_distance(depth, jump_m=0.015, max_px=4.0)
    assert (distance[10, 15:35] == 0).all() and (distance[10:30, 15] == 0).all()  # the rim, also beside the hole
    assert (distance[9, 16:34] == 1).all()  # the plane beside it is not an edge: one pixel away
    assert distance[20, 7] == pytest.approx(4.0)  # the far side of the hole, 8 px from the rim: no edge, truncated
    assert (distance[20, 34] > 0) and (distance[20, 33] > 0)  # no jump to the ledge
    assert (distance[1, :] > 0).all()  # next to the invalid row: no nearer surface, no outline


def test_edge_term_pins_an_in_plane_slide_that_depth_cannot_see():
    """A face-on box slid sideways: the clean-depth loss is flat in the slide (the face is the same
    plane), the edge term's minimum is at the true position and its gradient points back to it."""
    from ddsgen.scene_gradients.edges import edge_loss, outline_points, real_edge_distance

    intr = crop_camera()
    real = cast(face_on_box_scene(), intr, 0.075, 0.005).depth
    distance = torch.from_numpy(real_edge_distance(real))
    edge, depth_gap = [], []
    slides = np.arange(-6, 7) * 1e-3
    for dx in slides:
        scene = RefinableScene(face_on_box_scene(dx), intr, 0.075, 0.005)
        tensors = scene.cast()
        R, t = scene.poses()
        clean = posed_geometry(tensors, R, t, scene.poses.albedo).clean_depth
        outline = outline_points(tensors, [p.mesh for p in scene.parts], clean.detach().numpy(), scene.n_objects)
        assert len(outline) > 100
        loss = edge_loss(outline, R, t, distance, intr)
        loss.backward()
        if dx > 0.002:
            assert scene.poses.translation.grad[0, 0] > 0  # descent moves it back (towards -x)
        if dx < -0.002:
            assert scene.poses.translation.grad[0, 0] < 0
        edge.append(float(loss.detach()))
        on_face = (tensors.instance > 0).numpy() & (real > 0) & (real < 0.75)  # the box's front face in both
        assert on_face.sum() > 500
        depth_gap.append(float(np.abs(clean.detach().numpy()[on_face] - real[on_face]).mean()))
    assert slides[int(np.argmin(edge))] == 0.0 and edge[6] < 1e-4  # m: the outline sits on the real edges
    assert max(depth_gap) < 1e-5  # depth does not see the slide at all
    assert edge[0] > 1e-3 and edge[-1] > 1e-3  # 6 mm off: ~3.5 px at 0.7 m


# ------------------------------------------------------------------------------------------ CLI and writers

SMALL_PRESET = """\
name: kinect_v1_small
width_px: 160
height_px: 120
focal_px: 143.1025
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
SCENES = """\
scenes:
  - name: table
    frames: 1
    objects:
      - {shape: box, size: [0.2, 0.15, 0.12], albedo: 0.6}
      - {shape: l_bracket, albedo: 0.6}
    ground: {size: [6, 6], albedo: 0.6}
    camera: {distance: [0.9, 1.1], elevation_deg: [40, 50], azimuth_deg: [-30, 30]}
"""


@pytest.fixture(scope="module")
def rendered(tmp_path_factory):
    from ddsgen.runner import render_dataset

    root = tmp_path_factory.mktemp("refine")
    (root / "small.yaml").write_text(SMALL_PRESET)
    (root / "scenes.yaml").write_text(SCENES)
    render_dataset(str(root / "small.yaml"), str(root / "scenes.yaml"), 1, str(root / "scans"), workers=1, seed=5,
                   progress=False)  # fmt: skip
    return root


def test_refine_cli_writes_a_readable_manifest_with_refined_poses_and_a_report(rendered, tmp_path):
    from ddsgen.io.scanfolder import read_scan_folder

    out = tmp_path / "refined"
    code = main(["refine", str(rendered / "small.yaml"), str(rendered / "scans"), "--out", str(out), "--steps", "3",
                 "--quiet"])  # fmt: skip
    assert code == 0
    source, refined = read_scan_folder(rendered / "scans"), read_scan_folder(out)
    assert len(refined) == len(source) == 1
    assert np.array_equal(refined[0].depth, source[0].depth)  # the depth path points back at the source
    report = json.loads((out / "report" / "refine_report.json").read_text())
    frame_report = report["frames"][0]
    assert (out / "report" / frame_report["picture"]).is_file()
    for obj_new, obj_old, change in zip(refined[0].objects, source[0].objects, frame_report["objects"]):
        assert obj_new.id == obj_old.id == change["id"]
        deg, mm = pose_difference(obj_new.cam_T_obj, obj_old.cam_T_obj)
        assert deg == pytest.approx(change["rotation_deg"], abs=1e-3) and mm == pytest.approx(change["translation_mm"], abs=1e-3)
        # The rendered poses are exact: 3 steps move them a little, not far, and a move is kept only if the
        # held-out pixels find it better; otherwise the start is written, exactly, and the report says why.
        named = f"obj_id {obj_old.obj_id}" if obj_old.obj_id is not None else obj_old.class_name  # the dataset's id
        assert change["label"].split(" #")[0] == named and change["decision"]
        if change["kept"]:
            assert 0 < mm < 5.0 and deg < 2.0
        else:
            assert mm == deg == 0.0 and "start kept" in change["decision"]


def test_refine_cli_rejects_bad_input_with_one_line_and_writes_nothing(rendered, tmp_path, capsys):
    out = tmp_path / "never"
    assert main(["refine", str(rendered / "small.yaml"), str(rendered / "scans"), "--out", str(out), "--steps", "-1"]) == 2
    empty = tmp_path / "empty_scans"
    empty.mkdir()
    record = json.loads((rendered / "scans" / "manifest.jsonl").read_text().splitlines()[0])
    record["objects"] = []
    record["depth"] = str(Path("..") / rendered.name / "scans" / record["depth"])
    (empty / "manifest.jsonl").write_text(json.dumps(record) + "\n")
    assert main(["refine", str(rendered / "small.yaml"), str(empty), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert all(line.startswith("ddsgen: error:") for line in err) and len(err) == 2
    assert not out.exists()


def test_refine_cli_threads_gives_the_same_poses_twice_and_leaves_torch_as_it_was(rendered, tmp_path, capsys):
    """Results are bit-reproducible for a given torch thread count, not across counts (docs/scene_gradients.md):
    --threads fixes it for the run, and the caller's count comes back afterwards."""
    before = torch.get_num_threads()
    threads = 2 if before == 1 else 1
    manifests = []
    for run in range(2):
        out = tmp_path / f"run{run}"
        assert main(["refine", str(rendered / "small.yaml"), str(rendered / "scans"), "--out", str(out), "--steps", "3",
                     "--threads", str(threads), "--quiet"]) == 0  # fmt: skip
        assert torch.get_num_threads() == before
        manifests.append((out / "manifest.jsonl").read_text())
    assert manifests[0] == manifests[1]
    capsys.readouterr()
    assert main(["refine", str(rendered / "small.yaml"), str(rendered / "scans"), "--out", str(tmp_path / "never"),
                 "--threads", "0"]) == 2  # fmt: skip
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--threads" in err[0] and not (tmp_path / "never").exists()


def test_fit_with_refine_poses_reports_both_rounds(rendered, tmp_path):
    out = tmp_path / "fitted.yaml"
    code = main(["fit", str(rendered / "small.yaml"), str(rendered / "scans"), "--out", str(out), "--params", "beta",
                 "--steps", "2", "--refine-poses", "--pose-steps", "2", "--quiet"])  # fmt: skip
    assert code == 0 and out.is_file()
    report = json.loads((tmp_path / "fitted_report" / "fit_report.json").read_text())
    rounds = report["pose_refinement"]["rounds"]
    assert len(rounds) == 2 and all(r[0]["objects"] for r in rounds)


@pytest.mark.skipif(not LINEMOD.is_dir(), reason="shared LineMOD frame not available")
def test_refine_cli_on_bop_keeps_scene_gt_keys_row_major_rotation_and_millimetres(tmp_path):
    out = tmp_path / "refined"
    assert main(["refine", "kinect_v1", str(LINEMOD), "--out", str(out), "--steps", "4", "--gradient", "geometry",
                 "--quiet"]) == 0  # fmt: skip
    source = json.loads((LINEMOD / "test" / "000006" / "scene_gt.json").read_text())
    written = json.loads((out / "test" / "000006" / "scene_gt.json").read_text())
    assert written.keys() == source.keys()
    change = json.loads((out / "report" / "refine_report.json").read_text())["frames"][0]["objects"][0]
    for old, new in zip(source["0"], written["0"]):
        assert new.keys() == old.keys() and new["obj_id"] == old["obj_id"]
        if not change["kept"]:  # the start is kept: its entry as published, untouched (its R is not quite orthonormal)
            assert new == old and change["rotation_deg"] == change["translation_mm"] == 0.0
            continue
        R_old, R_new = np.reshape(old["cam_R_m2c"], (3, 3)), np.reshape(new["cam_R_m2c"], (3, 3))
        assert np.allclose(R_new @ R_new.T, np.eye(3), atol=1e-6)
        T_old, T_new = np.eye(4), np.eye(4)
        T_old[:3, :3], T_old[:3, 3] = R_old, np.asarray(old["cam_t_m2c"]) / 1000.0
        T_new[:3, :3], T_new[:3, 3] = R_new, np.asarray(new["cam_t_m2c"]) / 1000.0
        deg, mm = pose_difference(T_old, T_new)
        # The report's change, recomputed from the files: the same only with row-major R and t in mm.
        assert deg == pytest.approx(change["rotation_deg"], abs=0.05) and mm == pytest.approx(change["translation_mm"], abs=0.05)
        assert 0 < mm < 20


@pytest.mark.skipif(not LINEMOD.is_dir(), reason="shared LineMOD frame not available")
@pytest.mark.parametrize("draw", [3, 7])
def test_real_cat_perturbed_3_deg_8_mm_comes_back_to_the_published_pose(draw):
    """Issue 16's real target on the shared cat (median within 1.5 deg / 3 mm of the published pose, from starts
    3 deg / 8 mm off; measured over 20 starts by bench/bench_refine.py): no start goes astray. Draws 3 and 7 are
    the two of 20 that did with a rotation step of 1e-2 rad (6.99 and 2.67 deg: the noisy steps let the
    rotation wander into a worse pose, and the decayed steps did not bring it back); at 5e-3 every start ends
    within 1.51 deg. (Single starts scatter by ~0.4 deg about the ~1.1 deg by which the published pose itself
    disagrees with this frame's depth and outline: 2 deg, not 1.5, per start.)"""
    from ddsgen.realscan.inputs import adopt_camera
    from ddsgen.realscan.simulate import _load_object_mesh
    from ddsgen.io.scanfolder import read_scan_folder
    from ddsgen.scene_gradients.scan import refine_scan_frame

    (frame,) = read_scan_folder(LINEMOD)
    preset, _ = adopt_camera(load_preset("kinect_v1"), [frame])
    (cat,) = frame.objects
    published = cat.cam_T_obj.copy()
    centre = published[:3, :3] @ _load_object_mesh(cat).bounds.mean(0) + published[:3, 3]
    cat.cam_T_obj = perturb_pose(published, centre, 3.0, 8.0, np.random.default_rng(draw))
    assert pose_difference(cat.cam_T_obj, published) == pytest.approx((3.0, 8.0))
    with torch_threads(1):  # the trajectory depends on the thread count (docs/scene_gradients.md)
        refined = refine_scan_frame(preset, frame, 0, RefineSettings()).result.refined[0]
    deg, mm = pose_difference(refined, published)
    print(f"draw {draw}: {deg:.2f} deg {mm:.2f} mm from the published pose")
    assert deg <= 2.0 and mm <= 3.0
