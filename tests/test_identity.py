"""Stable object identity (obj_id / class_id, classes.json, BOP export), the models folder for mesh paths and the
``render --camera`` intrinsics override."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import yaml

from ddsgen.cli import main
from ddsgen.errors import InputError
from ddsgen.io.bop_writer import SPLIT, scans_folder, write_bop_dataset
from ddsgen.io.manifest import read_manifest
from ddsgen.io.scanfolder import read_scan_folder
from ddsgen.runner import render_dataset
from ddsgen.scene.scenelist import load_scene_list, scene_list_from_dict

from tiny_inputs import tiny_preset_yaml, tiny_scenes_yaml, written_inputs

ROOT = Path(__file__).resolve().parents[1]
LINEMOD_MODELS = Path("/work/shared/data/linemod_bop/models")
LINEMOD_IDS = {1, 5, 6, 8, 9, 10, 11, 12}


def ids_by_class(scene_list) -> dict[str, int]:
    return {entry.class_name: entry.obj_id for entry in scene_list.classes}


# ------------------------------------------------------------------------------------------------ the class table


def test_ids_come_from_the_key_then_the_bop_name_then_the_first_free_number(tmp_path):
    (tmp_path / "obj_000007.stl").write_bytes(b"")  # replaced below by a real mesh
    import trimesh

    trimesh.creation.box((0.05, 0.05, 0.05)).export(tmp_path / "obj_000007.stl")
    data = {"scenes": [
        {"objects": [{"shape": "box", "class": "crate"}, {"mesh": "obj_000007.stl", "class": "widget"},
                     {"shape": "sphere", "class": "ball", "obj_id": 1}]},
        {"objects": [{"shape": "cylinder", "class": "can"}, {"shape": "box", "class": "crate"}]},
    ]}  # fmt: skip
    scene_list = scene_list_from_dict(data, "x.yaml", base_dir=tmp_path)
    # ball claims 1 by key, widget 7 by its file name; crate and can take the free 2 and 3 in scene-list order,
    # and the crate of the second scene is the same object as the first one's
    assert ids_by_class(scene_list) == {"ball": 1, "crate": 2, "can": 3, "widget": 7}
    assert [e.class_id for e in scene_list.classes] == [1, 2, 3, 7]
    again = scene_list_from_dict(data, "x.yaml", base_dir=tmp_path)
    assert again.classes == scene_list.classes


def test_a_shared_class_name_gives_one_class_id_and_two_obj_ids():
    data = {"scenes": [{"objects": [{"shape": "box", "size": [0.1, 0.1, 0.1], "class": "box", "obj_id": 4},
                                    {"shape": "box", "size": [0.2, 0.1, 0.1], "class": "box"}]}]}  # fmt: skip
    entries = scene_list_from_dict(data, "x.yaml").classes
    assert [(e.obj_id, e.class_id) for e in entries] == [(1, 1), (4, 1)]  # class_id: the smallest obj_id


@pytest.mark.parametrize("objects, fragment", [
    ([{"shape": "box", "obj_id": 3}, {"shape": "sphere", "obj_id": 3}], "obj_id 3 (from scenes[0].objects[1].obj_id)"
                                                                         " is already the id of scenes[0].objects[0]"),
    ([{"shape": "box", "obj_id": 0}], "scenes[0].objects[0].obj_id: must be >= 1"),
    ([{"shape": "box", "obj_id": 2.5}], "scenes[0].objects[0].obj_id: expected an integer"),
])  # fmt: skip
def test_conflicting_or_bad_ids_are_one_line_errors(objects, fragment):
    with pytest.raises(InputError) as info:
        scene_list_from_dict({"scenes": [{"objects": objects}]}, "x.yaml")
    assert fragment in str(info.value) and "\n" not in str(info.value)


def test_every_frame_records_the_class_table_ids(tmp_path):
    with written_inputs(tmp_path, tiny_preset_yaml(64, 48), tiny_scenes_yaml(frames=2, clutter=(2, 3))) as paths:
        render_dataset(*paths, 4, str(tmp_path / "out"), seed=5, progress=False)
    table = json.loads((tmp_path / "out" / "classes.json").read_text())["classes"]
    assert [(row["id"], row["class"]) for row in table] == [(1, "box"), (2, "cylinder"), (3, "sphere")]
    by_class = {row["class"]: row["id"] for row in table}
    records = read_manifest(tmp_path / "out" / "manifest.jsonl")
    placed = [obj for record in records for obj in record["objects"]]
    assert len({obj["class"] for obj in placed}) >= 2  # the ids are checked on more than one class
    for obj in placed:
        assert obj["obj_id"] == obj["class_id"] == by_class[obj["class"]]
    frames = read_scan_folder(tmp_path / "out")
    assert [o.obj_id for f in frames for o in f.objects] == [o["obj_id"] for o in placed]


def test_a_manifest_without_ids_still_reads_and_exports(tmp_path):
    """Renders made before obj_id existed: the scan reader reads them, BOP export numbers meshes 1..N."""
    with written_inputs(tmp_path, tiny_preset_yaml(64, 48), tiny_scenes_yaml(frames=2, clutter=(2, 3))) as paths:
        render_dataset(*paths, 2, str(tmp_path / "out"), seed=5, progress=False)
    manifest = tmp_path / "out" / "manifest.jsonl"
    lines = []
    for record in read_manifest(manifest):
        for obj in record["objects"]:
            del obj["obj_id"], obj["class_id"]
        lines.append(json.dumps(record))
    manifest.write_text("\n".join(lines) + "\n")
    (tmp_path / "out" / "classes.json").unlink()
    frames = read_scan_folder(tmp_path / "out")
    assert frames and all(o.obj_id is None for f in frames for o in f.objects)
    write_bop_dataset(tmp_path / "out", tmp_path / "bop")
    models = sorted(p.name for p in (tmp_path / "bop" / "models").glob("*.ply"))
    assert models == [f"obj_{i:06d}.ply" for i in range(1, len(models) + 1)]


# ------------------------------------------------------------------------------------------------ LineMOD, BOP export


@pytest.mark.skipif(not LINEMOD_MODELS.is_dir(), reason=f"LineMOD models not present at {LINEMOD_MODELS}")
def test_bop_export_of_linemod_keeps_the_ids_its_file_names_give(tmp_path):
    """The shipped LineMOD scene list, its meshes found through --models: obj_ids are 1, 5, 6, ... as named."""
    scenes = ROOT / "scenes" / "linemod_objects.yaml"
    assert ids_by_class(load_scene_list(scenes, LINEMOD_MODELS)) == {
        "ape": 1, "can": 5, "cat": 6, "driller": 8, "duck": 9, "eggbox": 10, "glue": 11, "holepuncher": 12}
    (tmp_path / "tiny.yaml").write_text(tiny_preset_yaml(64, 48))
    root = tmp_path / "bop"
    code = main(["render", str(tmp_path / "tiny.yaml"), "--scenes", str(scenes), "--models", str(LINEMOD_MODELS),
                 "-n", "2", "--out", str(root), "--format", "bop", "--quiet", "--no-preview"])  # fmt: skip
    assert code == 0
    models = {int(p.stem[4:]) for p in (root / "models").glob("obj_*.ply")}
    names = json.loads((root / "models" / "models_names.json").read_text())
    assert models and models <= LINEMOD_IDS
    for obj_id in models:  # the model written as obj_00000K is the mesh the dataset calls K
        assert Path(names[str(obj_id)]["mesh"]).name == f"obj_{obj_id:06d}.ply"
    scene_gt = json.loads((root / SPLIT / "000000" / "scene_gt.json").read_text())
    gt_ids = {gt["obj_id"] for gts in scene_gt.values() for gt in gts}
    assert gt_ids == models
    table = json.loads((scans_folder(root) / "classes.json").read_text())["classes"]
    assert {row["id"] for row in table} == LINEMOD_IDS


def test_a_missing_mesh_says_how_to_point_at_the_models(tmp_path, monkeypatch):
    monkeypatch.delenv("DDSGEN_MODELS", raising=False)
    path = tmp_path / "s.yaml"
    path.write_text(yaml.safe_dump({"scenes": [{"objects": [{"mesh": "../nowhere/obj_000003.ply"}]}]}))
    with pytest.raises(InputError) as info:
        load_scene_list(path)
    message = str(info.value)
    assert "mesh file not found" in message and "--models DIR or DDSGEN_MODELS=DIR" in message
    assert "obj_000003.ply" in message and "\n" not in message


def test_the_models_variable_finds_a_mesh_by_its_file_name(tmp_path, monkeypatch):
    import trimesh

    models = tmp_path / "models"
    models.mkdir()
    trimesh.creation.box((40.0, 30.0, 20.0)).export(models / "obj_000003.ply")
    path = tmp_path / "s.yaml"
    path.write_text(yaml.safe_dump({"scenes": [{"objects": [{"mesh": "../nowhere/obj_000003.ply", "scale": 0.001}]}]}))
    monkeypatch.setenv("DDSGEN_MODELS", str(models))
    scene_list = load_scene_list(path)
    assert scene_list.scenes[0].objects[0].mesh_ref == str((models / "obj_000003.ply").resolve())
    assert [e.obj_id for e in scene_list.classes] == [3]
    monkeypatch.setenv("DDSGEN_MODELS", str(tmp_path / "absent"))
    with pytest.raises(InputError, match="DDSGEN_MODELS: .*absent: models folder not found"):
        load_scene_list(path)


# ------------------------------------------------------------------------------------------------ render --camera


def test_camera_option_sets_the_recorded_intrinsics(tmp_path):
    with written_inputs(tmp_path, tiny_preset_yaml(64, 48), tiny_scenes_yaml(frames=1, clutter=(1, 2))) as paths:
        out = tmp_path / "out"
        code = main(["render", paths[0], "--scenes", paths[1], "-n", "1", "--out", str(out), "--quiet",
                     "--no-preview", "--camera", "60,61.5,30.25,24.75"])  # fmt: skip
    assert code == 0
    (record,) = read_manifest(out / "manifest.jsonl")
    intr = record["intrinsics"]
    assert (intr["fx"], intr["fy"], intr["cx"], intr["cy"]) == (60.0, 61.5, 30.25, 24.75)
    saved = yaml.safe_load((out / "sensor.yaml").read_text())
    assert (saved["focal_px"], saved["focal_y_px"], saved["cx_px"], saved["cy_px"]) == (60.0, 61.5, 30.25, 24.75)
    # the poses project with those intrinsics: each visible object's box holds its projected origin's row band
    for obj in record["objects"]:
        t = np.asarray(obj["cam_T_obj"])[:3, 3]
        u = intr["fx"] * t[0] / t[2] + intr["cx"]
        x, y, w, h = obj["bbox"]
        if w and obj["visible_fraction"] > 0.9:
            assert x - 2 <= u <= x + w + 2


@pytest.mark.parametrize("value, fragment", [
    ("600,600,320", "--camera: expected four numbers fx,fy,cx,cy (px), got '600,600,320'"),
    ("a,b,c,d", "--camera: expected four numbers"),
    ("60,-1,30,24", "--camera: focal lengths must be > 0"),
    ("60,60,300,24", "--camera: principal point (300, 24) lies outside the 64x48 px image"),
])  # fmt: skip
def test_bad_camera_is_one_line_exit_2(tmp_path, capsys, value, fragment):
    with written_inputs(tmp_path, tiny_preset_yaml(64, 48), tiny_scenes_yaml(frames=1, clutter=(1, 2))) as paths:
        code = main(["render", paths[0], "--scenes", paths[1], "-n", "1", "--out", str(tmp_path / "out"),
                     "--quiet", "--camera", value])  # fmt: skip
    err = capsys.readouterr().err
    assert code == 2 and len(err.splitlines()) == 1 and fragment in err, err
    assert not (tmp_path / "out").exists()
