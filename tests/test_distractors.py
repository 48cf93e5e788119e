"""Distractors (ddsgen/scene/distractors.py): unlabelled objects around the clutter, placed by the physics of a
room (on the floor off the table and below its top, or on the table apart from the clutter), drawn from their
own random stream, and seen by the ray cast as background."""

from __future__ import annotations

import copy
import re

import numpy as np
import pytest
from scipy.spatial import ConvexHull

from ddsgen.errors import InputError
from ddsgen.preset import load_preset
from ddsgen.raycast import cast
from ddsgen.scene import sample_frame
from ddsgen.scene.default_scenes import default_scene_list_dict
from ddsgen.scene.footprints import polygons_separated
from ddsgen.scene.scenelist import scene_list_from_dict

TABLETOP, AGAINST_WALL = 0, 1  # the built-in list's scenes (4 frames each)


def _world_vertices(placed) -> np.ndarray:
    vertices = np.asarray(placed.mesh.vertices, dtype=np.float64)
    return vertices @ placed.world_T_obj[:3, :3].T + placed.world_T_obj[:3, 3]


def _footprint(placed) -> np.ndarray:
    xy = _world_vertices(placed)[:, :2]
    return xy[ConvexHull(xy).vertices]


def _distractors(frame):
    return [b for b in frame.background if not b.mesh_ref.startswith("plane:")]


def _layouts(scene_list, scene_index: int, seeds=range(6)):
    """The first frame of the scene's first block, for several seeds (each a different layout)."""
    first = sum(s.frames for s in scene_list.scenes[:scene_index])
    return [sample_frame(scene_list, first, seed) for seed in seeds]


def test_distractors_are_unlabelled_and_leave_the_labelled_layout_and_the_camera_where_they_were():
    with_them = scene_list_from_dict(default_scene_list_dict())
    plain = default_scene_list_dict()
    for scene in plain["scenes"]:
        del scene["distractors"]
    without = scene_list_from_dict(plain)
    n_distractors = 0
    for frame_index in range(8):
        a, b = sample_frame(without, frame_index, seed=3), sample_frame(with_them, frame_index, seed=3)
        assert [(o.id, o.class_name) for o in a.objects] == [(o.id, o.class_name) for o in b.objects]
        for oa, ob in zip(a.objects, b.objects):
            np.testing.assert_array_equal(oa.world_T_obj, ob.world_T_obj)
        np.testing.assert_array_equal(a.world_T_cam, b.world_T_cam)
        assert [p.albedo for p in a.background] == [p.albedo for p in b.background[: len(a.background)]]
        extra = b.background[len(a.background):]
        assert extra == _distractors(b)
        assert all(d.id == 0 for d in extra)
        n_distractors += len(extra)
    assert n_distractors >= 8 * 3  # the built-in groups draw 4-8 and 4-7 per layout (a few may find no room)


@pytest.mark.parametrize("area", [None, [2.2, 1.8]])  # the built-in region, and one hugging the table
def test_floor_distractors_stand_on_the_floor_off_the_table_and_below_its_top(area):
    data = default_scene_list_dict()
    if area is not None:
        data["scenes"][TABLETOP]["distractors"][0]["area"] = area
    scene_list = scene_list_from_dict(data)
    spec = scene_list.scenes[TABLETOP]
    group = spec.distractors[0]
    half_table = np.asarray(spec.ground.size) / 2.0
    table = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]]) * half_table
    seen = 0
    for frame in _layouts(scene_list, TABLETOP):
        for d in _distractors(frame):
            z = _world_vertices(d)[:, 2]
            assert z.min() == pytest.approx(-spec.floor.depth, abs=1e-6)  # resting on the floor
            assert z.max() < 0.0  # below the table top: never between a camera above it and the table
            footprint = _footprint(d)
            assert polygons_separated(footprint, table, group.min_gap - 1e-9)
            assert np.all(np.abs(footprint) <= np.asarray(spec.floor.size) / 2.0)
            assert 0.05 <= d.albedo <= 0.8
            seen += 1
    assert seen >= 6 * 2


def test_ground_distractors_stand_on_the_table_apart_from_the_clutter_and_in_front_of_the_wall():
    scene_list = scene_list_from_dict(default_scene_list_dict())
    spec = scene_list.scenes[AGAINST_WALL]
    group = spec.distractors[0]
    seen = 0
    for frame in _layouts(scene_list, AGAINST_WALL):
        distractors = _distractors(frame)
        footprints = [_footprint(d) for d in distractors]
        for d, footprint in zip(distractors, footprints):
            assert _world_vertices(d)[:, 2].min() == pytest.approx(0.0, abs=1e-6)  # on the table top
            assert footprint[:, 1].max() <= spec.wall.distance - group.min_gap + 1e-9
            assert np.all(np.abs(footprint) <= np.asarray(spec.ground.size) / 2.0)
            for obj in frame.objects:
                assert polygons_separated(footprint, _footprint(obj), group.min_gap - 1e-6)
            seen += 1
        for i in range(len(footprints)):
            for j in range(i):
                assert polygons_separated(footprints[i], footprints[j], group.min_gap - 1e-6)
    assert seen >= 6 * 3


def test_the_ray_cast_sees_distractors_as_background_with_depth():
    scene_list = scene_list_from_dict(default_scene_list_dict())
    preset = load_preset("kinect_v1")
    intrinsics = preset.intrinsics
    covered = 0
    for frame_index in (4, 5, 6, 7):  # against the wall: the back row faces the camera
        frame = sample_frame(scene_list, frame_index, seed=0)
        hits = cast(frame, intrinsics, preset.baseline_m, preset.shadow_bias_m, shadows=False)
        first_distractor = len(frame.objects) + len(frame.background) - len(_distractors(frame))
        on_distractor = hits.owner >= first_distractor
        assert np.all(hits.instance[on_distractor] == 0)
        assert np.all(hits.depth[on_distractor] > 0)
        covered += int(on_distractor.sum())
    assert covered > 0.01 * 4 * intrinsics.width * intrinsics.height


@pytest.mark.parametrize(
    "group, problem",
    [
        ({"surface": "shelf", "objects": ["box"]}, "scenes[0].distractors[0].surface: expected one of floor, ground"),
        ({"objects": ["box"]}, "scenes[0].distractors[0].surface: expected one of floor, ground"),
        ({True: "floor", "objects": ["box"]}, "scenes[0].distractors[0]: YAML reads the key `on` as true"),
        ({"surface": "floor", "objects": []}, "scenes[0].distractors[0].objects: expected a non-empty list"),
        ({"surface": "floor", "count": [5, 2], "objects": ["box"]}, "scenes[0].distractors[0].count: range"),
        ({"surface": "floor", "centre": [1.0], "objects": ["box"]}, "scenes[0].distractors[0].centre: expected a list"),
        ({"surface": "floor", "objects": [{"shape": "boxx"}]}, "scenes[0].distractors[0].objects[0].shape: unknown"),
    ],
)
def test_a_bad_distractor_group_names_its_key(group, problem):
    data = default_scene_list_dict()
    data["scenes"][0]["distractors"] = [group]
    with pytest.raises(InputError, match=r"^scenes\.yaml: " + re.escape(problem)):
        scene_list_from_dict(data, source="scenes.yaml")


def test_floor_distractors_need_a_floor():
    data = copy.deepcopy(default_scene_list_dict())
    del data["scenes"][0]["floor"]
    with pytest.raises(InputError, match=r"scenes\[0\]\.distractors\[0\]\.surface: distractors on the floor need"):
        scene_list_from_dict(data, source="scenes.yaml")
