"""EXR / PNG writers and readers, the JSON Lines manifest."""

from __future__ import annotations

import hashlib

import cv2
import numpy as np
import pytest

from ddsgen.errors import InputError
from ddsgen.io.exr import read_exr, write_exr
from ddsgen.io.png import (
    read_depth_png,
    read_png8,
    read_png16,
    write_depth_png,
    write_png8,
    write_png16,
)


def sha(path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def depth_image(h=24, w=32, seed=0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    depth = rng.uniform(0.4, 4.0, (h, w)).astype(np.float32)
    depth[rng.random((h, w)) < 0.2] = 0.0
    return depth


def no_temp_files(folder) -> bool:
    return not [p for p in folder.iterdir() if p.name.startswith(".")]


# ---------------------------------------------------------------- EXR


def test_exr_round_trip_exact(tmp_path):
    depth = depth_image()
    path = tmp_path / "d" / "000000.exr"
    write_exr(path, depth)
    back = read_exr(path)
    assert back.dtype == np.float32 and back.shape == depth.shape
    np.testing.assert_array_equal(back, depth)  # float32 is stored losslessly
    assert (back[depth == 0] == 0).all()
    assert no_temp_files(path.parent)


def test_exr_header_is_single_z_channel_zip(tmp_path):
    import OpenEXR

    path = tmp_path / "a.exr"
    write_exr(path, depth_image())
    exr = OpenEXR.File(str(path), separate_channels=True)
    assert list(exr.channels()) == ["Z"]
    assert exr.header()["compression"] == OpenEXR.ZIP_COMPRESSION
    assert exr.channels()["Z"].pixels.dtype == np.float32


def test_exr_deterministic_bytes(tmp_path):
    depth = depth_image()
    write_exr(tmp_path / "a.exr", depth)
    write_exr(tmp_path / "b.exr", depth.copy())
    assert sha(tmp_path / "a.exr") == sha(tmp_path / "b.exr")


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_exr_refuses_nan_inf(tmp_path, bad):
    depth = depth_image()
    depth[3, 4] = bad
    with pytest.raises(ValueError, match="NaN/inf"):
        write_exr(tmp_path / "a.exr", depth)
    assert not (tmp_path / "a.exr").exists() and no_temp_files(tmp_path)


def test_exr_refuses_wrong_shape(tmp_path):
    with pytest.raises(ValueError):
        write_exr(tmp_path / "a.exr", np.zeros((2, 3, 3), np.float32))


def test_exr_reads_rgb_and_half_and_y(tmp_path):
    import OpenEXR

    rgb = np.random.default_rng(1).random((5, 6, 3)).astype(np.float32)
    OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION}, {"RGB": rgb}).write(str(tmp_path / "rgb.exr"))
    np.testing.assert_array_equal(read_exr(tmp_path / "rgb.exr"), rgb[..., 0])

    half = rgb[..., 1].astype(np.float16)
    OpenEXR.File({}, {"Y": half}).write(str(tmp_path / "y.exr"))
    back = read_exr(tmp_path / "y.exr")
    assert back.dtype == np.float32
    np.testing.assert_array_equal(back, half.astype(np.float32))


def test_exr_foreign_nan_becomes_invalid(tmp_path):
    import OpenEXR

    z = np.ones((3, 4), np.float32)
    z[1, 1] = np.nan
    z[2, 2] = np.inf
    OpenEXR.File({}, {"Z": z}).write(str(tmp_path / "n.exr"))
    back = read_exr(tmp_path / "n.exr")
    assert back[1, 1] == 0 and back[2, 2] == 0 and back[0, 0] == 1


def test_exr_bad_files(tmp_path):
    with pytest.raises(InputError, match="missing.exr: cannot read EXR"):
        read_exr(tmp_path / "missing.exr")
    (tmp_path / "junk.exr").write_bytes(b"not an exr at all")
    with pytest.raises(InputError, match="junk.exr: cannot read EXR"):
        read_exr(tmp_path / "junk.exr")
    write_exr(tmp_path / "ok.exr", depth_image(64, 64))
    data = (tmp_path / "ok.exr").read_bytes()
    (tmp_path / "cut.exr").write_bytes(data[: len(data) // 2])
    with pytest.raises(InputError, match="cut.exr: cannot read EXR"):
        read_exr(tmp_path / "cut.exr")


# ---------------------------------------------------------------- PNG


def test_depth_png_round_trip_mm(tmp_path):
    depth = depth_image()
    path = tmp_path / "depth.png"
    write_depth_png(path, depth)
    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert raw.dtype == np.uint16 and raw.ndim == 2
    back = read_depth_png(path)
    assert back.dtype == np.float32 and back.shape == depth.shape
    assert np.abs(back - depth).max() <= 0.0005 + 1e-6  # half a millimetre
    assert (back[depth == 0] == 0).all() and (back[depth > 0] > 0).all()
    assert no_temp_files(tmp_path)


def test_depth_png_rounding_and_range(tmp_path):
    depth = np.array([[0.0, 1.0004, 1.0006, 0.0015, 65.535, 65.5354, 65.536, 100.0, -1.0]], np.float32)
    write_depth_png(tmp_path / "r.png", depth)
    units = read_png16(tmp_path / "r.png")
    np.testing.assert_array_equal(units, [[0, 1000, 1001, 2, 65535, 65535, 0, 0, 0]])
    np.testing.assert_allclose(read_depth_png(tmp_path / "r.png")[0, :3], [0.0, 1.0, 1.001], rtol=0, atol=1e-7)


def test_depth_png_other_scale(tmp_path):
    depth = np.array([[1.0, 2.0, 0.0]], np.float32)
    write_depth_png(tmp_path / "s.png", depth, depth_scale=0.0001)
    np.testing.assert_array_equal(read_png16(tmp_path / "s.png"), [[10000, 20000, 0]])
    np.testing.assert_allclose(read_depth_png(tmp_path / "s.png", depth_scale=0.0001), depth)


def test_depth_png_refuses_nan(tmp_path):
    with pytest.raises(ValueError, match="NaN/inf"):
        write_depth_png(tmp_path / "n.png", np.array([[np.nan, 1.0]]))
    assert not (tmp_path / "n.png").exists()


def test_png_deterministic_bytes(tmp_path):
    depth = depth_image()
    write_depth_png(tmp_path / "a.png", depth)
    write_depth_png(tmp_path / "b.png", depth.copy())
    assert sha(tmp_path / "a.png") == sha(tmp_path / "b.png")
    mask = (np.arange(24 * 32).reshape(24, 32) % 7).astype(np.uint16)
    write_png16(tmp_path / "m1.png", mask)
    write_png16(tmp_path / "m2.png", mask.copy())
    assert sha(tmp_path / "m1.png") == sha(tmp_path / "m2.png")


def test_read_depth_png_rejects_bad_files(tmp_path):
    cv2.imwrite(str(tmp_path / "eight.png"), np.full((4, 5), 7, np.uint8))
    with pytest.raises(InputError, match=r"eight.png: depth PNG must be 16-bit single-channel, got 8-bit"):
        read_depth_png(tmp_path / "eight.png")
    cv2.imwrite(str(tmp_path / "colour.png"), np.full((4, 5, 3), 700, np.uint16))
    with pytest.raises(InputError, match=r"colour.png: .*3 channels"):
        read_depth_png(tmp_path / "colour.png")
    (tmp_path / "junk.png").write_bytes(b"\x89PNG\r\n\x1a\n garbage")
    with pytest.raises(InputError, match=r"junk.png: cannot read depth PNG"):
        read_depth_png(tmp_path / "junk.png")
    (tmp_path / "empty.png").write_bytes(b"")
    with pytest.raises(InputError, match=r"empty.png: cannot read depth PNG"):
        read_depth_png(tmp_path / "empty.png")
    with pytest.raises(InputError, match=r"missing.png: cannot read depth PNG \(no such file\)"):
        read_depth_png(tmp_path / "missing.png")
    write_depth_png(tmp_path / "small.png", np.ones((4, 5)))
    assert read_depth_png(tmp_path / "small.png", expected_shape=(4, 5)).shape == (4, 5)
    with pytest.raises(InputError, match=r"small.png: depth PNG is 5x4 px, expected 640x480"):
        read_depth_png(tmp_path / "small.png", expected_shape=(480, 640))


def test_png16_mask_round_trip(tmp_path):
    mask = np.zeros((6, 7), np.int64)
    mask[2:4, 3:5] = 3
    mask[0, 0] = 65535
    write_png16(tmp_path / "mask.png", mask)
    back = read_png16(tmp_path / "mask.png")
    assert back.dtype == np.uint16
    np.testing.assert_array_equal(back, mask)
    with pytest.raises(ValueError):
        write_png16(tmp_path / "x.png", np.array([[70000]]))
    with pytest.raises(ValueError):
        write_png16(tmp_path / "x.png", np.array([[1.5]]))


def test_png8(tmp_path):
    ir = np.array([[0.0, 511.5, 1023.0, 5000.0, -3.0]])
    write_png8(tmp_path / "ir.png", ir, max_value=1023)
    np.testing.assert_array_equal(read_png8(tmp_path / "ir.png"), [[0, 128, 255, 255, 0]])
    u8 = np.arange(20, dtype=np.uint8).reshape(4, 5)
    write_png8(tmp_path / "u8.png", u8)
    np.testing.assert_array_equal(read_png8(tmp_path / "u8.png"), u8)
    with pytest.raises(ValueError, match="max_value"):
        write_png8(tmp_path / "f.png", ir)
    write_png16(tmp_path / "sixteen.png", np.ones((2, 2), np.uint16))
    with pytest.raises(InputError, match="must be 8-bit"):
        read_png8(tmp_path / "sixteen.png")


# ---------------------------------------------------------------- manifest

from ddsgen.io.manifest import (  # noqa: E402
    MANIFEST_SCHEMA,
    append_record,
    dumps_record,
    read_manifest,
    repair_manifest,
    sorted_records,
    validate_record,
)


def pose(angle=0.3, t=(0.1, -0.2, 1.0)) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    m = np.eye(4)
    m[:3, :3] = [[c, -s, 0], [s, c, 0], [0, 0, 1]]
    m[:3, 3] = t
    return m


def record(frame=0, **changes) -> dict:
    rec = {
        "frame": frame,
        "depth": f"depth/{int(frame):06d}.png",
        "depth_exr": f"depth/{int(frame):06d}.exr",
        "intrinsics": {"width": 640, "height": 480, "fx": 572.41, "fy": 573.57, "cx": 325.26, "cy": 242.05},
        "depth_scale": 0.001,
        "world_T_cam": pose(0.1, (0.0, 0.0, 1.5)),
        "objects": [
            {
                "id": 1,
                "mesh": "shape:box",
                "class": "box",
                "cam_T_obj": pose(),
                "bbox": [10, 20, 30, 40],
                "visible_fraction": 0.75,
            }
        ],
        "seed": 7,
    }
    rec.update(changes)
    return rec


def test_manifest_schema_documented():
    for key in ("frame", "depth", "intrinsics", "depth_scale", "world_T_cam", "cam_T_obj", "bbox", "seed"):
        assert key in MANIFEST_SCHEMA


def test_manifest_round_trip_and_canonical_bytes(tmp_path):
    path = tmp_path / "out" / "manifest.jsonl"
    for frame in (2, 0, 1):
        append_record(path, record(frame))
    records = read_manifest(path)
    assert [r["frame"] for r in records] == [2, 0, 1]
    assert [r["frame"] for r in sorted_records(records)] == [0, 1, 2]
    np.testing.assert_allclose(records[0]["objects"][0]["cam_T_obj"], pose())
    assert records[0]["intrinsics"]["fx"] == 572.41
    # canonical: same records -> same bytes, whatever the dict order
    shuffled = dict(reversed(list(record(5).items())))
    assert dumps_record(shuffled) == dumps_record(record(5))
    other = tmp_path / "again.jsonl"
    for frame in (2, 0, 1):
        append_record(other, record(frame))
    assert other.read_bytes() == path.read_bytes()
    assert path.read_bytes().count(b"\n") == 3 and b", " not in path.read_bytes()


def test_manifest_crash_truncated_last_line(tmp_path):
    path = tmp_path / "manifest.jsonl"
    append_record(path, record(0))
    append_record(path, record(1))
    full = path.read_bytes()
    line = dumps_record(record(2)).encode()
    path.write_bytes(full + line[: len(line) // 2])  # crash while appending frame 2
    assert [r["frame"] for r in read_manifest(path)] == [0, 1]
    append_record(path, record(2))  # repairs, then appends
    assert [r["frame"] for r in read_manifest(path)] == [0, 1, 2]
    assert path.read_bytes() == full + line + b"\n"


def test_repair_manifest(tmp_path):
    path = tmp_path / "manifest.jsonl"
    assert repair_manifest(path) is False  # missing: nothing to do
    append_record(path, record(0))
    assert repair_manifest(path) is False
    good = path.read_bytes()
    path.write_bytes(good + b'{"frame": 1, "dep')
    assert repair_manifest(path) is True
    assert path.read_bytes() == good
    # a hand-written file whose last complete record lacks the newline keeps it
    path.write_bytes(good + dumps_record(record(1)).encode())
    assert [r["frame"] for r in read_manifest(path)] == [0, 1]
    assert repair_manifest(path) is True and path.read_bytes().endswith(b"}\n")
    assert [r["frame"] for r in read_manifest(path)] == [0, 1]


def test_manifest_corrupt_middle_line(tmp_path):
    path = tmp_path / "manifest.jsonl"
    lines = [dumps_record(record(0)), '{"frame": 1, broken', dumps_record(record(2))]
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(InputError, match=r"manifest.jsonl: line 2: not valid JSON"):
        read_manifest(path)


def test_manifest_duplicate_frame_and_missing_file(tmp_path):
    path = tmp_path / "manifest.jsonl"
    append_record(path, record(0))
    append_record(path, record(0))
    with pytest.raises(InputError, match=r"line 2: frame: duplicate frame 0 \(first on line 1\)"):
        read_manifest(path)
    with pytest.raises(InputError, match=r"nope.jsonl: manifest not found"):
        read_manifest(tmp_path / "nope.jsonl")


def reflect(m):
    m = np.array(m)
    m[:3, 0] *= -1
    return m


def scaled(m):
    m = np.array(m)
    m[:3, :3] *= 1.01
    return m


def bad_last_row(m):
    m = np.array(m)
    m[3, 0] = 0.5
    return m


def obj(**changes):
    o = dict(record()["objects"][0])
    o.update(changes)
    return o


BAD_RECORDS = [
    ({"frame": -1}, "frame: must be an int >= 0"),
    ({"frame": 1.0}, "frame: must be an int"),
    ({"frame": True}, "frame: must be an int"),
    ({"depth": "/abs/depth.png"}, "depth: must be a path relative"),
    ({"depth": ""}, "depth: must be a non-empty relative path"),
    ({"mask": "C:\\x\\m.png"}, "mask: must be a path relative"),
    ({"intrinsics": {"width": 640, "height": 480, "fx": 1, "fy": 1, "cx": 1}}, "intrinsics.cy: missing"),
    ({"intrinsics": {"width": 640.5, "height": 480, "fx": 1, "fy": 1, "cx": 1, "cy": 1}}, "intrinsics.width"),
    ({"intrinsics": {"width": 640, "height": 480, "fx": -1, "fy": 1, "cx": 1, "cy": 1}}, "intrinsics.fx"),
    ({"intrinsics": {"width": 640, "height": 480, "fx": float("inf"), "fy": 1, "cx": 1, "cy": 1}}, "intrinsics.fx"),
    ({"depth_scale": 0}, "depth_scale: must be a finite number > 0"),
    ({"depth_scale": "0.001"}, "depth_scale"),
    ({"world_T_cam": None}, "world_T_cam: must be a 4x4 rigid transform, got null"),
    ({"world_T_cam": np.eye(3)}, "world_T_cam: must be a 4x4 matrix"),
    ({"world_T_cam": reflect(pose())}, "world_T_cam: rotation determinant"),
    ({"world_T_cam": scaled(pose())}, "world_T_cam: rotation is not orthonormal"),
    ({"world_T_cam": bad_last_row(pose())}, "world_T_cam: last row"),
    ({"world_T_cam": [[1, 0, 0, "a"]] * 4}, "world_T_cam: must be a 4x4 matrix of numbers"),
    ({"objects": {}}, "objects: must be a list"),
    ({"objects": [obj(id=0)]}, r"objects\[0\].id: must be an int >= 1"),
    ({"objects": [obj(), obj()]}, r"objects\[1\].id: duplicate id 1"),
    ({"objects": [obj(mesh="")]}, r"objects\[0\].mesh"),
    ({"objects": [obj(**{"class": 3})]}, r"objects\[0\].class"),
    ({"objects": [obj(cam_T_obj=scaled(pose()))]}, r"objects\[0\].cam_T_obj: rotation is not orthonormal"),
    ({"objects": [obj(bbox=[1, 2, 3])]}, r"objects\[0\].bbox"),
    ({"objects": [obj(bbox=[1, -2, 3, 4])]}, r"objects\[0\].bbox"),
    ({"objects": [obj(bbox=[1, 2.5, 3, 4])]}, r"objects\[0\].bbox"),
    ({"objects": [obj(visible_fraction=1.5)]}, r"objects\[0\].visible_fraction"),
    ({"objects": [obj(mesh_scale=0)]}, r"objects\[0\].mesh_scale: must be a finite number > 0"),
    ({"seed": "7"}, "seed: must be an int"),
]


@pytest.mark.parametrize("changes, message", BAD_RECORDS)
def test_validate_record_rejects(changes, message):
    with pytest.raises(InputError, match=message):
        validate_record(record(**changes))


@pytest.mark.parametrize("key", ["frame", "depth", "intrinsics", "depth_scale", "world_T_cam", "objects", "seed"])
def test_validate_record_missing_key(key):
    rec = record()
    del rec[key]
    with pytest.raises(InputError, match=f"{key}: missing"):
        validate_record(rec)
    for name in ("bbox", "visible_fraction", "cam_T_obj"):
        rec = record()
        del rec["objects"][0][name]
        with pytest.raises(InputError, match=rf"objects\[0\].{name}: missing"):
            validate_record(rec)


def test_validate_record_accepts_and_non_strict():
    validate_record(record())
    validate_record(record(objects=[], extra={"anything": 1}))
    real = record(world_T_cam=None)
    del real["seed"]
    del real["objects"][0]["bbox"], real["objects"][0]["visible_fraction"]
    validate_record(real, strict=False)
    with pytest.raises(InputError):
        validate_record(real)


def test_invalid_line_reported_with_file_and_line(tmp_path):
    path = tmp_path / "manifest.jsonl"
    append_record(path, record(0))
    with open(path, "a") as handle:
        handle.write(dumps_record(record(1, depth_scale=-1)) + "\n")
    with pytest.raises(InputError, match=r"manifest.jsonl: line 2: depth_scale: must be"):
        read_manifest(path)
    with pytest.raises(InputError, match=r"manifest.jsonl: depth_scale"):
        append_record(path, record(3, depth_scale=-1))
