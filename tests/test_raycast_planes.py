"""The analytic planar polygons: which pixels see them and at what depth, against a float64 per-pixel reference,
for polygons wholly in front of the camera, crossing the camera plane (a floor under the camera) and seen edge-on."""

from __future__ import annotations

import numpy as np
import pytest

from ddsgen.preset import Intrinsics
from ddsgen.raycast_planes import as_polygon, primary_depth, primary_depth_band, segments_blocked, write_primary_depth

WIDTH, HEIGHT, FX, FY, CX, CY = 80, 60, 70.0, 72.0, 39.5, 29.5
K = Intrinsics(width=WIDTH, height=HEIGHT, fx=FX, fy=FY, cx=CX, cy=CY)


def _quad(rng, crossing: bool) -> np.ndarray:
    """(4, 3) corners of a random rectangle in the camera frame; ``crossing``: some corners behind the camera."""
    normal = rng.normal(size=3)
    normal /= np.linalg.norm(normal)
    e1 = np.cross(normal, rng.normal(size=3))
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(normal, e1)
    centre = np.array([rng.uniform(-0.5, 0.5), rng.uniform(-0.5, 0.5), rng.uniform(0.3, 0.8) if crossing else
                       rng.uniform(1.0, 3.0)])  # fmt: skip
    half = rng.uniform(1.0, 4.0, size=2) if crossing else rng.uniform(0.2, 1.0, size=2)
    corners = [centre + sx * half[0] * e1 + sy * half[1] * e2 for sx, sy in ((-1, -1), (1, -1), (1, 1), (-1, 1))]
    return np.array(corners)


def _reference(corners: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """float64 per pixel: depth where the ray hits the rectangle (inf elsewhere) and the hit's distance to the
    rectangle's boundary (m), to leave out pixels that rounding may put on either side."""
    o, a, b = corners[0], corners[1] - corners[0], corners[3] - corners[0]
    n = np.cross(a, b)
    u, v = np.meshgrid(np.arange(WIDTH), np.arange(HEIGHT))
    d = np.stack([(u - CX) / FX, (v - CY) / FY, np.ones_like(u, dtype=float)], axis=-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (o @ n) / (d @ n)
    p = t[..., None] * d - o
    s, r = p @ a / (a @ a), p @ b / (b @ b)
    margin = np.minimum.reduce([s * np.linalg.norm(a), (1 - s) * np.linalg.norm(a), r * np.linalg.norm(b),
                                (1 - r) * np.linalg.norm(b)])  # fmt: skip
    inside = (t > 0) & (margin >= 0)
    return np.where(inside, t, np.inf), np.where(t > 0, np.abs(margin), np.inf)


@pytest.mark.parametrize("crossing", [False, True], ids=["in-front", "crossing-camera-plane"])
def test_primary_depth_matches_a_per_pixel_float64_reference(crossing):
    rng = np.random.default_rng(7 if crossing else 3)
    seen = 0
    for _ in range(40):
        corners = _quad(rng, crossing)
        polygon = as_polygon(corners.astype(np.float32), np.array([[0, 1, 2], [0, 2, 3]]))
        expected, margin = _reference(corners.astype(np.float32).astype(np.float64))
        got = primary_depth(polygon, K)
        clear = margin > 1e-5  # away from the boundary by more than rounding
        assert np.array_equal(np.isfinite(got)[clear], np.isfinite(expected)[clear])
        both = np.isfinite(got) & np.isfinite(expected)
        np.testing.assert_allclose(got[both], expected[both], rtol=1e-4)  # float32 arithmetic, grazing rays
        seen += int(np.isfinite(got).sum())
    assert seen > 0.1 * 40 * WIDTH * HEIGHT  # the polygons were in view, the comparison was not vacuous


def test_the_c_z_buffer_writes_the_numpy_definitions_depths(monkeypatch):
    """write_primary_depth's C pass (raster.c) and its numpy definition leave the same z-buffer and owners bit for bit,
    over rectangles in front of and across the camera plane drawn over each other in turn."""
    import ddsgen.raster as raster

    if raster._library() is None:
        pytest.skip("no C compiler: the numpy definition is the only path")
    rng = np.random.default_rng(11)
    polygons = [as_polygon(_quad(rng, crossing).astype(np.float32), np.array([[0, 1, 2], [0, 2, 3]]))
                for crossing in (False, True) * 10]  # fmt: skip

    def z_buffer():
        best_t = np.full((HEIGHT, WIDTH), np.inf, dtype=np.float32)
        owner = np.full((HEIGHT, WIDTH), -1, dtype=np.int32)
        for k, polygon in enumerate(polygons):
            write_primary_depth(polygon, K, k, best_t, owner)
        return best_t, owner

    fast = z_buffer()
    monkeypatch.setattr(raster, "_library", lambda: None)
    definition = z_buffer()
    for got, expected in zip(fast, definition):
        np.testing.assert_array_equal(got, expected)
    assert len(np.unique(fast[1])) >= 4  # several polygons nearest somewhere: the test is not vacuous
    v0, band = primary_depth_band(polygons[0], K)
    assert np.isfinite(band).any() and v0 >= 0


def test_a_floor_under_the_camera_fills_the_lower_image_to_the_horizon():
    # The camera 1 m above a floor reaching 50 m ahead, looking level: rows below the horizon (v > cy) see it
    # at depth h fy / (v - cy) up to 50 m, the rows above and nearer the horizon do not; the floor's near
    # corners lie behind the camera.
    floor = np.array([[-500.0, 1.0, -5.0], [500.0, 1.0, -5.0], [500.0, 1.0, 50.0], [-500.0, 1.0, 50.0]])
    polygon = as_polygon(floor.astype(np.float32), np.array([[0, 1, 2], [0, 2, 3]]))
    depth = primary_depth(polygon, K)
    with np.errstate(divide="ignore"):
        on_floor = 1.0 * FY / (np.arange(HEIGHT) - CY)
    below = (on_floor > 0) & (on_floor <= 50.0)
    assert below.sum() > HEIGHT // 3 and np.isinf(depth[~below]).all()
    expected = on_floor[below]
    np.testing.assert_allclose(depth[below], np.repeat(expected[:, None], WIDTH, axis=1), rtol=1e-6)


def test_a_polygon_seen_edge_on_covers_no_pixel():
    wall = np.array([[0.0, -1.0, 1.0], [0.0, 1.0, 1.0], [0.0, 1.0, 3.0], [0.0, -1.0, 3.0]])  # the plane x = 0
    polygon = as_polygon(wall.astype(np.float32), np.array([[0, 1, 2], [0, 2, 3]]))
    assert np.isinf(primary_depth(polygon, K)).all()


def test_segments_blocked_only_where_they_cross_inside_the_polygon():
    board = np.array([[-0.1, -0.1, 1.0], [0.1, -0.1, 1.0], [0.1, 0.1, 1.0], [-0.1, 0.1, 1.0]])
    polygon = as_polygon(board.astype(np.float32), np.array([[0, 1, 2], [0, 2, 3]]))
    end = np.array([0.0, 0.0, 0.0])
    starts = np.array([[0.0, 0.0, 2.0], [0.5, 0.0, 2.0], [0.0, 0.0, 0.5], [0.19, 0.0, 2.0], [0.21, 0.0, 2.0]],
                      dtype=np.float32)  # fmt: skip
    # through the centre; beside it; not reaching it; just inside (crosses at x = 0.095); just outside (0.105)
    assert segments_blocked(polygon, starts, end).tolist() == [True, False, False, True, False]


@pytest.mark.parametrize("make", ["box", "open_box_lid"])
def test_a_small_closed_or_folded_mesh_is_not_taken_for_a_polygon(make):
    """Background meshes of <= 64 faces are tried as polygons (distractor boxes are background):
    a closed box's face normals sum to zero and a folded sheet's fall short of twice its area; neither is a
    polygon, and neither warns (the zero normal was divided by its length)."""
    import warnings

    import trimesh

    mesh = trimesh.creation.box(extents=(0.6, 0.4, 0.3))
    vertices, faces = np.asarray(mesh.vertices) + [0.0, 0.0, 2.0], np.asarray(mesh.faces)
    if make == "open_box_lid":  # two faces of the box: an L-shaped fold, not planar
        normals = mesh.face_normals
        faces = faces[(np.abs(normals[:, 2]) > 0.9) | (normals[:, 0] > 0.9)]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert as_polygon(vertices, faces) is None
