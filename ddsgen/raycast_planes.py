"""Planar convex polygons (the ground, a table top, a wall, the floor) intersected analytically.

A mesh whose faces are coplanar and exactly cover their convex hull becomes a :class:`Polygon` in the camera
frame. Two queries, both vectorised numpy (no per-pixel Python):

* :func:`primary_depth`: the depth of every pixel's primary ray on the polygon. Which pixels see the polygon
  is decided in the image: the polygon, clipped to the half-space in front of the camera and projected, is a
  convex polygon in pixel coordinates, so every image row crosses it in one span of columns (computed per row
  from its edges, (K, H) work) and only the rows it spans compute a depth.
* :func:`segments_blocked`: which shadow segments (hit point -> projector) cross the polygon.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ddsgen.raster import plane_zbuffer

#: Polygon points nearer than this to the camera plane (m) are clipped off before projecting (a pixel's ray
#: meets them at a depth of at most this; far below any sensor's z_min).
NEAR_CLIP_M = 1e-4
#: A pixel centre this close to the projected boundary (px) counts as inside (rounding only).
SPAN_TOLERANCE_PX = 1e-6


@dataclasses.dataclass(frozen=True)
class Polygon:
    """A planar convex polygon in the camera frame: n . x = c, 2-D edges in the in-plane basis (e1, e2)."""

    normal: np.ndarray  # (3,) unit
    offset: float  # c
    basis: np.ndarray  # (3, 3) rows n, e1, e2
    corners: np.ndarray  # (K, 2) counter-clockwise, in (e1, e2) coordinates
    edge_normals: np.ndarray  # (K, 2) inward
    edge_offsets: np.ndarray  # (K,): inside where edge_normals . q >= edge_offsets

    def corners_3d(self) -> np.ndarray:
        """(K, 3) float64 corners in the camera frame."""
        return self.offset * self.basis[0] + self.corners @ self.basis[1:]


def as_polygon(vertices: np.ndarray, faces: np.ndarray) -> Polygon | None:
    """The mesh (camera-frame ``vertices`` (V, 3), ``faces`` (F, 3)) as one convex planar polygon if it is one
    (e.g. the ground or a wall), else None."""
    if len(faces) > 64:
        return None
    v = vertices.astype(np.float64)
    tri = v[faces]
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    areas = np.linalg.norm(cross, axis=1) / 2.0
    if areas.sum() <= 0:
        return None
    normal = cross.sum(axis=0)
    length = float(np.linalg.norm(normal))
    if length < areas.sum():  # coplanar faces' normals add up to twice the area; a closed mesh's to 0
        return None
    normal /= length
    offset = float(np.mean(v @ normal))
    scale = max(float(np.ptp(v, axis=0).max()), 1e-9)
    if np.max(np.abs(v @ normal - offset)) > 1e-6 * scale:
        return None  # not planar
    e1 = np.cross(normal, [1.0, 0.0, 0.0] if abs(normal[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(normal, e1)
    q = v @ np.stack([e1, e2]).T
    from scipy.spatial import ConvexHull

    try:
        hull = ConvexHull(q)
    except Exception:
        return None
    if abs(hull.volume - areas.sum()) > 1e-6 * hull.volume:
        return None  # not exactly its convex hull (holes, overlaps, concave)
    corners = q[hull.vertices]  # counter-clockwise
    edges = np.roll(corners, -1, axis=0) - corners
    inward = np.stack([-edges[:, 1], edges[:, 0]], axis=1)
    inward /= np.linalg.norm(inward, axis=1, keepdims=True)
    return Polygon(normal, offset, np.stack([normal, e1, e2]), corners, inward, np.einsum("ij,ij->i", inward, corners))


def _clip_in_front(points: np.ndarray, z_min: float) -> np.ndarray:
    """The convex polygon ``points`` (K, 3) clipped to z >= z_min (Sutherland-Hodgman, one plane) -> (M, 3)."""
    kept = []
    for a, b in zip(points, np.roll(points, -1, axis=0)):
        a_in, b_in = a[2] >= z_min, b[2] >= z_min
        if a_in:
            kept.append(a)
        if a_in != b_in:
            kept.append(a + (z_min - a[2]) / (b[2] - a[2]) * (b - a))
    return np.array(kept).reshape(-1, 3)


def image_spans(polygon: Polygon, fx: float, fy: float, cx: float, cy: float, height: int):
    """Per image row, the columns whose pixel centres see the polygon: ``(lo, hi)`` float64 (H,) each,
    inside where lo <= u <= hi (lo > hi: the row misses it). Pixel centres at integer (u, v)."""
    empty = np.full(height, np.inf), np.full(height, -np.inf)
    front = _clip_in_front(polygon.corners_3d(), NEAR_CLIP_M)
    if len(front) < 3:
        return empty
    px = np.stack([fx * front[:, 0] / front[:, 2] + cx, fy * front[:, 1] / front[:, 2] + cy], axis=1)
    edges = np.roll(px, -1, axis=0) - px
    keep = np.hypot(edges[:, 0], edges[:, 1]) > 1e-9  # drop repeated points (a clip through a corner)
    px, edges = px[keep], edges[keep]
    area2 = float(np.sum(px[:, 0] * np.roll(px[:, 1], -1) - np.roll(px[:, 0], -1) * px[:, 1]))
    if len(px) < 3 or abs(area2) < 1e-12:
        return empty  # seen edge-on
    # Inward unit normals (a, b): inside where a u + b v >= c, with the orientation of the projected polygon.
    inward = np.stack([-edges[:, 1], edges[:, 0]], axis=1) * np.sign(area2)
    inward /= np.hypot(inward[:, 0], inward[:, 1])[:, None]
    a, b = inward[:, 0:1], inward[:, 1:2]  # (M, 1)
    c = np.einsum("ij,ij->i", inward, px)[:, None] - SPAN_TOLERANCE_PX
    rows = np.arange(height, dtype=np.float64)[None, :]  # (1, H)
    need = c - b * rows  # a u >= need, (M, H)
    horizontal = np.abs(a) < 1e-12
    with np.errstate(divide="ignore", invalid="ignore"):
        bound = need / a
    lo = np.max(np.where(~horizontal & (a > 0), bound, -np.inf), axis=0)
    hi = np.min(np.where(~horizontal & (a < 0), bound, np.inf), axis=0)
    row_out = np.any(horizontal & (need > 0), axis=0)  # a horizontal edge with the row on its outer side
    lo[row_out], hi[row_out] = np.inf, -np.inf
    return lo, hi


def primary_depth(polygon: Polygon, intrinsics) -> np.ndarray:
    """(H, W) float32 ray parameter (= depth) of the rays from the origin through K^-1 [u, v, 1] (``intrinsics``:
    a :class:`~ddsgen.preset.Intrinsics`); inf where they miss the polygon."""
    t = np.full((int(intrinsics.height), int(intrinsics.width)), np.float32(np.inf), dtype=np.float32)
    v0, band = primary_depth_band(polygon, intrinsics)
    t[v0 : v0 + len(band)] = band
    return t


def _depth_band_terms(polygon: Polygon, intrinsics):
    """``(v0, lo, hi, row_term, col_term)`` of the rows v0.. the polygon spans (None when it spans none; convex: the
    rows are contiguous): their column spans (float64) and the float32 terms whose sum is n . d for the ray d through
    each pixel (row_term (R,) + col_term (W,))."""
    fx, fy, cx, cy = intrinsics.fx, intrinsics.fy, intrinsics.cx, intrinsics.cy
    xs = (np.arange(int(intrinsics.width), dtype=np.float64) - cx) / fx  # directions' x and y (z = 1)
    ys = (np.arange(int(intrinsics.height), dtype=np.float64) - cy) / fy
    lo, hi = image_spans(polygon, fx, fy, cx, cy, len(ys))
    rows = np.flatnonzero(lo <= hi)
    if not len(rows):
        return None
    v0, v1 = int(rows[0]), int(rows[-1]) + 1
    n = polygon.basis[0]
    return v0, lo[v0:v1], hi[v0:v1], (n[1] * ys[v0:v1] + n[2]).astype(np.float32), (n[0] * xs).astype(np.float32)


def primary_depth_band(polygon: Polygon, intrinsics) -> tuple[int, np.ndarray]:
    """``(v0, band)``: :func:`primary_depth` on the rows the polygon spans only, ``band`` (R, W) float32 being
    rows v0..v0 + R - 1 (R = 0 when it spans none; every other row misses it)."""
    terms = _depth_band_terms(polygon, intrinsics)
    if terms is None:
        return 0, np.empty((0, int(intrinsics.width)), dtype=np.float32)
    return terms[0], _depth_band(polygon, *terms[1:])


def _depth_band(polygon: Polygon, lo, hi, row_term, col_term) -> np.ndarray:
    """(R, W) float32 ray parameters of :func:`_depth_band_terms`' rows, inf where the rays miss the polygon."""
    nd = row_term[:, None] + col_term[None, :]
    with np.errstate(divide="ignore", invalid="ignore"):
        band = np.float32(polygon.offset) / nd
    cols = np.arange(len(col_term), dtype=np.float64)[None, :]
    ok = (cols >= lo[:, None]) & (cols <= hi[:, None]) & (band > 0)  # band > 0: False for nan
    return np.where(ok, band, np.float32(np.inf))


def write_primary_depth(polygon: Polygon, intrinsics, index: int, best_t: np.ndarray, owner: np.ndarray) -> None:
    """Write the polygon's primary hits into the z-buffer ``best_t`` / ``owner`` ((H, W) float32 / int32, in place):
    where :func:`primary_depth` is nearer than ``best_t``, it becomes ``best_t`` and ``index`` the owner. One C pass
    where the raster is compiled (:func:`ddsgen.raster.plane_zbuffer`, the same values), numpy otherwise."""
    terms = _depth_band_terms(polygon, intrinsics)
    if terms is None:
        return
    v0, lo, hi, row_term, col_term = terms
    if plane_zbuffer(polygon.offset, row_term, col_term, lo, hi, v0, index, best_t, owner):
        return
    band = _depth_band(polygon, lo, hi, row_term, col_term)
    rows = slice(v0, v0 + len(band))
    nearer = band < best_t[rows]
    owner[rows][nearer] = index
    best_t[rows][nearer] = band[nearer]


def _inside(polygon: Polygon, q1: np.ndarray, q2: np.ndarray) -> np.ndarray:
    """True where the in-plane point (q1, q2) is inside every edge: a q1 + b q2 >= c - 1e-7 (m), evaluated in
    float64 (the edge coefficients are float64 scalars) into two reused buffers."""
    inside = np.ones(q1.shape, dtype=bool)
    along, other = np.empty(q1.shape, dtype=np.float64), np.empty(q1.shape, dtype=np.float64)
    for (a, b), c in zip(polygon.edge_normals, polygon.edge_offsets):
        np.multiply(a, q1, out=along)
        np.multiply(b, q2, out=other)
        along += other
        inside &= along >= c - 1e-7
    return inside


def segments_blocked(polygon: Polygon, starts: np.ndarray, end: np.ndarray) -> np.ndarray:
    """(M,) bool: True where the segment start -> end crosses the polygon (``starts`` (M, 3) float32,
    ``end`` (3,), camera frame)."""
    side_start = starts @ polygon.normal.astype(np.float32) - np.float32(polygon.offset)
    side_end = float(end @ polygon.normal - polygon.offset)
    crossing = np.flatnonzero((side_start > 0) != (side_end > 0))
    blocked = np.zeros(len(starts), dtype=bool)
    if len(crossing):
        s = starts[crossing].astype(np.float64)
        a = side_start[crossing].astype(np.float64)
        w = a / (a - side_end)  # fraction of the way to the end where the plane is crossed
        point = s + w[:, None] * (end[None, :] - s)
        q = point @ polygon.basis[1:].T
        blocked[crossing] = _inside(polygon, q[:, 0], q[:, 1])
    return blocked
