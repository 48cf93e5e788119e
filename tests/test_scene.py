"""Scene lists (validation, one-line errors), shapes, and frame sampling (determinism, physics of placement)."""

from __future__ import annotations

import copy
import math
from pathlib import Path

import numpy as np
import pytest
import yaml

from ddsgen.errors import InputError
from ddsgen.scene import load_scene_list, sample_frame
from ddsgen.scene.default_scenes import default_scene_list_dict
from ddsgen.scene.sampling import invert_pose
from ddsgen.scene.scenelist import scene_list_from_dict
from ddsgen.scene.shapes import SHAPES, make_shape, mesh_from_ref, shape_params, shape_ref

ROOT = Path(__file__).resolve().parent.parent
LINEMOD = ROOT.parent / "shared" / "data" / "linemod_bop" / "models"


def write(tmp_path: Path, data, name="scenes.yaml") -> Path:
    path = tmp_path / name
    path.write_text(data if isinstance(data, str) else yaml.safe_dump(data), encoding="utf-8")
    return path


def minimal(**scene) -> dict:
    base = {"objects": [{"shape": "box"}]}
    base.update(scene)
    return {"scenes": [base]}


# ------------------------------------------------------------------------------------------------ shapes


@pytest.mark.parametrize("name", sorted(SHAPES))
def test_shapes_are_metric_and_round_trip_through_their_reference(name):
    params = {k: p.default for k, p in shape_params(name).items()}
    mesh = make_shape(name, params)
    assert len(mesh.faces) > 0 and np.isfinite(mesh.vertices).all()
    assert 0.02 < mesh.extents.max() < 0.5  # metres, object-sized
    ref = shape_ref(name, params)
    again = mesh_from_ref(ref)
    np.testing.assert_allclose(again.vertices, mesh.vertices)


# ------------------------------------------------------------------------------------------------ scene lists


def test_builtin_default_needs_no_files_and_matches_scenes_default_yaml():
    builtin = load_scene_list(None)
    assert len(builtin.scenes) >= 2
    assert all(not o.mesh_ref.startswith("/") for s in builtin.scenes for o in s.objects)
    shipped = load_scene_list(ROOT / "scenes" / "default.yaml")
    assert shipped.scenes == builtin.scenes


def test_scene_for_frame_cycles_through_blocks():
    data = minimal(frames=2)
    data["scenes"].append({"objects": [{"shape": "sphere"}], "frames": 3})
    scene_list = scene_list_from_dict(data, "x.yaml")
    got = [scene_list.scene_for_frame(i) for i in range(12)]
    assert [g[0] for g in got] == [0, 0, 1, 1, 1, 0, 0, 1, 1, 1, 0, 0]
    assert [g[1] for g in got] == [0, 0, 2, 2, 2, 5, 5, 7, 7, 7, 10, 10]


@pytest.mark.skipif(not LINEMOD.is_dir(), reason=f"LineMOD models not present at {LINEMOD}")
def test_linemod_example_scene_list_loads_in_metres():
    scene_list = load_scene_list(ROOT / "scenes" / "linemod_objects.yaml")
    scene = sample_frame(scene_list, 0, seed=1)
    assert scene.objects
    for obj in scene.objects:
        assert Path(obj.mesh_ref).is_file() and obj.mesh_scale == 0.001
        assert 0.03 < obj.mesh.extents.max() < 0.3  # LineMOD objects are 4-26 cm


# ------------------------------------------------------------------------------------------------ errors


def expect_error(path: Path, *fragments: str) -> str:
    with pytest.raises(InputError) as info:
        load_scene_list(path)
    message = str(info.value)
    assert "\n" not in message
    assert message.startswith(str(path)), message
    for fragment in fragments:
        assert fragment in message, message
    return message


def test_unknown_key_names_nearest(tmp_path):
    data = minimal(camera={"distanse": [1, 2]})
    expect_error(write(tmp_path, data), "scenes[0].camera.distanse", "unknown key", "'distance'")
    data = minimal()
    data["scenes"][0]["objects"][0]["sise"] = [0.1, 0.1, 0.1]
    expect_error(write(tmp_path, data), "scenes[0].objects[0].sise", "'size'")
    expect_error(write(tmp_path, {"scene": []}), "scene:", "'scenes'")


def test_missing_mesh_file_is_named(tmp_path):
    data = {"scenes": [{"objects": [{"mesh": "models/nope.ply", "scale": 0.001}]}]}
    expect_error(write(tmp_path, data), "scenes[0].objects[0].mesh", "models/nope.ply", "not found")


@pytest.mark.parametrize(
    "text, key",
    [
        ("scenes: [{objects: [{shape: box, albedo: .nan}]}]", "scenes[0].objects[0].albedo"),
        ("scenes: [{objects: [box], camera: {distance: [0.5, .inf]}}]", "scenes[0].camera.distance[1]"),
        ("scenes: [{objects: [box], ground: {size: .nan}}]", "scenes[0].ground.size"),
    ],
)
def test_non_finite_numbers(tmp_path, text, key):
    expect_error(write(tmp_path, text), key, "finite")


@pytest.mark.parametrize(
    "text, fragments",
    [
        ("", ["empty"]),
        ("scenes: []", ["scenes", "non-empty"]),
        ("scenes: [{objects: []}]", ["scenes[0].objects", "non-empty"]),
        ("scenes: [{frames: 2}]", ["scenes[0].objects", "missing"]),
        ("scenes: [{objects: [box], frames: two}]", ["scenes[0].frames", "integer"]),
        ("scenes: [{objects: [box], frames: 0}]", ["scenes[0].frames", ">= 1"]),
        ("scenes: [{objects: [{shape: box, albedo: [0.9, 0.2]}]}]", ["albedo", "lo <= hi"]),
        ("scenes: [{objects: [{shape: box, albedo: 1.5}]}]", ["albedo", "<= 1"]),
        ("scenes: [{objects: [{shape: box, size: [0.1, 0.1]}]}]", ["size", "3 numbers"]),
        ("scenes: [{objects: [{shape: cube}]}]", ["objects[0].shape", "'cube'"]),
        ("scenes: [{objects: [{shape: torus, major_radius: 0.01, minor_radius: 0.02}]}]", ["minor_radius"]),
        ("scenes: [{objects: [{shape: box, mesh: a.ply}]}]", ["exactly one of"]),
        ("scenes: [{objects: [{shape: box, rest: sideways}]}]", ["rest", "stable"]),
        ("scenes: [{objects: [box], clutter: {count: [1, 2.5]}}]", ["clutter.count[1]", "integer"]),
        ("scenes: [{objects: [box], clutter: {count: [1, 3], unique: true}}]", ["clutter.count", "pool holds 1"]),
        ("scenes: [{objects: [box], camera: {elevation_deg: [10, 95]}}]", ["elevation_deg[1]", "<= 89"]),
        ("scenes: [{objects: [box], wall: {distance: 1}, camera: {azimuth_deg: [-180, 180]}}]", ["azimuth_deg", "wall"]),
        ("scenes: [{objects: [box], ground: null, floor: {depth: 0.7}}]", ["scenes[0].floor", "give a `ground`"]),
        ("scenes: [{objects: [box], floor: {depth: -0.7}}]", ["scenes[0].floor.depth", "> 0"]),
        ("scenes: [{objects: [box]}]\n  bad: [", ["malformed YAML"]),
        ("- just a list", ["mapping"]),
    ],
)
def test_bad_scene_lists_fail_with_one_line(tmp_path, text, fragments):
    expect_error(write(tmp_path, text), *fragments)


def test_missing_scene_list_file(tmp_path):
    expect_error(tmp_path / "absent.yaml", "not found")


def test_mesh_with_no_faces(tmp_path):
    ply = "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\nend_header\n"
    ply += "0 0 0\n1 0 0\n0 1 0\n"
    (tmp_path / "points.ply").write_text(ply)
    data = {"scenes": [{"objects": [{"mesh": "points.ply"}]}]}
    message = expect_error(write(tmp_path, data), "points.ply")
    assert "no faces" in message or "not a triangle mesh" in message


def test_non_mesh_files(tmp_path):
    (tmp_path / "notes.txt").write_text("hello")
    expect_error(write(tmp_path, {"scenes": [{"objects": [{"mesh": "notes.txt"}]}]}), "notes.txt", "not a mesh file")
    (tmp_path / "garbage.stl").write_bytes(b"\x00\x01garbage" * 7)
    message = expect_error(write(tmp_path, {"scenes": [{"objects": [{"mesh": "garbage.stl"}]}]}), "garbage.stl")
    assert "cannot read" in message or "no faces" in message or "not a triangle mesh" in message
    (tmp_path / "empty.obj").write_text("# nothing here\n")
    expect_error(write(tmp_path, {"scenes": [{"objects": [{"mesh": "empty.obj"}]}]}), "empty.obj")


def test_millimetre_model_without_scale_is_caught(tmp_path):
    import trimesh

    trimesh.creation.box(extents=[80.0, 60.0, 40.0]).export(tmp_path / "part_mm.stl")
    expect_error(write(tmp_path, {"scenes": [{"objects": [{"mesh": "part_mm.stl"}]}]}), "scale", "0.001")
    scene_list = load_scene_list(write(tmp_path, {"scenes": [{"objects": [{"mesh": "part_mm.stl", "scale": 0.001}]}]}))
    mesh = scene_list.scenes[0].objects[0].mesh()
    np.testing.assert_allclose(sorted(mesh.extents), [0.04, 0.06, 0.08])


# ------------------------------------------------------------------------------------------------ sampling


def scene_signature(scene):
    return (
        [(o.id, o.class_name, o.mesh_ref, o.albedo, o.world_T_obj.tobytes()) for o in scene.objects],
        [(b.class_name, b.albedo, b.world_T_obj.tobytes()) for b in scene.background],
        scene.world_T_cam.tobytes(),
    )


def test_same_seed_and_frame_give_identical_scene_in_any_order():
    scene_list = load_scene_list(None)
    forward = [scene_signature(sample_frame(scene_list, i, seed=7)) for i in range(10)]
    backward = [scene_signature(sample_frame(scene_list, i, seed=7)) for i in reversed(range(10))][::-1]
    assert forward == backward
    # a fresh copy of the scene list (as a worker process would unpickle it) gives the same scenes
    fresh = scene_list_from_dict(default_scene_list_dict(), "other")
    assert scene_signature(sample_frame(fresh, 6, seed=7)) == forward[6]
    assert scene_signature(sample_frame(scene_list, 6, seed=8)) != forward[6]


def test_frames_of_one_block_share_the_layout_but_not_the_camera():
    scene_list = load_scene_list(None)
    frames = scene_list.scenes[0].frames
    a, b = sample_frame(scene_list, 0, 3), sample_frame(scene_list, frames - 1, 3)
    assert scene_signature(a)[:2] == scene_signature(b)[:2]
    assert not np.allclose(a.world_T_cam, b.world_T_cam)
    c = sample_frame(scene_list, scene_list.cycle_length, 3)  # same scene template, next block
    assert scene_signature(a)[0] != scene_signature(c)[0]


def crowded_scene_list():
    data = copy.deepcopy(default_scene_list_dict())
    for scene in data["scenes"]:
        scene["frames"] = 1
        scene["clutter"] = {"count": [8, 12], "area": [0.45, 0.45], "min_gap": 0.0}
    data["scenes"][1]["wall"]["distance"] = 0.25
    return scene_list_from_dict(data, "crowded")


def world_vertices(obj, sample: int = 0, rng=None):
    import trimesh

    points = np.asarray(obj.mesh.vertices)
    if sample:  # hull vertices plus random surface points
        hull = np.asarray(obj.mesh.convex_hull.vertices)
        points = np.concatenate([hull, trimesh.sample.sample_surface(obj.mesh, sample, seed=rng)[0]])
    return points @ obj.world_T_obj[:3, :3].T + obj.world_T_obj[:3, 3]


def test_dropped_objects_rest_on_the_ground_without_interpenetration():
    from scipy.spatial import ConvexHull

    scene_list = crowded_scene_list()
    pairs = 0
    for frame_index in range(6):
        scene = sample_frame(scene_list, frame_index, seed=11)
        assert len(scene.objects) >= 4
        assert [o.id for o in scene.objects] == list(range(1, len(scene.objects) + 1))
        points = [world_vertices(o, sample=600, rng=frame_index) for o in scene.objects]
        for obj, pts in zip(scene.objects, points):
            assert abs(pts[:, 2].min()) < 1e-9, "resting on the ground plane z = 0"
            R = obj.world_T_obj[:3, :3]
            np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-9)
            assert np.linalg.det(R) == pytest.approx(1.0)
            if scene.scene_name == "against_wall":
                assert pts[:, 1].max() <= scene_list.scenes[1].wall.distance + 1e-9, "in front of the wall"
        hulls = [ConvexHull(p).equations for p in points]  # (F, 4): inside where n . x + c <= 0 for all faces
        for i in range(len(points)):
            for j in range(len(points)):
                if i != j:
                    pairs += 1
                    inside = (points[i] @ hulls[j][:, :3].T + hulls[j][:, 3] < -1e-9).all(axis=1)
                    assert not inside.any(), f"frame {frame_index}: object {i + 1} penetrates object {j + 1}"
    assert pairs > 60


def test_a_floor_below_makes_the_ground_a_table_that_objects_stay_on():
    # A 0.5 x 0.4 m table top with a drop area larger than it: no footprint may hang over an edge.
    pool = [{"shape": "box", "size": [0.12, 0.08, 0.06]}, {"shape": "cylinder", "radius": 0.04, "height": 0.12}]
    table = {"objects": pool, "frames": 1, "clutter": {"count": [6, 6], "area": [0.9, 0.9], "min_gap": 0.01},
             "ground": {"size": [0.5, 0.4], "albedo": 0.5}, "floor": {"depth": 0.72, "size": [4, 3], "albedo": 0.3},
             "wall": {"distance": 0.2, "width": 3, "height": 2}, "camera": {"azimuth_deg": [-60, 60]}}
    scene_list = scene_list_from_dict({"scenes": [table]})
    placed = 0
    for frame_index in range(8):
        scene = sample_frame(scene_list, frame_index, seed=3)
        for obj in scene.objects:
            pts = world_vertices(obj)
            assert np.all(np.abs(pts[:, 0]) <= 0.25 - 0.01 + 1e-9) and np.all(np.abs(pts[:, 1]) <= 0.2 - 0.01 + 1e-9)
            placed += 1
        floor = [b for b in scene.background if b.class_name == "floor"]
        assert len(floor) == 1 and floor[0].albedo == 0.3
        corners = np.asarray(floor[0].mesh.vertices) @ floor[0].world_T_obj[:3, :3].T + floor[0].world_T_obj[:3, 3]
        np.testing.assert_allclose(corners[:, 2], -0.72)
        np.testing.assert_allclose(np.ptp(corners[:, :2], axis=0), [4.0, 3.0])
        wall = next(b for b in scene.background if b.class_name == "wall")
        wall_z = np.asarray(wall.mesh.vertices) @ wall.world_T_obj[:3, :3].T + wall.world_T_obj[:3, 3]
        assert wall_z[:, 2].min() == pytest.approx(-0.72) and wall_z[:, 2].max() == pytest.approx(2.0 - 0.72)
    assert placed >= 8  # some objects fit; the rest were left out, not hung over the edge


def test_a_scene_list_without_a_floor_keeps_its_layouts():
    # The table-edge rule never triggers on a ground larger than the drop area, and the floor's albedo is drawn
    # after everything else: adding the floor key leaves the objects and the camera where they were.
    plain = default_scene_list_dict()
    plain["scenes"][0]["ground"] = {"size": [5.0, 5.0], "albedo": [0.4, 0.7]}  # endless, as before the table
    del plain["scenes"][0]["floor"], plain["scenes"][0]["distractors"]  # (those stand on the floor)
    with_floor = copy.deepcopy(plain)
    with_floor["scenes"][0]["floor"] = {"depth": 0.75}
    a, b = scene_list_from_dict(plain), scene_list_from_dict(with_floor)
    for frame_index in range(4):
        sa, sb = sample_frame(a, frame_index, seed=5), sample_frame(b, frame_index, seed=5)
        assert [o.class_name for o in sa.objects] == [o.class_name for o in sb.objects]
        for oa, ob in zip(sa.objects, sb.objects):
            np.testing.assert_array_equal(oa.world_T_obj, ob.world_T_obj)
        np.testing.assert_array_equal(sa.world_T_cam, sb.world_T_cam)
        assert len(sb.background) == len(sa.background) + 1


def test_camera_looks_at_the_clutter_from_the_sampled_distance_range():
    scene_list = load_scene_list(None)
    for frame_index in range(0, 24, 3):
        scene = sample_frame(scene_list, frame_index, seed=5)
        spec = scene_list.scenes[scene.scene_index].camera
        T = scene.world_T_cam
        R = T[:3, :3]
        np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-9)
        assert np.linalg.det(R) == pytest.approx(1.0)
        assert R[:, 1] @ [0.0, 0.0, 1.0] < 0, "image y points down in the world (no roll in the default)"
        assert T[2, 3] > 0.1, "camera above the ground"
        if scene.objects:
            corners = np.concatenate([world_vertices(o) for o in scene.objects])
            centre = (corners.min(axis=0) + corners.max(axis=0)) / 2
            in_cam = invert_pose(T) @ np.append(centre, 1.0)
            jitter = spec.look_at_jitter * math.sqrt(3)
            assert spec.distance[0] - jitter <= in_cam[2] <= spec.distance[1] + jitter
            assert math.hypot(in_cam[0], in_cam[1]) <= jitter + 1e-9, "optical axis through the clutter centre"
            assert 0.6 <= in_cam[2] <= 2.5, "Kinect working range"
            elevation = math.degrees(math.asin(np.clip(-R[2, 2], -1, 1)))
            assert spec.elevation_deg[0] - 5 <= elevation <= spec.elevation_deg[1] + 5


def test_albedo_ranges_are_respected_and_vary():
    scene_list = load_scene_list(None)
    albedos = {}
    for frame_index in range(0, 64, 4):
        for obj in sample_frame(scene_list, frame_index, seed=2).objects:
            spec = next(o for o in scene_list.scenes[0].objects if o.mesh_ref == obj.mesh_ref)
            assert spec.albedo[0] <= obj.albedo <= spec.albedo[1]
            albedos.setdefault(obj.class_name, set()).add(round(obj.albedo, 6))
    assert max(len(v) for v in albedos.values()) > 2
