"""Scan-folder readers: ddsgen layout and BOP layout (synthetic folders + the real LineMOD frame)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from ddsgen.errors import InputError
from ddsgen.io.exr import write_exr
from ddsgen.io.manifest import append_record
from ddsgen.io.png import write_depth_png, write_png8, write_png16
from ddsgen.io.scan_frame import ScanFrame
from ddsgen.io.scanfolder import detect_layout, read_scan_folder
from ddsgen.preset import Intrinsics

LINEMOD = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "linemod_bop"
H, W = 12, 16


def rot_z(angle):
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


def pose(angle=0.4, t=(0.05, -0.02, 0.9)):
    m = np.eye(4)
    m[:3, :3] = rot_z(angle)
    m[:3, 3] = t
    return m


def write_ply(path: Path):
    import trimesh

    path.parent.mkdir(parents=True, exist_ok=True)
    trimesh.creation.box(extents=(50.0, 50.0, 50.0)).export(path)


def depth_values(seed=0):
    rng = np.random.default_rng(seed)
    depth = np.round(rng.uniform(0.5, 2.0, (H, W)), 3).astype(np.float32)
    depth[0, :3] = 0
    return depth


# ---------------------------------------------------------------- ddsgen layout


def make_ddsgen(folder: Path, exr_frame: bool = True) -> dict:
    intr = {"width": W, "height": H, "fx": 20.0, "fy": 21.0, "cx": 7.5, "cy": 5.5}
    mesh_abs = folder.parent / "elsewhere" / "thing.ply"
    write_ply(folder / "meshes" / "cube.ply")
    write_ply(mesh_abs)
    expected = {}
    for frame in range(2 + exr_frame):
        depth = depth_values(frame)
        use_exr = exr_frame and frame == 2
        rel = f"depth/{frame:06d}.exr" if use_exr else f"depth/{frame:06d}.png"
        (write_exr if use_exr else write_depth_png)(folder / rel, depth)
        write_png16(folder / "mask" / f"{frame:06d}.png", (depth > 1).astype(np.uint16))
        write_png8(folder / "ir" / f"{frame:06d}.png", depth, max_value=2.0)
        objects = [
            {"id": 1, "mesh": "meshes/cube.ply", "class": "cube", "cam_T_obj": pose(0.1 * frame),
             "bbox": [1, 2, 3, 4], "visible_fraction": 0.5, "mesh_scale": 0.001},
            {"id": 2, "mesh": "shape:sphere", "class": "ball", "cam_T_obj": pose(), "bbox": [0, 0, 1, 1],
             "visible_fraction": 1.0},
            {"id": 3, "mesh": str(mesh_abs), "class": "thing", "cam_T_obj": pose(-0.3), "bbox": [0, 0, 1, 1],
             "visible_fraction": 0.0},
        ]
        append_record(folder / "manifest.jsonl", {
            "frame": frame, "depth": rel, "intrinsics": intr, "depth_scale": 0.001,
            "world_T_cam": pose(0.2 * frame, (0, 0, 1.5)), "objects": objects, "seed": 3,
            "mask": f"mask/{frame:06d}.png", "ir": f"ir/{frame:06d}.png",
        })
        expected[frame] = depth
    return expected


def test_ddsgen_layout_round_trip(tmp_path):
    folder = tmp_path / "scans"
    expected = make_ddsgen(folder)
    assert detect_layout(folder) == "ddsgen"
    frames = read_scan_folder(folder)
    assert [f.name for f in frames] == ["scans/000000", "scans/000001", "scans/000002"]
    for frame in frames:
        assert frame.layout == "ddsgen" and repr(frame).count("lazy") == 1
        assert frame.intrinsics == Intrinsics(W, H, 20.0, 21.0, 7.5, 5.5)
        depth = frame.depth
        assert depth.dtype == np.float32 and depth.shape == (H, W)
        np.testing.assert_allclose(depth, expected[frame.frame], atol=1e-6)
        assert (depth[0, :3] == 0).all()
        np.testing.assert_allclose(frame.world_T_cam, pose(0.2 * frame.frame, (0, 0, 1.5)))
        cube, ball, thing = frame.objects
        assert (cube.id, cube.class_name, cube.mesh_scale) == (1, "cube", 0.001)
        assert Path(cube.mesh_path) == folder / "meshes" / "cube.ply" and Path(cube.mesh_path).is_file()
        assert ball.mesh_path == "shape:sphere" and ball.mesh_scale == 1.0
        assert Path(thing.mesh_path) == tmp_path / "elsewhere" / "thing.ply"
        np.testing.assert_allclose(cube.cam_T_obj, pose(0.1 * frame.frame))
        assert cube.cam_T_obj.dtype == np.float64 and cube.cam_T_obj.shape == (4, 4)
        assert frame.record["seed"] == 3
    assert frames[2].source_depth_path.endswith(".exr")
    assert read_scan_folder(folder / "manifest.jsonl", eager=True)[0].__dict__["_depth"] is not None


def test_ddsgen_real_scan_manifest_minimal(tmp_path):
    """A hand-written real-scan manifest: no seed/bbox/visible_fraction, unknown world_T_cam."""
    write_depth_png(tmp_path / "d.png", depth_values())
    record = {"frame": 0, "depth": "d.png", "depth_scale": 0.001, "world_T_cam": None,
              "intrinsics": {"width": W, "height": H, "fx": 20, "fy": 20, "cx": 8, "cy": 6},
              "objects": [{"id": 1, "mesh": "shape:box", "class": "box", "cam_T_obj": pose().tolist()}]}
    (tmp_path / "manifest.jsonl").write_text(json.dumps(record))  # no trailing newline either
    (frame,) = read_scan_folder(tmp_path)
    assert frame.world_T_cam is None and frame.objects[0].mesh_path == "shape:box"


def test_ddsgen_layout_errors(tmp_path):
    folder = tmp_path / "scans"
    make_ddsgen(folder, exr_frame=False)
    manifest = (folder / "manifest.jsonl").read_bytes()

    (folder / "depth" / "000001.png").unlink()
    with pytest.raises(InputError, match=r"manifest.jsonl: frame 1: depth: file not found"):
        read_scan_folder(folder)

    write_depth_png(folder / "depth" / "000001.png", np.ones((H + 1, W)))
    with pytest.raises(InputError, match=r"000001.png: depth image is 16x13 px, but .*manifest.jsonl .* gives 16x12"):
        read_scan_folder(folder)

    write_png8(folder / "depth" / "000001.png", np.ones((H, W), np.uint8))
    with pytest.raises(InputError, match=r"000001.png: depth PNG must be 16-bit single-channel, got 8-bit"):
        read_scan_folder(folder)
    write_depth_png(folder / "depth" / "000001.png", np.ones((H, W)))

    (folder / "meshes" / "cube.ply").unlink()
    with pytest.raises(InputError, match=r"frame 0: objects\[0\].mesh: file not found"):
        read_scan_folder(folder)
    write_ply(folder / "meshes" / "cube.ply")

    (folder / "manifest.jsonl").write_bytes(manifest.replace(b'"depth_scale":0.001', b'"depth_scale":-1', 1))
    with pytest.raises(InputError, match=r"manifest.jsonl: line 1: depth_scale"):
        read_scan_folder(folder)
    (folder / "manifest.jsonl").write_bytes(b"")
    with pytest.raises(InputError, match=r"manifest.jsonl: no complete records"):
        read_scan_folder(folder)


def test_lazy_depth_reports_corrupt_file_on_access(tmp_path):
    folder = tmp_path / "scans"
    make_ddsgen(folder, exr_frame=False)
    frames = read_scan_folder(folder)
    data = (folder / "depth" / "000000.png").read_bytes()
    (folder / "depth" / "000000.png").write_bytes(data[:60])  # header intact, pixels cut
    with pytest.raises(InputError, match=r"000000.png: cannot read depth PNG"):
        _ = frames[0].depth


# ---------------------------------------------------------------- BOP layout (synthetic)


def make_bop(root: Path, split="test", scene="000001", depth_scale=0.1, n_images=2) -> Path:
    scene_dir = root / split / scene
    write_ply(root / "models" / "obj_000003.ply")
    cameras, gts = {}, {}
    for image_id in range(n_images):
        depth_m = depth_values(image_id)
        units = np.round(depth_m * 1000 / depth_scale).astype(np.uint16)
        write_png16(scene_dir / "depth" / f"{image_id:06d}.png", units)
        cameras[str(image_id)] = {"cam_K": [20.0, 0, 7.5, 0, 21.0, 5.5, 0, 0, 1], "depth_scale": depth_scale}
        gts[str(image_id)] = [
            {"obj_id": 3, "cam_R_m2c": rot_z(0.3).ravel().tolist(), "cam_t_m2c": [10.0, -20.0, 900.0 + image_id]},
            {"obj_id": 3, "cam_R_m2c": np.eye(3).ravel().tolist(), "cam_t_m2c": [0.0, 0.0, 1200.0]},
        ]
    (scene_dir / "scene_camera.json").write_text(json.dumps(cameras))
    (scene_dir / "scene_gt.json").write_text(json.dumps(gts))
    return scene_dir


def test_bop_layout_synthetic(tmp_path):
    scene = make_bop(tmp_path)
    for path in (tmp_path, tmp_path / "test", scene):
        assert detect_layout(path) == "bop"
        frames = read_scan_folder(path)
        assert [f.name for f in frames] == ["000001/000000", "000001/000001"]
    frame = frames[1]
    assert frame.layout == "bop" and frame.world_T_cam is None
    assert frame.intrinsics == Intrinsics(W, H, 20.0, 21.0, 7.5, 5.5)
    assert frame.depth_scale == pytest.approx(0.0001)
    np.testing.assert_allclose(frame.depth, depth_values(1), atol=1e-6)
    first, second = frame.objects
    assert (first.id, second.id, first.obj_id, first.class_name) == (1, 2, 3, "obj_000003")
    assert first.mesh_scale == 0.001 and Path(first.mesh_path) == tmp_path / "models" / "obj_000003.ply"
    np.testing.assert_allclose(first.cam_T_obj[:3, 3], [0.010, -0.020, 0.901])  # mm -> m
    np.testing.assert_allclose(first.cam_T_obj[:3, :3], rot_z(0.3), atol=1e-12)


def test_bop_world_pose_and_split_choice(tmp_path):
    scene = make_bop(tmp_path, n_images=1)
    make_bop(tmp_path, split="train_pbr", scene="000009", n_images=1)
    cameras = json.loads((scene / "scene_camera.json").read_text())
    cameras["0"]["cam_R_w2c"] = rot_z(0.5).ravel().tolist()
    cameras["0"]["cam_t_w2c"] = [0.0, 100.0, 2000.0]
    (scene / "scene_camera.json").write_text(json.dumps(cameras))
    (frame,) = read_scan_folder(tmp_path)  # two splits: "test" wins
    assert frame.name == "000001/000000"
    cam_T_world = np.linalg.inv(frame.world_T_cam)
    np.testing.assert_allclose(cam_T_world[:3, 3], [0, 0.1, 2.0], atol=1e-12)
    np.testing.assert_allclose(cam_T_world[:3, :3], rot_z(0.5), atol=1e-12)
    shutil.rmtree(tmp_path / "test")
    make_bop(tmp_path, split="val_a", scene="000002", n_images=1)
    with pytest.raises(InputError, match="several BOP splits"):
        read_scan_folder(tmp_path)


def edit_json(path: Path, change):
    data = json.loads(path.read_text())
    change(data)
    path.write_text(json.dumps(data))


BOP_BREAKAGES = [
    ("scene_camera.json", lambda d: d["0"].pop("cam_K"), r"scene_camera.json: 0.cam_K: missing"),
    ("scene_camera.json", lambda d: d["0"].pop("depth_scale"), r"scene_camera.json: 0.depth_scale: missing"),
    ("scene_camera.json", lambda d: d["0"].update(depth_scale=0), r"0.depth_scale: must be a finite number > 0"),
    ("scene_camera.json", lambda d: d["0"].update(cam_K=[1, 2, 3]), r"0.cam_K: must be a list of 9 numbers"),
    ("scene_camera.json", lambda d: d["0"].update(cam_K=[20, 0, 75, 0, 21, 5.5, 0, 0, 1]), r"principal point"),
    ("scene_gt.json", lambda d: d.pop("1"), r"scene_gt.json: 1: missing"),
    ("scene_gt.json", lambda d: d["0"][1].pop("cam_t_m2c"), r"scene_gt.json: 0\[1\].cam_t_m2c: missing"),
    ("scene_gt.json", lambda d: d["0"][0].update(cam_R_m2c=[1.1, 0, 0, 0, 1, 0, 0, 0, 1]),
     r"scene_gt.json: 0\[0\].cam_R_m2c: rotation is not orthonormal"),
    ("scene_gt.json", lambda d: d["0"][0].update(cam_R_m2c=[-1, 0, 0, 0, 1, 0, 0, 0, 1]),
     r"0\[0\].cam_R_m2c: rotation determinant"),
    ("scene_gt.json", lambda d: d["0"][0].update(obj_id=4), r"obj_000004.ply: model of obj_id 4 not found"),
    ("scene_gt.json", lambda d: d["0"][0].update(cam_t_m2c=["a", 0, 0]), r"0\[0\].cam_t_m2c: must be a list"),
]


@pytest.mark.parametrize("name, change, message", BOP_BREAKAGES)
def test_bop_bad_json(tmp_path, name, change, message):
    scene = make_bop(tmp_path)
    edit_json(scene / name, change)
    with pytest.raises(InputError, match=message):
        read_scan_folder(tmp_path)


def test_bop_bad_files(tmp_path):
    scene = make_bop(tmp_path)
    (scene / "scene_gt.json").write_text("{not json")
    with pytest.raises(InputError, match=r"scene_gt.json: not valid JSON"):
        read_scan_folder(scene)
    (scene / "scene_gt.json").unlink()
    with pytest.raises(InputError, match=r"scene_gt.json: not found"):
        read_scan_folder(scene)

    scene = make_bop(tmp_path / "b")
    (scene / "depth" / "000001.png").unlink()
    with pytest.raises(InputError, match=r"depth/000001.png: depth image not found"):
        read_scan_folder(scene)
    write_png8(scene / "depth" / "000001.png", np.ones((H, W), np.uint8))
    with pytest.raises(InputError, match=r"000001.png: depth PNG must be 16-bit single-channel, got 8-bit"):
        read_scan_folder(scene)
    (scene / "depth" / "000001.png").write_bytes(b"junk")
    with pytest.raises(InputError, match=r"000001.png: cannot read depth PNG \(not a PNG file\)"):
        read_scan_folder(scene)
    write_png16(scene / "depth" / "000001.png", np.ones((H, W), np.uint16))
    (tmp_path / "b" / "camera.json").write_text(json.dumps({"width": 640, "height": 480}))
    with pytest.raises(InputError, match=r"000000.png: depth image is 16x12 px, but .*camera.json gives 640x480"):
        read_scan_folder(scene)
    (tmp_path / "b" / "camera.json").write_text(json.dumps({"width": W, "height": H}))
    assert len(read_scan_folder(scene)) == 2

    shutil.rmtree(tmp_path / "b" / "models")
    deep = tmp_path / "c" / "x" / "y" / "z"
    make_bop(deep)
    shutil.move(str(deep / "models"), str(tmp_path / "c"))  # 4 levels above the scene: too far
    with pytest.raises(InputError, match=r"000001: models: no models/ folder .* up to 3 levels"):
        read_scan_folder(deep / "test" / "000001")


def test_not_a_scan_folder(tmp_path):
    with pytest.raises(InputError, match=r"missing: scan folder not found"):
        read_scan_folder(tmp_path / "missing")
    (tmp_path / "empty" / "sub").mkdir(parents=True)
    with pytest.raises(InputError, match=r"empty: not a scan folder"):
        read_scan_folder(tmp_path / "empty")


def test_scanframe_with_given_depth():
    frame = ScanFrame(name="x/000000", intrinsics=Intrinsics(2, 1, 1.0, 1.0, 1.0, 0.5), objects=[],
                      world_T_cam=None, source_depth_path="", depth=np.array([[1.0, 0.0]]))
    assert frame.depth.dtype == np.float32 and frame.depth.tolist() == [[1.0, 0.0]]


# ---------------------------------------------------------------- the real LineMOD frame


@pytest.fixture
def linemod():
    if not (LINEMOD / "test" / "000006" / "scene_gt.json").is_file():
        pytest.skip(f"real LineMOD data absent ({LINEMOD.resolve()})")
    return LINEMOD


def test_linemod_real_frame(linemod):
    for path in (linemod, linemod / "test", linemod / "test" / "000006"):
        assert detect_layout(path) == "bop"
    (frame,) = read_scan_folder(linemod / "test" / "000006")
    assert frame.name == "000006/000000"
    intr = frame.intrinsics
    assert (intr.width, intr.height) == (640, 480)
    assert intr.fx == pytest.approx(572.41, abs=0.01) and intr.fy == pytest.approx(573.57, abs=0.01)
    assert intr.cx == pytest.approx(325.26, abs=0.01) and intr.cy == pytest.approx(242.05, abs=0.01)

    depth = frame.depth
    assert depth.dtype == np.float32 and depth.shape == (480, 640)
    valid = depth > 0
    assert depth[valid].min() == pytest.approx(0.468, abs=1e-6)
    assert depth.max() == pytest.approx(2.090, abs=1e-6)
    assert 0.05 < 1 - valid.mean() < 0.08  # 6.4 % invalid (PROVENANCE.txt)

    (cat,) = frame.objects
    assert (cat.id, cat.obj_id, cat.mesh_scale) == (1, 6, 0.001)
    assert Path(cat.mesh_path).name == "obj_000006.ply" and Path(cat.mesh_path).is_file()
    rotation, t = cat.cam_T_obj[:3, :3], cat.cam_T_obj[:3, 3]
    np.testing.assert_allclose(rotation @ rotation.T, np.eye(3), atol=1e-12)  # re-orthonormalised
    assert np.linalg.det(rotation) == pytest.approx(1.0, abs=1e-12)
    assert cat.visible_fraction is None  # this copy ships no scene_gt_info.json
    assert 0.9 < np.linalg.norm(t) < 1.2 and t[2] == pytest.approx(1.0508, abs=1e-3)

    # the pose is in metres and in this camera: its origin projects into the annotated box [331, 130, 65, 64]
    # and the measured depth there lies within the cat's radius (~77 mm) in front of its centre
    u = intr.fx * t[0] / t[2] + intr.cx
    v = intr.fy * t[1] / t[2] + intr.cy
    assert 331 <= u <= 331 + 65 and 130 <= v <= 130 + 64
    patch = depth[int(v) - 2 : int(v) + 3, int(u) - 2 : int(u) + 3]
    assert 0 < t[2] - np.median(patch[patch > 0]) < 0.08


# ---------------------------------------------------------------- BOP data as published (issue 14)


def test_bop_rounded_rotation_is_reorthonormalised_broken_ones_rejected(tmp_path):
    scene = make_bop(tmp_path, n_images=1)
    exact = rot_z(0.3) @ np.array([[1, 0, 0], [0, np.cos(1.1), -np.sin(1.1)], [0, np.sin(1.1), np.cos(1.1)]])
    rounded = np.round(exact, 3)  # published to 3 decimals: |R R^T - I| ~ 1e-3
    assert np.abs(rounded @ rounded.T - np.eye(3)).max() > 1e-4  # the old limit refused this
    edit_json(scene / "scene_gt.json", lambda d: d["0"][0].update(cam_R_m2c=rounded.ravel().tolist()))
    (frame,) = read_scan_folder(tmp_path)
    rotation = frame.objects[0].cam_T_obj[:3, :3]
    np.testing.assert_allclose(rotation @ rotation.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(rotation) == pytest.approx(1.0, abs=1e-12)
    np.testing.assert_allclose(rotation, exact, atol=1e-3)  # the nearest rotation: the one that was rounded
    # A shear of 5 % is not rounding: still refused with one line, as are NaN and reflections.
    for bad, message in ((exact @ np.diag([1.05, 1, 1]), r"0\[0\].cam_R_m2c: rotation is not orthonormal .* > 0.01"),
                         (np.full((3, 3), np.nan), r"0\[0\].cam_R_m2c: has non-finite values"),
                         (-exact, r"0\[0\].cam_R_m2c: rotation determinant")):  # fmt: skip
        edit_json(scene / "scene_gt.json", lambda d, m=bad: d["0"][0].update(cam_R_m2c=m.ravel().tolist()))
        with pytest.raises(InputError, match=message):
            read_scan_folder(tmp_path)


def test_bop_dataset_with_several_scenes_and_no_rgb(tmp_path):
    make_bop(tmp_path, scene="000001", n_images=2)
    second = make_bop(tmp_path, scene="000002", n_images=1)
    units = np.round(depth_values(7) * 1000 / 0.1).astype(np.uint16)  # scene 2 has its own depth
    write_png16(second / "depth" / "000000.png", units)
    assert not any(tmp_path.rglob("rgb"))
    frames = read_scan_folder(tmp_path)
    assert [f.name for f in frames] == ["000001/000000", "000001/000001", "000002/000000"]
    np.testing.assert_allclose(frames[2].depth, depth_values(7), atol=1e-6)
    np.testing.assert_allclose(frames[0].depth, depth_values(0), atol=1e-6)
    assert frames[0].frame == frames[2].frame == 0  # image ids repeat across scenes; names do not


def test_bop_depth_scale_per_image(tmp_path):
    scene = make_bop(tmp_path, depth_scale=0.1, n_images=2)
    # image 1 stored in whole millimetres instead of 0.1 mm units
    write_png16(scene / "depth" / "000001.png", np.round(depth_values(1) * 1000).astype(np.uint16))
    edit_json(scene / "scene_camera.json", lambda d: d["1"].update(depth_scale=1.0))
    first, second = read_scan_folder(scene)
    assert (first.depth_scale, second.depth_scale) == pytest.approx((0.0001, 0.001))
    np.testing.assert_allclose(first.depth, depth_values(0), atol=1e-6)
    np.testing.assert_allclose(second.depth, depth_values(1), atol=1e-6)


def test_bop_scene_gt_info_visibility(tmp_path):
    scene = make_bop(tmp_path, n_images=2)
    info = {"0": [{"visib_fract": 0.4, "px_count_visib": 10}, {"visib_fract": 0.0, "px_count_visib": 0}],
            "1": [{"visib_fract": 1.0}, {"visib_fract": 0.25}]}  # fmt: skip
    (scene / "scene_gt_info.json").write_text(json.dumps(info))
    first, second = read_scan_folder(tmp_path)
    # image 0: the fully hidden second object is not counted; ids stay BOP's gt index + 1
    assert [(o.id, o.visible_fraction) for o in first.objects] == [(1, 0.4)]
    assert [(o.id, o.visible_fraction) for o in second.objects] == [(1, 1.0), (2, 0.25)]
    for change, message in ((lambda d: d["0"].pop(), r"scene_gt_info.json: 0: must list one entry per object .* 1 "
                                                     r"entries"),
                            (lambda d: d.pop("1"), r"scene_gt_info.json: 1: .* got missing"),
                            (lambda d: d["1"][1].update(visib_fract=1.5), r"1\[1\].visib_fract: must be a number in "
                                                                          r"\[0, 1\], got 1.5")):  # fmt: skip
        (scene / "scene_gt_info.json").write_text(json.dumps(info))
        edit_json(scene / "scene_gt_info.json", change)
        with pytest.raises(InputError, match=message):
            read_scan_folder(tmp_path)
    # without scene_gt_info.json, visibility is unknown and every object is kept
    (scene / "scene_gt_info.json").unlink()
    assert [o.visible_fraction for o in read_scan_folder(tmp_path)[0].objects] == [None, None]


def test_ddsgen_layout_keeps_visible_fraction(tmp_path):
    make_ddsgen(tmp_path / "scans", exr_frame=False)
    frame = read_scan_folder(tmp_path / "scans")[0]
    assert [o.visible_fraction for o in frame.objects] == [0.5, 1.0, 0.0]
