"""Physics of the ray caster: z-depth, normals, projector shadows, instance masks and labels; every test runs
with the C raster (when a compiler is there) and with Embree alone (a machine without one)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import trimesh

from ddsgen.preset import Intrinsics
from ddsgen.raycast import cast, object_labels, ray_directions
from ddsgen.scene.sampling import FrameScene, PlacedObject, invert_pose, sample_frame
from ddsgen.scene.scenelist import load_scene_list
from ddsgen.scene.shapes import make_shape, plane_mesh

@pytest.fixture(autouse=True, params=["raster", "embree"])
def caster(request, monkeypatch):
    """Which path casts the meshes: the C raster (ddsgen/raster.py) or Embree (ddsgen/raycast_embree.py)."""
    import ddsgen.raster as raster

    if request.param == "raster" and not raster.raster_available():
        pytest.skip("no C compiler: the raster is not built")
    if request.param == "embree":
        monkeypatch.setattr(raster, "_library", lambda: None)
    return request.param


K_SMALL = Intrinsics(width=64, height=48, fx=50.0, fy=52.0, cx=31.5, cy=23.5)
K_MID = Intrinsics(width=320, height=240, fx=300.0, fy=300.0, cx=159.5, cy=119.5)


def pose(rotation=None, translation=(0.0, 0.0, 0.0)) -> np.ndarray:
    T = np.eye(4)
    if rotation is not None:
        T[:3, :3] = rotation
    T[:3, 3] = translation
    return T


def rot_x(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def frame(objects=(), background=(), world_T_cam=None) -> FrameScene:
    return FrameScene(list(objects), list(background), np.eye(4) if world_T_cam is None else world_T_cam, 0, 0)


def fine_plane(size: float, n: int = 12) -> trimesh.Trimesh:
    """A plane of many triangles: not treated as an analytic polygon, goes through Embree."""
    mesh = plane_mesh(size, size)
    return mesh.subdivide().subdivide().subdivide() if n else mesh


def placed_plane(mesh, T, as_object: bool, albedo=0.5):
    if as_object:
        return PlacedObject(1, "plane", "plane", mesh, T, albedo), None
    return None, PlacedObject(0, "wall", "plane", mesh, T, albedo)


def scene_with(obj, bg, world_T_cam=None):
    return frame([obj] if obj else [], [bg] if bg else [], world_T_cam)


# ------------------------------------------------------------------------------------------------ depth and normals


@pytest.mark.parametrize("as_object", [False, True], ids=["analytic-plane", "embree-mesh"])
@pytest.mark.parametrize("z", [0.5, 1.3, 3.7])
def test_fronto_parallel_plane_gives_z_not_ray_length(z, as_object):
    mesh = fine_plane(40.0) if as_object else plane_mesh(40.0, 40.0)
    obj, bg = placed_plane(mesh, pose(translation=(0.0, 0.0, z)), as_object)
    hits = cast(scene_with(obj, bg), K_SMALL, baseline_m=0.075, shadow_bias_m=0.005)
    assert hits.hit.all()
    np.testing.assert_allclose(hits.depth, z, rtol=2e-6)
    np.testing.assert_allclose(hits.points[..., 2], hits.depth, rtol=1e-6)
    # corners: the ray is longer than z by sqrt(1 + x'^2 + y'^2)
    d = ray_directions(K_SMALL)
    length = np.linalg.norm(hits.points, axis=-1)
    np.testing.assert_allclose(length, z * np.linalg.norm(d, axis=-1), rtol=2e-6)
    assert length[0, 0] > hits.depth[0, 0] * 1.2  # corner ray 26 % longer than z
    # hit points reproject to the integer pixel centres (OpenCV convention)
    u = K_SMALL.fx * hits.points[..., 0] / hits.points[..., 2] + K_SMALL.cx
    v = K_SMALL.fy * hits.points[..., 1] / hits.points[..., 2] + K_SMALL.cy
    np.testing.assert_allclose(u, np.arange(K_SMALL.width)[None, :] + 0 * v, atol=1e-3)
    np.testing.assert_allclose(v, np.arange(K_SMALL.height)[:, None] + 0 * u, atol=1e-3)
    np.testing.assert_allclose(hits.normals, np.broadcast_to([0.0, 0.0, -1.0], hits.normals.shape), atol=1e-6)
    assert not hits.shadow.any()
    assert hits.instance.dtype == np.uint16 and hits.depth.dtype == np.float32
    np.testing.assert_array_equal(hits.instance, 1 if as_object else 0)
    np.testing.assert_allclose(hits.albedo, 0.5)


@pytest.mark.parametrize("as_object", [False, True], ids=["analytic-plane", "embree-mesh"])
@pytest.mark.parametrize("tilt_deg", [-50.0, 20.0, 45.0])
def test_tilted_plane_normals_and_depth(tilt_deg, as_object):
    z0 = 1.5
    R = rot_x(math.radians(tilt_deg))
    mesh = fine_plane(20.0) if as_object else plane_mesh(20.0, 20.0)
    obj, bg = placed_plane(mesh, pose(R, (0.0, 0.0, z0)), as_object)
    hits = cast(scene_with(obj, bg), K_SMALL, 0.075, 0.005)
    normal = R @ np.array([0.0, 0.0, 1.0])
    normal = -normal if normal[2] > 0 else normal  # towards the camera at the origin
    assert hits.hit.all()
    np.testing.assert_allclose(hits.normals, np.broadcast_to(normal, hits.normals.shape), atol=1e-5)
    np.testing.assert_allclose(np.linalg.norm(hits.normals, axis=-1), 1.0, atol=1e-6)
    d = ray_directions(K_SMALL).astype(np.float64)
    expected_z = (normal @ [0.0, 0.0, z0]) / (d @ normal)  # t along d (z = 1) is the depth
    np.testing.assert_allclose(hits.depth, expected_z, rtol=1e-5)
    assert (np.einsum("hwc,hwc->hw", hits.normals, d) < 0).all()


def test_nothing_in_view_is_no_hit():
    mesh = plane_mesh(1.0, 1.0)
    behind = PlacedObject(0, "wall", "plane", mesh, pose(translation=(0.0, 0.0, -2.0)), 0.5)
    hits = cast(frame(background=[behind]), K_SMALL, 0.075, 0.005)
    assert not hits.hit.any() and not hits.shadow.any()
    assert (hits.depth == 0).all() and (hits.normals == 0).all() and (hits.instance == 0).all()


# ------------------------------------------------------------------------------------------------ projector shadow


@pytest.mark.parametrize("occluder_as_box", [False, True])
def test_shadow_band_lies_away_from_projector_with_geometric_width(occluder_as_box):
    """Projector at +x: an occluder's shadow on the wall behind it shows on its -x (left) side, f*b*(1/zo - 1/zw) px wide.

    A wall point X_w is shadowed if the segment X_w -> projector (b, 0, 0) crosses the occluder (x in [x0, x1] at
    depth zo); seen from the camera those points lie at u in [cx + f*(b/zw + (x0 - b)/zo), cx + f*(b/zw + (x1 - b)/zo)],
    i.e. the occluder's own image interval shifted by -f*b*(1/zo - 1/zw): the visible part is on its left.
    """
    b, zo, zw, f = 0.075, 1.0, 2.0, K_MID.fx
    x0, x1 = -0.05, 0.15
    wall = PlacedObject(0, "wall", "plane", plane_mesh(20.0, 20.0), pose(translation=(0.0, 0.0, zw)), 0.5)
    if occluder_as_box:
        mesh = trimesh.creation.box(extents=[x1 - x0, 0.4, 0.02])
        T = pose(translation=((x0 + x1) / 2, 0.0, zo + 0.01))  # front face at z = zo
    else:
        mesh = fine_plane(1.0)
        mesh.apply_scale([x1 - x0, 0.4, 1.0])
        T = pose(translation=((x0 + x1) / 2, 0.0, zo))
    occluder = PlacedObject(1, "card", "card", mesh, T, 0.5)
    hits = cast(frame([occluder], [wall]), K_MID, baseline_m=b, shadow_bias_m=0.005)

    assert hits.hit.all()
    assert not (hits.shadow & (hits.instance == 1)).any(), "the occluder's front face is lit"
    rows = np.flatnonzero((hits.instance == 1).any(axis=1))
    shadow_rows = np.flatnonzero(hits.shadow.any(axis=1))
    assert set(shadow_rows) <= set(range(rows.min() - 1, rows.max() + 2)), "shadow rows = occluder rows (epipolar)"
    predicted_width = f * b * (zw - zo) / (zo * zw)
    assert predicted_width == pytest.approx(11.25)
    left_edge = K_MID.cx + f * (b / zw + (x0 - b) / zo)
    occluder_left = K_MID.cx + f * x0 / zo
    for v in rows[2:-2]:
        cols = np.flatnonzero(hits.shadow[v])
        occ = np.flatnonzero(hits.instance[v] == 1)
        assert cols.size and cols.max() < occ.min(), "shadow on the -x side (away from the projector)"
        assert cols.max() == occ.min() - 1, "band touches the occluder"
        assert np.all(np.diff(cols) == 1), "one contiguous band"
        expected = np.arange(math.ceil(left_edge - 0.05), math.ceil(occluder_left - 0.05))
        assert abs(cols.size - predicted_width) <= 1.0
        assert abs(cols.min() - expected.min()) <= 1


def test_surface_facing_away_from_projector_is_shadowed():
    # A plane tilted so steeply that the camera sees its front but the projector (at +x) sees its back.
    b = 0.2
    # plane through (0, 0, 1) containing the direction towards the point halfway between camera and projector
    n = np.array([1.0, 0.0, 0.1])
    n /= np.linalg.norm(n)
    # camera at origin sees side where n.(0 - p0) has sign s; projector sees side sign of n.(b,0,0) - n.p0
    p0 = np.array([0.01, 0.0, 1.0])
    assert (n @ (np.zeros(3) - p0)) * (n @ (np.array([b, 0, 0]) - p0)) < 0, "test geometry: opposite sides"
    z = np.array([0.0, 0.0, 1.0])
    axis = np.cross(z, n)
    angle = math.acos(float(z @ n))
    R = trimesh.transformations.rotation_matrix(angle, axis)[:3, :3]
    wall = PlacedObject(0, "wall", "plane", plane_mesh(0.3, 0.3), pose(R, p0), 0.5)
    hits = cast(frame(background=[wall]), K_SMALL, baseline_m=b, shadow_bias_m=0.0)
    assert hits.hit.any()
    assert hits.shadow[hits.hit].all()


# ------------------------------------------------------------------------------------------------ masks and labels


def two_boxes_scene():
    """A front box hiding the right half of a back box, a wall behind, and one object out of view."""
    wall = PlacedObject(0, "wall", "plane", plane_mesh(20.0, 20.0), pose(translation=(0.0, 0.0, 3.0)), 0.7)
    back = PlacedObject(1, "back", "shape:box", make_shape("box", {"size": (0.4, 0.4, 0.05)}),
                        pose(translation=(0.0, 0.0, 2.0)), 0.4)
    front = PlacedObject(2, "front", "shape:box", make_shape("box", {"size": (0.4, 0.5, 0.05)}),
                         pose(rot_x(0.0), (0.2, 0.0, 1.2)), 0.9)  # left edge at x = 0
    away = PlacedObject(3, "away", "shape:sphere", make_shape("sphere"), pose(translation=(0.0, 0.0, -1.0)), 0.5)
    # camera slightly moved: world_T_cam not identity
    world_T_cam = pose(rot_x(0.02), (0.01, -0.02, 0.0))
    return frame([back, front, away], [wall], world_T_cam)


def test_instance_mask_matches_per_object_hits_and_depth():
    scene = two_boxes_scene()
    hits = cast(scene, K_MID, 0.075, 0.005)
    alone = {o.id: cast(frame([o], [], scene.world_T_cam), K_MID, 0.075, 0.005) for o in scene.objects}
    wall_alone = cast(frame([], scene.background, scene.world_T_cam), K_MID, 0.075, 0.005)
    stack = np.stack([np.where(wall_alone.hit, wall_alone.depth, np.inf)]
                     + [np.where(a.hit, a.depth, np.inf) for a in alone.values()])
    nearest = np.argmin(stack, axis=0)
    expected = np.array([0] + list(alone))[nearest].astype(np.uint16)
    np.testing.assert_array_equal(hits.instance, expected)
    np.testing.assert_allclose(hits.depth, stack.min(axis=0), rtol=1e-6)
    for oid, a in alone.items():
        mask = hits.instance == oid
        assert np.all(a.hit[mask]), "every mask pixel is a hit of that object"
        np.testing.assert_allclose(hits.depth[mask], a.depth[mask], rtol=1e-6)
    assert (hits.albedo[hits.instance == 2] == np.float32(0.9)).all()


def test_labels_bbox_and_visible_fraction_agree_with_mask():
    scene = two_boxes_scene()
    hits = cast(scene, K_MID, 0.075, 0.005)
    labels = {entry["id"]: entry for entry in object_labels(scene, hits, K_MID)}
    assert sorted(labels) == [1, 2, 3]
    for oid in (1, 2):
        mask = hits.instance == oid
        rows, cols = np.nonzero(mask)
        x, y = cols.min(), rows.min()
        assert labels[oid]["bbox"] == [x, y, cols.max() - x + 1, rows.max() - y + 1]
        alone = cast(frame([o for o in scene.objects if o.id == oid], [], scene.world_T_cam), K_MID, 0.075, 0.005)
        assert labels[oid]["visible_fraction"] == pytest.approx(mask.sum() / alone.hit.sum(), abs=1e-12)
        placed = next(o for o in scene.objects if o.id == oid)
        np.testing.assert_allclose(labels[oid]["cam_T_obj"], invert_pose(scene.world_T_cam) @ placed.world_T_obj)
        assert labels[oid]["mesh"] == placed.mesh_ref and labels[oid]["class"] == placed.class_name
    assert labels[2]["visible_fraction"] == 1.0
    # the front box covers about the right half of the back box
    assert 0.35 < labels[1]["visible_fraction"] < 0.65
    assert labels[3]["visible_fraction"] == 0.0 and labels[3]["bbox"] == [0, 0, 0, 0]


# ------------------------------------------------------------------------------------------------ against a brute-force reference


def reference_cast(scene, intrinsics, b, xi):
    """All geometry in one Embree scene, every ray cast, no culls: what :func:`cast` must reproduce."""
    from embreex import rtcore_scene
    from embreex.mesh_construction import TriangleMesh

    cam_T_world = invert_pose(scene.world_T_cam)
    placed = list(scene.objects) + list(scene.background)
    embree = rtcore_scene.EmbreeScene()
    for p in placed:
        T = cam_T_world @ p.world_T_obj
        v = (np.asarray(p.mesh.vertices) @ T[:3, :3].T + T[:3, 3]).astype(np.float32)
        TriangleMesh(embree, v, np.asarray(p.mesh.faces, dtype=np.int32))
    d = ray_directions(intrinsics).reshape(-1, 3)
    r = embree.run(np.zeros_like(d), d, output=1)
    hit = r["geomID"] >= 0
    ids = np.array([p.id for p in placed])
    instance = np.where(hit, ids[np.maximum(r["geomID"], 0)], 0)
    depth = np.where(hit, r["tfar"], 0.0)
    n = r["Ng"] / np.maximum(np.linalg.norm(r["Ng"], axis=1, keepdims=True), 1e-30)
    n *= -np.sign(np.einsum("ij,ij->i", n, d))[:, None]
    points = d * depth[:, None]
    start = (points + xi * n).astype(np.float32)
    proj = np.array([b, 0.0, 0.0], dtype=np.float32)
    occ = embree.run(start, proj - start, dists=np.full(len(d), 1 - 1e-6, np.float32), query="OCCLUDED") >= 0
    back = np.einsum("ij,ij->i", n, proj - points) <= 0
    shadow = hit & (occ | back)
    shape = (intrinsics.height, intrinsics.width)
    return instance.reshape(shape), depth.reshape(shape), shadow.reshape(shape), n.reshape(shape + (3,))


def test_cast_matches_brute_force_reference_on_sampled_scenes():
    scene_list = load_scene_list(None)
    K = Intrinsics(width=160, height=120, fx=143.1, fy=143.1, cx=79.5, cy=59.5)
    for frame_index in (0, 5, 9):
        scene = sample_frame(scene_list, frame_index, seed=3)
        hits = cast(scene, K, 0.075, 0.005)
        instance, depth, shadow, normals = reference_cast(scene, K, 0.075, 0.005)
        assert (hits.instance != instance).mean() < 2e-3  # float ties at silhouettes only
        same = hits.instance == instance
        np.testing.assert_allclose(hits.depth[same], depth[same], rtol=1e-4, atol=1e-5)
        assert (hits.shadow != shadow)[same].mean() < 2e-3
        assert hits.shadow.sum() > 0 or shadow.sum() == 0
        np.testing.assert_allclose(np.linalg.norm(hits.normals[hits.hit], axis=-1), 1.0, atol=1e-5)
        assert (np.einsum("hwc,hwc->hw", hits.normals, ray_directions(K))[hits.hit] < 0).all()
        assert set(np.unique(hits.instance)) <= {0} | {o.id for o in scene.objects}


def test_labels_without_cached_coverage_cast_the_object_alone():
    scene = two_boxes_scene()
    hits = cast(scene, K_MID, 0.075, 0.005)
    with_cache = object_labels(scene, hits, K_MID)
    hits.coverage = {}
    assert object_labels(scene, hits, K_MID) == with_cache


def test_a_flat_board_object_casts_without_numpy_warnings():
    """A flat mesh as an object (the noise study's board) has a hull without volume; casting it must not print
    numpy's 'invalid value encountered in divide' from trimesh's centre of mass to the user's terminal."""
    import warnings

    board = PlacedObject(1, "board", "plane", plane_mesh(0.5, 0.4), pose(translation=(0.0, 0.0, 1.0)), 0.8)
    with warnings.catch_warnings(record=True) as caught:  # recorded, not raised: cast() catches exceptions there
        warnings.simplefilter("always")
        hits = cast(frame(objects=[board]), K_SMALL, 0.075, 0.005)
    assert [str(w.message) for w in caught] == []
    assert hits.hit.any() and np.allclose(hits.depth[hits.hit], 1.0, atol=1e-5)


def test_a_cast_widened_by_the_ir_margin_splits_into_the_image_and_the_strip_cast_alone():
    """A registered device's IR view is cast once, widened by the margin strip (cast_widened): its columns are
    pixel for pixel what the image and the strip give when each is cast on its own."""
    from ddsgen.sensor.ir_margin import cast_widened, margin_intrinsics

    K = Intrinsics(width=160, height=120, fx=143.1, fy=143.1, cx=79.5, cy=59.5)
    scene = sample_frame(load_scene_list(None), 2, seed=4)
    wide = cast_widened(scene, K, 6, 0.075, 0.005)
    image, strip = wide.columns(0, 160), wide.columns(160, 166)
    alone = {"image": cast(scene, K, 0.075, 0.005), "strip": cast(scene, margin_intrinsics(K, 6), 0.075, 0.005)}
    for name, part in (("image", image), ("strip", strip)):
        for field in ("depth", "points", "normals", "instance", "hit", "shadow", "albedo", "owner", "triangle",
                      "barycentric"):  # fmt: skip
            np.testing.assert_array_equal(getattr(part, field), getattr(alone[name], field), err_msg=f"{name} {field}")
    assert strip.hit.any() and strip.shadow.shape == (120, 6)
    assert cast_widened(scene, K, 0, 0.075, 0.005).depth.shape == (120, 160)


def test_a_widened_cast_becomes_the_sensor_geometry_and_its_margin_without_a_copy():
    """SensorGeometry.from_hits(wide, width=W): the same tensors as the image and the strip handed over apart; the
    whole IR image comes back without a concatenation, and a replaced field is never hidden by it."""
    import dataclasses

    import torch

    from ddsgen.sensor.geometry import SensorGeometry
    from ddsgen.sensor.ir_margin import cast_widened

    K = Intrinsics(width=160, height=120, fx=143.1, fy=143.1, cx=79.5, cy=59.5)
    wide = cast_widened(sample_frame(load_scene_list(None), 2, seed=4), K, 6, 0.075, 0.005)
    viewed = SensorGeometry.from_hits(wide, width=160)
    apart = SensorGeometry.from_hits(wide.columns(0, 160), ir_margin=wide.columns(160, 166))
    whole, concatenated = viewed.with_ir_margin(), apart.with_ir_margin()
    for name in SensorGeometry._FIELDS:
        assert torch.equal(getattr(viewed, name), getattr(apart, name)), name
        assert torch.equal(getattr(viewed.ir_margin, name), getattr(apart.ir_margin, name)), name
        assert torch.equal(getattr(whole, name), getattr(concatenated, name)), name
    assert whole.points.data_ptr() == viewed.points.data_ptr()  # views of one tensor: nothing copied
    moved = dataclasses.replace(viewed, points=viewed.points + 1.0)
    assert torch.equal(moved.with_ir_margin().points[:, :160], viewed.points + 1.0)
    assert torch.equal(moved.with_ir_margin().points[:, 160:], viewed.ir_margin.points)
