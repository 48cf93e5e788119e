"""``ddsgen render --format bop``: the BOP layout, read back by ddsgen's BOP reader and checked
against the BOP format documentation (bop_toolkit's docs/bop_datasets_format.md): keys, units
(mm), rotation matrices, depth_scale, mask_visib pixel counts, binary PLY models."""

from __future__ import annotations

import json
import struct
from pathlib import Path

import cv2
import numpy as np
import pytest

from ddsgen.cli import main
from ddsgen.io.bop_writer import SPLIT, ply_bytes, scans_folder
from ddsgen.io.scanfolder import read_scan_folder
from ddsgen.runner import render_dataset

from tiny_inputs import tiny_preset_yaml, tiny_scenes_yaml, tree_hashes, written_inputs

N = 5


@pytest.fixture(scope="module")
def bop(tmp_path_factory):
    folder = tmp_path_factory.mktemp("bop")
    with written_inputs(folder, tiny_preset_yaml(96, 72), tiny_scenes_yaml(frames=3, clutter=(2, 3))) as paths:
        root = folder / "dataset"
        args = (*paths, N, str(root))
        render_dataset(*args, seed=3, progress=False, output_format="bop")
        yield root, args


def load_ply_like_bop(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Parse a PLY the way bop_toolkit's inout.load_ply does (header properties, float/int/uchar, triangles)."""
    data = path.read_bytes()
    head, body = data.split(b"end_header\n", 1)
    lines = head.decode("utf8").splitlines()
    assert lines[0] == "ply" and lines[1] == "format binary_little_endian 1.0"
    n_pts = n_faces = 0
    props, section = [], None
    for line in lines:
        if line.startswith("element vertex"):
            n_pts, section = int(line.split()[-1]), "v"
        elif line.startswith("element face"):
            n_faces, section = int(line.split()[-1]), "f"
        elif line.startswith("property list") and section == "f":
            assert line.split()[2:] == ["uchar", "int", "vertex_indices"]
        elif line.startswith("property") and section == "v":
            props.append(line.split()[-1])
    assert props[:3] == ["x", "y", "z"]
    stride = 4 * len(props)
    pts = np.frombuffer(body[: n_pts * stride], "<f4").reshape(n_pts, len(props))[:, :3]
    faces = []
    offset = n_pts * stride
    for _ in range(n_faces):
        assert body[offset] == 3  # triangles only, like BOP
        faces.append(struct.unpack("<3i", body[offset + 1 : offset + 13]))
        offset += 13
    assert offset == len(body)
    return pts.astype(np.float64), np.array(faces)


def test_layout_and_json_keys(bop):
    root, _ = bop
    scene = root / SPLIT / "000000"
    camera = json.loads((root / "camera.json").read_text())
    assert set(camera) == {"cx", "cy", "depth_scale", "fx", "fy", "height", "width"}
    scene_camera = json.loads((scene / "scene_camera.json").read_text())
    scene_gt = json.loads((scene / "scene_gt.json").read_text())
    gt_info = json.loads((scene / "scene_gt_info.json").read_text())
    assert sorted(scene_camera, key=int) == sorted(scene_gt, key=int) == sorted(gt_info, key=int) == [
        str(i) for i in range(N)
    ]
    models_info = json.loads((root / "models" / "models_info.json").read_text())
    for im_id, gts in scene_gt.items():
        cam = scene_camera[im_id]
        assert set(cam) >= {"cam_K", "depth_scale"} and len(cam["cam_K"]) == 9
        assert len(gts) == len(gt_info[im_id]) >= 1
        for gt_id, (gt, info) in enumerate(zip(gts, gt_info[im_id])):
            assert set(gt) == {"obj_id", "cam_R_m2c", "cam_t_m2c"} and str(gt["obj_id"]) in models_info
            rotation = np.array(gt["cam_R_m2c"]).reshape(3, 3)
            assert np.allclose(rotation @ rotation.T, np.eye(3), atol=1e-6) and np.linalg.det(rotation) > 0
            assert 300 < gt["cam_t_m2c"][2] < 2000  # millimetres (camera 0.7-1.0 m away)
            assert set(info) == {"bbox_obj", "bbox_visib", "px_count_all", "px_count_valid", "px_count_visib",
                                 "visib_fract"}  # fmt: skip
            mask = cv2.imread(str(scene / "mask_visib" / f"{int(im_id):06d}_{gt_id:06d}.png"), cv2.IMREAD_UNCHANGED)
            assert mask.dtype == np.uint8 and set(np.unique(mask)) <= {0, 255}
            assert int((mask > 0).sum()) == info["px_count_visib"]
            assert info["px_count_valid"] <= info["px_count_visib"] <= info["px_count_all"]


def test_bop_reader_reads_the_same_frames(bop):
    """ddsgen's BOP reader (auto-detected at the dataset root) agrees with the ddsgen-layout render."""
    root, _ = bop
    bop_frames = read_scan_folder(root, eager=True)
    own = read_scan_folder(scans_folder(root), eager=True)
    assert [f.frame for f in bop_frames] == [f.frame for f in own] == list(range(N))
    for a, b in zip(bop_frames, own):
        assert a.layout == "bop" and b.layout == "ddsgen"
        assert a.intrinsics == b.intrinsics
        np.testing.assert_allclose(a.depth, b.depth, atol=1e-6)
        np.testing.assert_allclose(a.world_T_cam, b.world_T_cam, atol=1e-6)
        assert len(a.objects) == len(b.objects)
        for oa, ob in zip(a.objects, b.objects):
            assert oa.id == ob.id and oa.mesh_scale == 0.001
            np.testing.assert_allclose(oa.cam_T_obj, ob.cam_T_obj, atol=1e-6)


def test_models_are_millimetre_plys_that_project_onto_the_masks(bop):
    root, _ = bop
    scene = root / SPLIT / "000000"
    scene_gt = json.loads((scene / "scene_gt.json").read_text())
    camera = json.loads((scene / "scene_camera.json").read_text())
    models_info = json.loads((root / "models" / "models_info.json").read_text())
    for im_id, gts in scene_gt.items():
        K = np.array(camera[im_id]["cam_K"]).reshape(3, 3)
        for gt_id, gt in enumerate(gts):
            pts, faces = load_ply_like_bop(root / "models" / f"obj_{gt['obj_id']:06d}.ply")
            assert faces.max() < len(pts)
            extent = pts.max(0) - pts.min(0)
            assert np.allclose(extent, [models_info[str(gt["obj_id"])][k] for k in ("size_x", "size_y", "size_z")],
                               atol=1e-3)  # fmt: skip
            assert 20 < extent.max() < 500  # millimetres
            cam = pts @ np.array(gt["cam_R_m2c"]).reshape(3, 3).T + np.array(gt["cam_t_m2c"])
            uv = cam @ K.T
            uv = uv[:, :2] / uv[:, 2:]
            mask = cv2.imread(str(scene / "mask_visib" / f"{int(im_id):06d}_{gt_id:06d}.png"), cv2.IMREAD_UNCHANGED)
            ys, xs = np.nonzero(mask)
            if len(xs):  # every visible pixel lies inside the projected model's box
                assert xs.min() >= uv[:, 0].min() - 1.5 and xs.max() <= uv[:, 0].max() + 1.5
                assert ys.min() >= uv[:, 1].min() - 1.5 and ys.max() <= uv[:, 1].max() + 1.5


def test_depth_png_in_bop_units(bop):
    root, _ = bop
    scene = root / SPLIT / "000000"
    camera = json.loads((scene / "scene_camera.json").read_text())
    from ddsgen.io.exr import read_exr

    for im_id in range(N):
        depth = cv2.imread(str(scene / "depth" / f"{im_id:06d}.png"), cv2.IMREAD_UNCHANGED)
        assert depth.dtype == np.uint16
        mm = depth.astype(np.float64) * camera[str(im_id)]["depth_scale"]
        exr = read_exr(scans_folder(root) / "depth" / f"{im_id:06d}.exr").astype(np.float64) * 1000.0
        assert np.abs(mm - exr)[exr > 0].max() <= 0.5 + 1e-6 and (mm[exr == 0] == 0).all()


def test_rerun_resumes_and_is_byte_identical(bop):
    root, args = bop
    before = tree_hashes(root)
    render_dataset(*args, seed=3, progress=False, output_format="bop")
    assert tree_hashes(root) == before


def test_bop_into_foreign_folder_is_one_line_exit_2(bop, tmp_path, capsys):
    _, args = bop
    out = tmp_path / "occupied"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    code = main(["render", args[0], "--scenes", args[1], "-n", "1", "--out", str(out), "--format", "bop", "--quiet"])
    err = capsys.readouterr().err
    assert code == 2 and len(err.strip().splitlines()) == 1 and "not a ddsgen BOP render" in err, err
    assert sorted(p.name for p in out.iterdir()) == ["notes.txt"]


def test_ply_writer_round_trip():
    vertices = np.array([[0, 0, 0], [10, 0, 0], [0, 10, 0]], dtype=np.float64)
    normals = np.array([[0, 0, 1]] * 3, dtype=np.float64)
    path_bytes = ply_bytes(vertices, np.array([[0, 1, 2]]), normals)
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "m.ply"
        path.write_bytes(path_bytes)
        pts, faces = load_ply_like_bop(path)
        import trimesh

        mesh = trimesh.load(path, force="mesh")
    np.testing.assert_allclose(pts, vertices)
    assert faces.tolist() == [[0, 1, 2]] and len(mesh.faces) == 1
