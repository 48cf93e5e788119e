"""The C raster (ddsgen/raster.py, csrc/raster.c) against Embree: the same primary hits, shadows and coverage,
including meshes that reach behind the camera and points spread far apart in the projector's image."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

import ddsgen.raster as raster
from ddsgen.preset import Intrinsics
from ddsgen.raycast import _alone_pixel_count, cast, ray_directions
from ddsgen.scene.sampling import FrameScene, PlacedObject, invert_pose, sample_frame
from ddsgen.scene.scenelist import load_scene_list
from ddsgen.scene.shapes import plane_mesh

K = Intrinsics(width=160, height=120, fx=143.1, fy=143.1, cx=79.5, cy=59.5)

pytestmark = pytest.mark.skipif(not raster.raster_available(), reason="no C compiler: the raster is not built")


@pytest.fixture
def embree_only(monkeypatch):
    """Cast as on a machine without a C compiler: Embree takes every ray."""
    monkeypatch.setattr(raster, "_library", lambda: None)


def _cast_both(scene, intrinsics, monkeypatch, shadows=True):
    with_raster = cast(scene, intrinsics, 0.075, 0.005, shadows=shadows)
    with monkeypatch.context() as patch:
        patch.setattr(raster, "_library", lambda: None)
        with_embree = cast(scene, intrinsics, 0.075, 0.005, shadows=shadows)
    return with_raster, with_embree


def _hit_points_from_barycentrics(scene, hits) -> np.ndarray:
    """(N, 3) camera-frame points P = (1 - u - v) V0 + u V1 + v V2 of the mesh hits, from owner / triangle /
    barycentric (what ddsgen.scene_gradients recomputes), and the (N,) flat pixel indices."""
    placed = list(scene.objects) + list(scene.background)
    cam_T_world = invert_pose(scene.world_T_cam)
    owner, triangle, bary = hits.owner.reshape(-1), hits.triangle.reshape(-1), hits.barycentric.reshape(-1, 2)
    points, pixels = [], []
    for k, p in enumerate(placed):
        where = np.flatnonzero(owner == k)
        if not len(where) or len(p.mesh.faces) <= 2:  # analytic planes report face 0, no barycentrics
            continue
        T = cam_T_world @ p.world_T_obj
        v = np.asarray(p.mesh.vertices) @ T[:3, :3].T + T[:3, 3]
        tri = v[np.asarray(p.mesh.faces)[triangle[where]]]
        u, w = bary[where, 0:1].astype(np.float64), bary[where, 1:2].astype(np.float64)
        points.append((1 - u - w) * tri[:, 0] + u * tri[:, 1] + w * tri[:, 2])
        pixels.append(where)
    return np.concatenate(points), np.concatenate(pixels)


@pytest.mark.parametrize("frame_index", [0, 4, 9])
def test_raster_gives_embrees_hits_shadows_and_coverage_on_sampled_scenes(frame_index, monkeypatch):
    scene = sample_frame(load_scene_list(None), frame_index, seed=3)
    fast, slow = _cast_both(scene, K, monkeypatch)
    assert np.array_equal(fast.hit, slow.hit)
    assert (fast.owner != slow.owner).mean() < 1e-3  # ties at silhouettes only
    same = fast.owner == slow.owner
    np.testing.assert_allclose(fast.depth[same], slow.depth[same], rtol=2e-5, atol=1e-6)
    assert (fast.shadow != slow.shadow).mean() < 1e-3
    assert fast.shadow.sum() > 100  # the scenes do cast shadows
    np.testing.assert_allclose(fast.normals[same], slow.normals[same], atol=2e-3)
    assert fast.coverage.keys() == slow.coverage.keys()
    for key, alone in slow.coverage.items():
        assert abs(fast.coverage[key] - alone) <= 2
    # The barycentrics put the hit on the ray at the reported depth (what scene_gradients relies on).
    points, pixels = _hit_points_from_barycentrics(scene, fast)
    expected = ray_directions(K).reshape(-1, 3)[pixels] * fast.depth.reshape(-1)[pixels, None]
    np.testing.assert_allclose(points, expected, atol=2e-5)


def test_a_mesh_reaching_behind_the_camera_is_cast_where_it_is_in_front(monkeypatch):
    """A tiled floor under the camera from 2 m behind it to 10 m ahead: its triangles crossing the camera
    plane are clipped, not dropped. Depth of a plane y = h at pixel row v: z = h fy / (v - cy)."""
    floor = plane_mesh(2.0, 12.0).subdivide().subdivide().subdivide()  # 256 faces: a mesh, not a polygon
    T = np.eye(4)
    T[:3, :3] = [[1, 0, 0], [0, 0, 1], [0, -1, 0]]  # the plane's normal (0, 0, 1) -> (0, -1, 0), facing up
    T[:3, 3] = [0.0, 0.4, 4.0]  # 0.4 m below the camera (camera y points down), z from -2 to 10 m
    scene = FrameScene([PlacedObject(1, "floor", "plane", floor, T, 0.5)], [], np.eye(4), 0, 0)
    fast, slow = _cast_both(scene, K, monkeypatch)
    rows = np.arange(K.height)
    below = rows > K.cy + 0.4 * K.fy / 10.0 + 1  # rows that see the floor nearer than 10 m
    expected = 0.4 * K.fy / (rows - K.cy)
    centre = K.width // 2
    np.testing.assert_allclose(fast.depth[below, centre], expected[below], rtol=1e-5)
    assert fast.hit[below, centre].all() and not fast.hit[rows < K.cy, centre].any()
    assert np.array_equal(fast.hit, slow.hit)
    np.testing.assert_allclose(fast.depth, slow.depth, rtol=1e-5, atol=1e-6)
    assert fast.coverage[1] == slow.coverage[1] == int(fast.hit.sum())


def test_coverage_counts_an_occluded_object_as_if_alone(monkeypatch):
    """A small box half behind a bigger one: its visible pixels are fewer than the pixels it covers alone,
    which the raster counts as Embree does (one cast of the object on its own)."""
    near = PlacedObject(1, "box", "box", trimesh.creation.box((0.3, 0.3, 0.3)), np.eye(4), 0.5)
    near.world_T_obj[:3, 3] = [-0.1, 0.0, 1.0]
    far = PlacedObject(2, "box", "box", trimesh.creation.box((0.3, 0.3, 0.3)), np.eye(4), 0.5)
    far.world_T_obj[:3, 3] = [0.1, 0.0, 1.6]
    scene = FrameScene([near, far], [], np.eye(4), 0, 0)
    hits = cast(scene, K, 0.075, 0.005)
    visible = int((hits.instance == 2).sum())
    alone = _alone_pixel_count(far, np.eye(4), K)
    assert 0 < visible < alone - 50
    assert abs(hits.coverage[2] - alone) <= 1 and abs(hits.coverage[1] - int((hits.instance == 1).sum())) <= 1


def test_shadow_segments_spread_far_apart_match_embree():
    """Points whose projector-image positions are thousands of pixels apart make the bucket grid coarsen
    (at most 4 cells per point); the answers stay the ones of a capped Embree occlusion ray per segment."""
    from embreex import rtcore_scene
    from embreex.mesh_construction import TriangleMesh

    rng = np.random.default_rng(5)
    mesh = trimesh.creation.icosphere(2, radius=0.2)
    vertices = (np.asarray(mesh.vertices) + [0.05, 0.0, 0.8]).astype(np.float32)
    faces = np.asarray(mesh.faces, dtype=np.int32)
    near_sphere = rng.normal(size=(3000, 3)) * [0.3, 0.3, 0.2] + [0.0, 0.0, 1.4]  # behind the sphere
    far_apart = np.array([[40.0, 0.0, 1.0], [-40.0, 30.0, 1.0], [0.0, -50.0, 2.0]])  # way outside the image
    starts = np.concatenate([near_sphere, far_apart]).astype(np.float32)
    starts = starts[starts[:, 2] > 1e-3]
    blocked = raster.raster_shadow(raster.raster_meshes([(0, vertices, faces)]), starts, 0.075, K)
    embree = rtcore_scene.EmbreeScene()
    TriangleMesh(embree, vertices, faces)
    projector = np.array([0.075, 0.0, 0.0], dtype=np.float32)
    occluded = embree.run(starts, projector - starts, dists=np.full(len(starts), 1 - 1e-6, np.float32),
                          query="OCCLUDED") >= 0  # fmt: skip
    assert 300 < blocked.sum() < len(starts) - 300  # both kinds are there
    assert (blocked != occluded).sum() <= 2  # float32 (Embree) against double (raster) at the sphere's rim
    some = np.flatnonzero(rng.random(len(starts)) < 0.5)  # only these segments, read in place from all the starts
    part = raster.raster_shadow(raster.raster_meshes([(0, vertices, faces)]), starts, 0.075, K, rays=some)
    assert part.shape == blocked.shape and np.array_equal(part[some], blocked[some])
    assert not np.delete(part, some).any() and part.sum() > 100


def test_without_a_compiler_the_embree_path_casts_everything(embree_only):
    assert not raster.raster_available()
    board = PlacedObject(1, "board", "plane", plane_mesh(0.5, 0.4).subdivide(), np.eye(4), 0.8)
    board.world_T_obj[2, 3] = 1.0
    hits = cast(FrameScene([board], [], np.eye(4), 0, 0), K, 0.075, 0.005)
    assert hits.hit.any() and np.allclose(hits.depth[hits.hit], 1.0, atol=1e-5)
    with pytest.raises(RuntimeError, match="unavailable"):
        raster.raster_hits(raster.raster_meshes([]), K, *(np.zeros(1),) * 5)


def test_the_c_hit_attributes_are_the_numpy_lookups(monkeypatch):
    """take_rows and hit_attributes (raster.c) give np.take's rows and the numpy hit attributes bit for bit: owner -1
    reads the tables' last row, depth is 0 there (points -0.0 where a direction is negative, as numpy's product), a
    polygon's hits name face 0."""
    if raster._library() is None:
        pytest.skip("no C compiler: the numpy definition is the only path")
    rng = np.random.default_rng(6)
    n, owners = 5000, 7
    owner = rng.integers(-1, owners, n).astype(np.int32)
    table = rng.normal(size=(owners + 1, 3)).astype(np.float32)
    best_t = rng.uniform(0.3, 5.0, n).astype(np.float32)
    directions = np.column_stack([rng.normal(size=(n, 2)), np.ones(n)]).astype(np.float32)
    ids = np.append(rng.integers(0, 9, owners), 0).astype(np.uint16)
    albedos = np.append(rng.random(owners), 0.0).astype(np.float32)
    is_polygon = np.append(rng.random(owners) < 0.4, False)
    triangle = rng.integers(0, 100, n).astype(np.int32)

    def run():
        tri = triangle.copy()
        return (raster.take_rows(table, owner), *raster.hit_attributes(owner, best_t, directions, tri, ids, albedos,
                                                                        is_polygon), tri)  # fmt: skip

    fast = run()
    monkeypatch.setattr(raster, "_library", lambda: None)
    definition = run()
    for got, expected in zip(fast, definition):
        assert got.dtype == expected.dtype
        np.testing.assert_array_equal(got, expected)
        assert np.array_equal(np.signbit(got), np.signbit(expected)) if got.dtype.kind == "f" else True
    assert (fast[-1] == 0).sum() > (triangle == 0).sum() and (fast[2][owner < 0] == 0).all()
