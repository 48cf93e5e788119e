"""Regenerate the bad-input corpus (tests/bad_inputs/): malformed presets, scene lists and scan folders.

Run from anywhere: ``python tests/bad_inputs/make_corpus.py``. It rewrites every case and
``manifest.json`` (what each case tests and a fragment the error line must contain).
Every case is small (a few hundred bytes; scan images are 16x12 px). The committed files
are the corpus; this script documents how the binary ones (PNG, PLY) were made.
"""

from __future__ import annotations

import json
import shutil
import struct
import zlib
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent

# A valid tiny preset (96x72 px, kinect_v1 focal scaled by 96/640); cases change one thing.
GOOD_PRESET = {
    "name": "tiny",
    "width_px": 96,
    "height_px": 72,
    "focal_px": 85.86,
    "baseline_m": 0.075,
    "z_min_m": 0.4,
    "z_max_m": 4.0,
    "block_size_px": 9,
    "emitted_intensity": "1.5e6",
    "shadow_bias_m": 0.005,
    "softargmax_beta": 15.0,
    "subpixel_level": 2,
}


def preset_text(**changes) -> str:
    data = dict(GOOD_PRESET)
    for key, value in changes.items():
        if value is _DROP:
            data.pop(key)
        else:
            data[key] = value
    return "".join(f"{k}: {v}\n" for k, v in data.items())


_DROP = object()

CASES: list[dict] = []


def case(kind: str, path: str, tests: str, expect: str, content: str | bytes | None = None) -> None:
    """Record a case; write ``content`` to ``path`` (relative to this folder) when given."""
    if content is not None:
        target = HERE / path
        target.parent.mkdir(parents=True, exist_ok=True)
        if isinstance(content, bytes):
            target.write_bytes(content)
        else:
            target.write_text(content)
    CASES.append({"kind": kind, "path": path, "tests": tests, "expect": expect})


# ----------------------------------------------------------------- binary helpers


def png_bytes(array: np.ndarray) -> bytes:
    """A minimal PNG encoder (grayscale 8 or 16 bit), so the corpus does not depend on OpenCV's output."""
    array = np.asarray(array)
    height, width = array.shape
    depth = 16 if array.dtype == np.uint16 else 8
    raw = b"".join(b"\x00" + (row.astype(">u2").tobytes() if depth == 16 else row.astype(np.uint8).tobytes())
                   for row in array)  # fmt: skip

    def chunk(tag: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data) & 0xFFFFFFFF)

    header = struct.pack(">IIBBBBB", width, height, depth, 0, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", zlib.compress(raw, 9)) + chunk(b"IEND", b"")


TETRA_PLY_MM = """ply
format ascii 1.0
element vertex 4
property float x
property float y
property float z
element face 4
property list uchar int vertex_indices
end_header
0 0 0
50 0 0
0 50 0
0 0 50
3 0 2 1
3 0 1 3
3 0 3 2
3 1 2 3
"""

POINTS_ONLY_PLY = """ply
format ascii 1.0
element vertex 3
property float x
property float y
property float z
end_header
0 0 0
0.1 0 0
0 0.1 0
"""

SCENE_OK_OBJECT = "      - {shape: box, size: [0.1, 0.1, 0.1]}\n"


def scenes_text(objects: str = SCENE_OK_OBJECT, extra: str = "") -> str:
    return "scenes:\n  - name: s\n    frames: 2\n    objects:\n" + objects + extra


# 16x12 scan images
W, H = 16, 12
INTR = {"width": W, "height": H, "fx": 14.3, "fy": 14.3, "cx": 7.5, "cy": 5.5}
EYE = [[1.0, 0, 0, 0], [0, 1.0, 0, 0], [0, 0, 1.0, 0], [0, 0, 0, 1.0]]
POSE = [[1.0, 0, 0, 0], [0, 1.0, 0, 0], [0, 0, 1.0, 0.6], [0, 0, 0, 1.0]]
DEPTH = np.full((H, W), 600, np.uint16)


def ddsgen_scan(name: str, tests: str, expect: str, record_changes=None, depth_png: bytes | None = None,
                manifest_text: str | None = None, with_mesh: bool = True) -> None:  # fmt: skip
    folder = f"scans/{name}"
    record = {
        "frame": 0,
        "depth": "depth/000000.png",
        "intrinsics": dict(INTR),
        "depth_scale": 0.001,
        "world_T_cam": EYE,
        "objects": [{"id": 1, "mesh": "tetra.ply", "class": "tetra", "cam_T_obj": POSE, "mesh_scale": 0.001}],
        "seed": 0,
    }
    for key, value in (record_changes or {}).items():
        if value is _DROP:
            record.pop(key)
        else:
            record[key] = value
    text = manifest_text if manifest_text is not None else json.dumps(record, sort_keys=True) + "\n"
    case("scan", folder, tests, expect, None)
    root = HERE / folder
    root.mkdir(parents=True, exist_ok=True)
    (root / "manifest.jsonl").write_text(text)
    (root / "depth").mkdir(exist_ok=True)
    (root / "depth" / "000000.png").write_bytes(depth_png if depth_png is not None else png_bytes(DEPTH))
    if with_mesh:
        (root / "tetra.ply").write_text(TETRA_PLY_MM)


def bop_scan(name: str, tests: str, expect: str, camera=None, gt=None, depth_png: bytes | None = None,
             raw: dict[str, str] | None = None) -> None:  # fmt: skip
    folder = f"scans/{name}"
    case("scan", folder, tests, expect, None)
    root = HERE / folder
    root.mkdir(parents=True, exist_ok=True)
    cam = {"0": {"cam_K": [14.3, 0, 7.5, 0, 14.3, 5.5, 0, 0, 1], "depth_scale": 1.0}}
    rot = [1, 0, 0, 0, 1, 0, 0, 0, 1]
    scene_gt = {"0": [{"obj_id": 1, "cam_R_m2c": rot, "cam_t_m2c": [0, 0, 600]}]}
    if camera is not None:
        cam = camera(cam)
    if gt is not None:
        scene_gt = gt(scene_gt)
    files = {"scene_camera.json": json.dumps(cam), "scene_gt.json": json.dumps(scene_gt)}
    files.update(raw or {})
    for file_name, text in files.items():
        if text is None:
            (root / file_name).unlink(missing_ok=True)
        else:
            (root / file_name).write_text(text)
    (root / "depth").mkdir(exist_ok=True)
    (root / "depth" / "000000.png").write_bytes(depth_png if depth_png is not None else png_bytes(DEPTH))
    (root / "models").mkdir(exist_ok=True)
    (root / "models" / "obj_000001.ply").write_text(TETRA_PLY_MM)
    camera_json = {"cx": 7.5, "cy": 5.5, "depth_scale": 1.0, "fx": 14.3, "fy": 14.3, "height": H, "width": W}
    (root / "camera.json").write_text(json.dumps(camera_json))  # BOP's dataset-level camera (image size)


def build() -> None:
    for sub in ("presets", "scenes", "scans", "meshes", "controls"):
        shutil.rmtree(HERE / sub, ignore_errors=True)

    # ---------------------------------------------------------------- presets
    P = "preset"
    case(P, "presets/truncated.yaml", "YAML cut off mid-list", "malformed YAML",
         preset_text()[: preset_text().index("block_size_px")] + "block_size_px: [9, 1")
    case(P, "presets/empty.yaml", "empty file", "mapping", "")
    case(P, "presets/not_a_mapping.yaml", "a YAML list instead of a mapping", "mapping", "- width_px\n- 640\n")
    case(P, "presets/binary_garbage.yaml", "not UTF-8 text", "cannot read preset", b"\xff\xfe\x00\x81width_px\x00\x9c")
    case(P, "presets/unknown_key.yaml", "misspelt key, with a suggestion", "focal_lenght_px",
         preset_text().replace("focal_px", "focal_lenght_px"))
    case(P, "presets/missing_focal.yaml", "required key absent", "focal_px", preset_text(focal_px=_DROP))
    case(P, "presets/width_string.yaml", "wrong type: text for an integer", "width_px", preset_text(width_px="wide"))
    case(P, "presets/width_bool.yaml", "wrong type: boolean for an integer", "width_px", preset_text(width_px="true"))
    case(P, "presets/block_fractional.yaml", "wrong type: 9.5 for an integer", "block_size_px",
         preset_text(block_size_px=9.5))
    case(P, "presets/focal_list.yaml", "wrong type: a list for a number", "focal_px", preset_text(focal_px="[572, 572]"))
    case(P, "presets/focal_nan.yaml", "NaN number", "focal_px", preset_text(focal_px=".nan"))
    case(P, "presets/baseline_inf.yaml", "infinite number", "baseline_m", preset_text(baseline_m=".inf"))
    case(P, "presets/intensity_text_nan.yaml", "NaN written as the string 'nan'", "emitted_intensity",
         preset_text(emitted_intensity="nan"))
    case(P, "presets/focal_negative.yaml", "negative focal length", "focal_px", preset_text(focal_px=-85.86))
    case(P, "presets/baseline_zero.yaml", "zero baseline", "baseline_m", preset_text(baseline_m=0))
    case(P, "presets/block_even.yaml", "even block size", "block_size_px", preset_text(block_size_px=8))
    case(P, "presets/block_too_large.yaml", "block larger than the 96x72 image", "block_size_px",
         preset_text(block_size_px=99))
    case(P, "presets/range_inverted.yaml", "z_min >= z_max", "z_min_m", preset_text(z_min_m=4.0, z_max_m=0.4))
    case(P, "presets/disparity_too_large.yaml", "f*b/z_min wider than the image", "z_min_m",
         preset_text(z_min_m=0.05))
    case(P, "presets/subpixel_too_high.yaml", "sub-pixel level out of range", "subpixel_level",
         preset_text(subpixel_level=12))
    case(P, "presets/width_too_small.yaml", "image width below the minimum", "width_px", preset_text(width_px=2))
    case(P, "presets/pattern_missing.yaml", "dot pattern file that does not exist", "pattern file not found",
         preset_text(pattern="no_such_pattern.png"))
    case(P, "presets/pattern_not_an_image.yaml", "dot pattern file that is not an image", "pattern",
         preset_text(pattern="../meshes/not_a_mesh.txt"))
    case(P, "presets/unknown_effect.yaml", "an effect name that does not exist", "effects",
         preset_text(effects="[{name: no_such_effect}]"))

    # ---------------------------------------------------------------- scene lists
    S = "scenes"
    (HERE / "meshes").mkdir(parents=True, exist_ok=True)
    (HERE / "meshes" / "not_a_mesh.txt").write_text("this is not a mesh\n")
    (HERE / "meshes" / "corrupt.ply").write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 99\n\x00\x01garbage")
    (HERE / "meshes" / "points_only.ply").write_text(POINTS_ONLY_PLY)
    (HERE / "meshes" / "empty.obj").write_text("# an OBJ with no vertices and no faces\n")
    case(S, "scenes/empty_file.yaml", "empty scene list file", "empty", "")
    case(S, "scenes/empty_list.yaml", "scenes: [] (no scene)", "scenes", "scenes: []\n")
    case(S, "scenes/truncated.yaml", "YAML cut off mid-mapping", "malformed YAML",
         "scenes:\n  - name: s\n    objects:\n      - {shape: box, size: [0.1, 0.1")
    case(S, "scenes/not_a_mapping.yaml", "a bare string instead of a mapping", "scenes", "just some text\n")
    case(S, "scenes/unknown_key.yaml", "unknown key in an object entry", "colour",
         scenes_text("      - {shape: box, colour: red}\n"))
    case(S, "scenes/unknown_scene_key.yaml", "misspelt key in a scene (with a suggestion)", "clutter",
         scenes_text(extra="    cluter: {count: [1, 2]}\n"))
    case(S, "scenes/empty_pool.yaml", "a scene with no objects", "objects", "scenes:\n  - name: s\n    objects: []\n")
    case(S, "scenes/unknown_shape.yaml", "a built-in shape that does not exist", "dodecahedron",
         scenes_text("      - {shape: dodecahedron}\n"))
    case(S, "scenes/missing_mesh.yaml", "mesh file that does not exist", "not found",
         scenes_text("      - {mesh: ../meshes/does_not_exist.ply}\n"))
    case(S, "scenes/non_mesh_file.yaml", "a text file given as mesh", "not a mesh",
         scenes_text("      - {mesh: ../meshes/not_a_mesh.txt}\n"))
    case(S, "scenes/corrupt_mesh.yaml", "a .ply file with garbage inside", "corrupt.ply",
         scenes_text("      - {mesh: ../meshes/corrupt.ply}\n"))
    case(S, "scenes/mesh_no_faces.yaml", "a PLY point cloud (vertices, no faces)", "points_only.ply",
         scenes_text("      - {mesh: ../meshes/points_only.ply}\n"))
    case(S, "scenes/mesh_empty_obj.yaml", "an OBJ file with nothing in it", "empty.obj",
         scenes_text("      - {mesh: ../meshes/empty.obj}\n"))
    case(S, "scenes/scale_nan.yaml", "NaN mesh scale", "scale",
         scenes_text("      - {shape: box, scale: .nan}\n"))
    case(S, "scenes/scale_negative.yaml", "negative mesh scale", "scale",
         scenes_text("      - {mesh: ../meshes/points_only.ply, scale: -0.001}\n"))
    case(S, "scenes/frames_text.yaml", "wrong type: frames per scene as text", "frames",
         "scenes:\n  - name: s\n    frames: four\n    objects:\n" + SCENE_OK_OBJECT)
    case(S, "scenes/count_negative.yaml", "negative clutter count", "count",
         scenes_text(extra="    clutter: {count: [-1, 3]}\n"))
    case(S, "scenes/range_inverted.yaml", "camera distance range [hi, lo]", "distance",
         scenes_text(extra="    camera: {distance: [2.0, 1.0]}\n"))
    case(S, "scenes/elevation_out_of_range.yaml", "elevation above 89 degrees", "elevation_deg",
         scenes_text(extra="    camera: {elevation_deg: [10, 120]}\n"))
    case(S, "scenes/albedo_inf.yaml", "infinite albedo", "albedo",
         scenes_text("      - {shape: box, albedo: .inf}\n"))

    # ---------------------------------------------------------------- scan folders (ddsgen layout)
    ddsgen_scan("ddsgen_corrupt_depth_png", "depth PNG that is not a PNG", "000000.png",
                depth_png=b"\x89PNG\r\n\x1a\nthis is not really a png")
    ddsgen_scan("ddsgen_wrong_size_depth", "depth PNG 10x10 where intrinsics say 16x12", "000000.png",
                depth_png=png_bytes(np.full((10, 10), 600, np.uint16)))
    ddsgen_scan("ddsgen_8bit_depth", "8-bit depth PNG (must be 16-bit)", "16-bit",
                depth_png=png_bytes(np.full((H, W), 60, np.uint8)))
    ddsgen_scan("ddsgen_nonrigid_pose", "cam_T_obj with a scaled rotation", "cam_T_obj",
                record_changes={"objects": [{"id": 1, "mesh": "tetra.ply", "class": "tetra", "mesh_scale": 0.001,
                                             "cam_T_obj": [[2.0, 0, 0, 0], [0, 1.0, 0, 0], [0, 0, 1.0, 0.6],
                                                           [0, 0, 0, 1.0]]}]})  # fmt: skip
    ddsgen_scan("ddsgen_reflection_pose", "world_T_cam with determinant -1 (a mirror)", "world_T_cam",
                record_changes={"world_T_cam": [[-1.0, 0, 0, 0], [0, 1.0, 0, 0], [0, 0, 1.0, 0], [0, 0, 0, 1.0]]})
    ddsgen_scan("ddsgen_missing_mesh", "object mesh file absent", "mesh", with_mesh=False)
    ddsgen_scan("ddsgen_missing_intrinsics", "record without intrinsics", "intrinsics",
                record_changes={"intrinsics": _DROP})
    ddsgen_scan("ddsgen_corrupt_manifest_line", "a corrupt line before a good one", "line 1",
                manifest_text='{"frame": 0, "depth": \n' + json.dumps({"frame": 1}) + "\n")

    # ---------------------------------------------------------------- scan folders (BOP layout)
    bop_scan("bop_camera_missing_cam_K", "scene_camera.json entry without cam_K", "cam_K",
             camera=lambda c: {"0": {"depth_scale": 1.0}})
    bop_scan("bop_gt_missing_translation", "scene_gt.json entry without cam_t_m2c", "cam_t_m2c",
             gt=lambda g: {"0": [{"obj_id": 1, "cam_R_m2c": [1, 0, 0, 0, 1, 0, 0, 0, 1]}]})
    bop_scan("bop_gt_missing_image", "scene_gt.json lacks an image listed in scene_camera.json", "scene_gt.json",
             gt=lambda g: {})
    bop_scan("bop_no_scene_gt", "scene_gt.json file absent", "scene_gt.json", raw={"scene_gt.json": None})
    bop_scan("bop_invalid_json", "scene_camera.json is not JSON", "scene_camera.json",
             raw={"scene_camera.json": '{"0": {"cam_K": [1, 2'})
    bop_scan("bop_nonrigid_rotation", "cam_R_m2c not orthonormal (scaled by 1.5)", "cam_R_m2c",
             gt=lambda g: {"0": [{"obj_id": 1, "cam_R_m2c": [1.5, 0, 0, 0, 1.5, 0, 0, 0, 1.5],
                                  "cam_t_m2c": [0, 0, 600]}]})  # fmt: skip
    bop_scan("bop_depth_wrong_size", "depth PNG 10x10 where camera.json says 16x12", "000000.png",
             depth_png=png_bytes(np.full((10, 10), 600, np.uint16)))
    bop_scan("bop_model_missing", "obj_id with no models/obj_000002.ply", "obj_id",
             gt=lambda g: {"0": [{"obj_id": 2, "cam_R_m2c": [1, 0, 0, 0, 1, 0, 0, 0, 1], "cam_t_m2c": [0, 0, 600]}]})

    # ---------------------------------------------------------------- controls: the unbroken originals
    # (each case above changes one thing in one of these; the tests check that the controls load)
    bad = list(CASES)
    CASES.clear()
    case("preset", "controls/good_preset.yaml", "the valid tiny preset the preset cases start from", "", preset_text())
    case("scenes", "controls/good_scenes.yaml", "a valid scene list like the scene-list cases", "", scenes_text())
    ddsgen_scan("../controls/good_ddsgen_scan", "a valid ddsgen-layout scan folder", "")
    bop_scan("../controls/good_bop_scan", "a valid BOP-layout scan folder", "")
    controls = [dict(c, path=c["path"].replace("scans/../", "")) for c in CASES]
    CASES[:] = bad
    manifest = {"cases": CASES, "controls": controls}
    (HERE / "manifest.json").write_text(json.dumps(manifest, indent=1) + "\n")
    rows = "".join(f"| `{c['path']}` | {c['kind']} | {c['tests']} | `{c['expect']}` |\n" for c in CASES)
    (HERE / "README.md").write_text(
        "# Bad-input corpus\n\n"
        "Malformed presets, scene lists and scan folders. Each must make ddsgen exit with code 2 and print exactly\n"
        "one line on stderr that names the file and the problem (it must contain the *expect* fragment), with no\n"
        "traceback and nothing written in the output folder (`tests/test_bad_inputs.py`). `controls/` holds the\n"
        "valid originals the cases were derived from (one change each); they must load. `meshes/` holds the broken\n"
        "mesh files the scene lists point at. Regenerate everything with `python tests/bad_inputs/make_corpus.py`;\n"
        "`manifest.json` is the machine-readable list.\n\n"
        f"{len(CASES)} cases:\n\n| path | kind | what is wrong | expect |\n|---|---|---|---|\n" + rows
    )


if __name__ == "__main__":
    build()
    print(f"{len(CASES)} cases in {HERE}")
