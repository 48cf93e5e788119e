"""Ray casting with Embree (embreex): clean depth, hit points, normals, instance ids, projector shadow.

Geometry is transformed into the camera frame once per frame (float64 -> float32),
so every primary ray starts at the origin and float32 precision is spent where the
scene is. Primary rays use the *unnormalised* directions ``K^-1 [u, v, 1]`` (z = 1),
so Embree's hit distance ``t`` is the depth z itself. Pixel centres are at integer
``(u, v)`` (OpenCV).

Projector shadow: from each hit point P (camera frame), offset by the shadow bias
``xi`` along the camera-facing normal, one occlusion ray towards the projector centre
``(+b, 0, 0)``, capped just before the projector. ``shadow`` is True where that ray is
blocked or where the surface faces away from the projector (n . (t_p - P) <= 0).

Everything is vectorised: one ``run`` call for all primary rays, one occlusion call for
all shadow rays. Embree releases the GIL inside ``run``.
"""

from __future__ import annotations

import dataclasses
import functools

import numpy as np

from ddsgen.preset import Intrinsics


@dataclasses.dataclass
class RayHits:
    """Per-pixel ray-cast results, all numpy, image shape (H, W); see docs/ARCHITECTURE.md."""

    depth: np.ndarray  # float32 (H, W): z of the first hit (m), 0 where no hit
    points: np.ndarray  # float32 (H, W, 3): hit point in the camera frame (m), 0 where no hit
    normals: np.ndarray  # float32 (H, W, 3): unit normal, camera frame, towards the camera; 0 where no hit
    instance: np.ndarray  # uint16 (H, W): object id, 0 = background / nothing
    hit: np.ndarray  # bool (H, W)
    shadow: np.ndarray  # bool (H, W): hit point not seen by the projector at (+b, 0, 0)
    albedo: np.ndarray  # float32 (H, W): IR reflectance of the hit surface, 0 where no hit


@functools.lru_cache(maxsize=8)
def _ray_directions(width: int, height: int, fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    """(H*W, 3) float32 directions K^-1 [u, v, 1] (z = 1), row-major over (v, u); read-only."""
    u = (np.arange(width, dtype=np.float64) - cx) / fx
    v = (np.arange(height, dtype=np.float64) - cy) / fy
    directions = np.empty((height, width, 3), dtype=np.float32)
    directions[..., 0] = u[None, :]
    directions[..., 1] = v[:, None]
    directions[..., 2] = 1.0
    directions = directions.reshape(-1, 3)
    directions.flags.writeable = False
    return directions


def ray_directions(intrinsics: Intrinsics) -> np.ndarray:
    """(H, W, 3) float32 ray directions with z = 1 (so ``t`` along them is the depth)."""
    i = intrinsics
    return _ray_directions(int(i.width), int(i.height), float(i.fx), float(i.fy), float(i.cx), float(i.cy)).reshape(
        int(i.height), int(i.width), 3
    )


def _camera_vertices(placed, cam_T_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    cam_T_obj = cam_T_world @ placed.world_T_obj
    vertices = np.asarray(placed.mesh.vertices, dtype=np.float64) @ cam_T_obj[:3, :3].T + cam_T_obj[:3, 3]
    faces = np.asarray(placed.mesh.faces, dtype=np.int32)
    return np.ascontiguousarray(vertices, dtype=np.float32), np.ascontiguousarray(faces)


def _build_scene(meshes):
    """An Embree scene with one geometry per (vertices, faces); geometry id = list index."""
    from embreex import rtcore_scene
    from embreex.mesh_construction import TriangleMesh

    scene = rtcore_scene.EmbreeScene()
    for vertices, faces in meshes:
        TriangleMesh(scene, vertices, faces)
    return scene


def _unit(v: np.ndarray) -> np.ndarray:
    norm = np.linalg.norm(v, axis=-1, keepdims=True)
    return v / np.maximum(norm, 1e-30)


@dataclasses.dataclass(frozen=True)
class _Polygon:
    """A planar convex polygon in the camera frame: n . x = c, 2-D edges in the in-plane basis (e1, e2)."""

    normal: np.ndarray  # (3,) unit
    offset: float  # c
    basis: np.ndarray  # (3, 3) rows n, e1, e2
    corners: np.ndarray  # (K, 2) counter-clockwise, in (e1, e2) coordinates
    edge_normals: np.ndarray  # (K, 2) inward
    edge_offsets: np.ndarray  # (K,): inside where edge_normals . q >= edge_offsets


def _as_polygon(vertices: np.ndarray, faces: np.ndarray) -> _Polygon | None:
    """The mesh as one convex planar polygon if it is one (e.g. the ground or a wall), else None."""
    if len(faces) > 64:
        return None
    v = vertices.astype(np.float64)
    tri = v[faces]
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    areas = np.linalg.norm(cross, axis=1) / 2.0
    if areas.sum() <= 0:
        return None
    normal = cross.sum(axis=0)
    normal /= np.linalg.norm(normal)
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
    return _Polygon(normal, offset, np.stack([normal, e1, e2]), corners, inward, np.einsum("ij,ij->i", inward, corners))


def _polygon_inside(polygon: _Polygon, q1: np.ndarray, q2: np.ndarray) -> np.ndarray:
    inside = np.ones(q1.shape, dtype=bool)
    for (a, b), c in zip(polygon.edge_normals, polygon.edge_offsets):
        inside &= a * q1 + b * q2 >= c - 1e-7
    return inside


def _polygon_primary_t(polygon: _Polygon, xs: np.ndarray, ys: np.ndarray) -> np.ndarray:
    """(H, W) ray parameter (= depth) of the rays from the origin through K^-1 [u, v, 1]; inf where they miss.

    ``xs`` (W,) and ``ys`` (H,) are the x and y of the directions (z = 1): dot products are outer sums.
    """
    def dot(row):
        return (row[1] * ys + row[2]).astype(np.float32)[:, None] + (row[0] * xs).astype(np.float32)[None, :]

    nd = dot(polygon.basis[0])
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.float32(polygon.offset) / nd
    q1 = t * dot(polygon.basis[1])
    q2 = t * dot(polygon.basis[2])
    ok = t > 0  # False for nan; inf only where nd == 0 (parallel): rejected by the edge tests below
    ok &= _polygon_inside(polygon, q1, q2)
    return np.where(ok, t, np.float32(np.inf))


def _segment_blocked_by_polygon(polygon: _Polygon, starts: np.ndarray, end: np.ndarray) -> np.ndarray:
    """True where the segment start -> end crosses the polygon (vectorised over starts (M, 3))."""
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
        blocked[crossing] = _polygon_inside(polygon, q[:, 0], q[:, 1])
    return blocked


def cast(scene, intrinsics: Intrinsics, baseline_m: float, shadow_bias_m: float) -> RayHits:
    """Ray-cast a :class:`~ddsgen.scene.sampling.FrameScene` for a pinhole camera.

    Args:
        scene: FrameScene (objects with id >= 1, background with id 0, ``world_T_cam``).
        intrinsics: image size and K (px); pixel centres at integer coordinates.
        baseline_m: projector offset b along the camera's +x axis (m).
        shadow_bias_m: shadow-ray origin offset xi along the normal (m).

    Returns:
        RayHits with arrays of shape (H, W) / (H, W, 3).

    Planar convex background pieces (ground, walls) are intersected analytically; everything else goes
    through one Embree scene (objects only: the huge ground triangles would slow every ray's traversal).
    """
    height, width = int(intrinsics.height), int(intrinsics.width)
    placed = list(scene.objects) + list(scene.background)
    cam_T_world = np.linalg.inv(np.asarray(scene.world_T_cam, dtype=np.float64))
    directions = ray_directions(intrinsics).reshape(-1, 3)
    n_rays = directions.shape[0]

    polygons: list[tuple[int, _Polygon]] = []  # (index into placed, polygon)
    meshes: list[tuple[np.ndarray, np.ndarray]] = []
    mesh_owner: list[int] = []
    for k, p in enumerate(placed):
        vertices, faces = _camera_vertices(p, cam_T_world)
        polygon = _as_polygon(vertices, faces) if p.id == 0 else None
        if polygon is not None:
            polygons.append((k, polygon))
        else:
            meshes.append((vertices, faces))
            mesh_owner.append(k)

    # --- primary rays: nearest of the analytic polygons and the Embree scene
    xs = (np.arange(width, dtype=np.float64) - intrinsics.cx) / intrinsics.fx
    ys = (np.arange(height, dtype=np.float64) - intrinsics.cy) / intrinsics.fy
    best_t = np.full((height, width), np.inf, dtype=np.float32)
    owner = np.full((height, width), -1, dtype=np.int32)
    for k, polygon in polygons:
        t = _polygon_primary_t(polygon, xs, ys)
        owner = np.where(t < best_t, np.int32(k), owner)
        best_t = np.minimum(best_t, t)
    best_t, owner = best_t.reshape(-1), owner.reshape(-1)
    # Normals: a plane seen from the origin shows one side (n . x = c, t > 0 -> sign(n . d) = sign(c)).
    table = np.zeros((len(placed) + 1, 3), dtype=np.float32)  # row -1 (last) = no hit
    for k, polygon in polygons:
        table[k] = -polygon.normal if polygon.offset > 0 else polygon.normal
    mesh_hits = normals_of_mesh_hits = None
    embree = None
    mesh_hits = None
    boxes = [_image_box(vertices, intrinsics) for vertices, _ in meshes]
    if meshes:
        # Only rays inside some mesh's projected box can hit it (exact, conservative cull).
        candidates = np.zeros((height, width), dtype=bool)
        for box in boxes:
            if box is None:
                candidates[:] = True
                break
            u0, v0, u1, v1 = box
            iu0, iv0 = max(int(np.ceil(u0)), 0), max(int(np.ceil(v0)), 0)
            iu1, iv1 = min(int(np.floor(u1)), width - 1), min(int(np.floor(v1)), height - 1)
            if iu0 <= iu1 and iv0 <= iv1:
                candidates[iv0 : iv1 + 1, iu0 : iu1 + 1] = True
        rays = np.flatnonzero(candidates)
        if len(rays):
            embree = _build_scene(meshes)
            d = directions[rays]
            result = embree.run(np.zeros_like(d), d, output=1)
            geom = result["geomID"]
            closer = np.flatnonzero((geom >= 0) & (result["tfar"] < best_t[rays]))
            mesh_hits = rays[closer]
            best_t[mesh_hits] = result["tfar"][closer]
            owner[mesh_hits] = np.asarray(mesh_owner, dtype=np.int32)[geom[closer]]
            n = result["Ng"][closer]
            n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), np.float32(1e-30))
            flip = np.einsum("ij,ij->i", n, d[closer]) > 0
            n[flip] *= -1.0
    normals = table[owner]
    if mesh_hits is not None:
        normals[mesh_hits] = n

    hit = owner >= 0
    depth = np.where(hit, best_t, np.float32(0.0))
    points = directions * depth[:, None]
    ids = np.append(np.array([o.id for o in placed], dtype=np.uint16), np.uint16(0))
    albedos = np.append(np.array([o.albedo for o in placed], dtype=np.float32), np.float32(0.0))
    instance = ids[owner]
    albedo = albedos[owner]

    # --- shadow rays from the biased hit points S towards the projector at (+b, 0, 0), capped before it.
    # Computed on all pixels (no gathers) and masked with `hit` at the end.
    projector = np.array([baseline_m, 0.0, 0.0], dtype=np.float64)
    start = points + np.float32(shadow_bias_m) * normals
    # surface facing away from the projector: n . (t_p - P) <= 0
    blocked = normals[:, 0] * np.float32(baseline_m) - np.einsum("ij,ij->i", normals, points) <= 0.0
    for _, polygon in polygons:
        blocked |= _segment_blocked_by_polygon(polygon, start, projector)
    if embree is not None:
        # The segment S -> projector projects onto image row v_S, columns u >= u_S (a half-line), so it can only
        # meet a mesh whose projected box spans that row to the right of u_S (exact, conservative cull).
        with np.errstate(divide="ignore", invalid="ignore"):
            inv_z = np.float32(1.0) / start[:, 2]
            u_s = start[:, 0] * inv_z * np.float32(intrinsics.fx) + np.float32(intrinsics.cx)
            v_s = start[:, 1] * inv_z * np.float32(intrinsics.fy) + np.float32(intrinsics.cy)
        maybe = np.zeros(n_rays, dtype=bool)
        for box in boxes:
            if box is None:
                maybe[:] = True
                break
            u0, v0, u1, v1 = box
            maybe |= (v_s >= v0 - 1.0) & (v_s <= v1 + 1.0) & (u_s <= u1 + 1.0)
        maybe |= ~(start[:, 2] > 0)  # start behind the camera plane (or nan): no cull
        todo = np.flatnonzero(maybe & hit & ~blocked)
        if len(todo):
            s = start[todo]
            occluded = embree.run(
                s,
                projector.astype(np.float32)[None, :] - s,
                dists=np.full(len(todo), 1.0 - 1e-6, dtype=np.float32),
                query="OCCLUDED",
            )
            blocked[todo] |= occluded >= 0
    shadow = blocked & hit
    normals[~hit] = 0.0

    shape2, shape3 = (height, width), (height, width, 3)
    return RayHits(
        depth=depth.reshape(shape2),
        points=points.reshape(shape3),
        normals=normals.reshape(shape3),
        instance=instance.reshape(shape2),
        hit=hit.reshape(shape2),
        shadow=shadow.reshape(shape2),
        albedo=albedo.reshape(shape2),
    )


def _image_box(vertices_cam: np.ndarray, intrinsics: Intrinsics):
    """Continuous pixel box (u0, v0, u1, v1) of the projection of a mesh entirely in front of the camera;
    None if some vertex is at or behind the camera plane (then no image-space cull is valid)."""
    z = vertices_cam[:, 2].astype(np.float64)
    if not np.all(z > 1e-6):
        return None
    u = intrinsics.fx * vertices_cam[:, 0] / z + intrinsics.cx
    v = intrinsics.fy * vertices_cam[:, 1] / z + intrinsics.cy
    return float(u.min()) - 0.5, float(v.min()) - 0.5, float(u.max()) + 0.5, float(v.max()) + 0.5


def _projected_box(vertices_cam: np.ndarray, intrinsics: Intrinsics) -> tuple[int, int, int, int] | None:
    """Pixel box (u0, v0, u1, v1) inclusive that contains the object's projection, or None if not in view."""
    width, height = int(intrinsics.width), int(intrinsics.height)
    z = vertices_cam[:, 2]
    if np.all(z <= 1e-6):
        return None
    if np.any(z <= 1e-6):  # straddles the camera plane: be safe, use the whole image
        return 0, 0, width - 1, height - 1
    u = intrinsics.fx * vertices_cam[:, 0] / z + intrinsics.cx
    v = intrinsics.fy * vertices_cam[:, 1] / z + intrinsics.cy
    u0, u1 = int(np.floor(u.min())) - 1, int(np.ceil(u.max())) + 1
    v0, v1 = int(np.floor(v.min())) - 1, int(np.ceil(v.max())) + 1
    u0, v0, u1, v1 = max(u0, 0), max(v0, 0), min(u1, width - 1), min(v1, height - 1)
    if u0 > u1 or v0 > v1:
        return None
    return u0, v0, u1, v1


def _alone_pixel_count(placed, cam_T_world: np.ndarray, intrinsics: Intrinsics) -> int:
    """Pixels the object covers when ray-cast alone (only rays inside its projected box are cast)."""
    vertices, faces = _camera_vertices(placed, cam_T_world)
    box = _projected_box(vertices, intrinsics)
    if box is None:
        return 0
    u0, v0, u1, v1 = box
    directions = np.ascontiguousarray(ray_directions(intrinsics)[v0 : v1 + 1, u0 : u1 + 1].reshape(-1, 3))
    embree = _build_scene([(vertices, faces)])
    geom = embree.run(np.zeros_like(directions), directions, query="OCCLUDED")  # any hit, no distance needed
    return int(np.count_nonzero(geom >= 0))


def object_labels(scene, hits: RayHits, intrinsics: Intrinsics) -> list[dict]:
    """Manifest ``objects`` entries, one per placed object (ids ascending).

    Each: ``id``, ``mesh`` (mesh_ref), ``class``, ``cam_T_obj`` (4x4 nested list, metres, maps the mesh in
    metres = file units x ``mesh_scale``), ``mesh_scale``, ``bbox`` [x, y, w, h] of the visible mask pixels
    ([0, 0, 0, 0] when not visible; like BOP's bbox_visib), ``visible_fraction`` = visible pixels / pixels the
    object would cover alone (0 when it is out of view).
    """
    cam_T_world = np.linalg.inv(np.asarray(scene.world_T_cam, dtype=np.float64))
    instance = hits.instance
    labels = []
    present = set(np.unique(instance).tolist())
    for placed in sorted(scene.objects, key=lambda o: o.id):
        visible = 0
        bbox = [0, 0, 0, 0]
        if placed.id in present:
            rows, cols = np.nonzero(instance == placed.id)
            visible = len(rows)
            x0, y0 = int(cols.min()), int(rows.min())
            bbox = [x0, y0, int(cols.max()) - x0 + 1, int(rows.max()) - y0 + 1]
        fraction = 0.0
        if visible:
            alone = _alone_pixel_count(placed, cam_T_world, intrinsics)
            fraction = min(1.0, visible / alone) if alone else 1.0
        cam_T_obj = cam_T_world @ placed.world_T_obj
        labels.append(
            {
                "id": int(placed.id),
                "mesh": placed.mesh_ref,
                "class": placed.class_name,
                "cam_T_obj": [[float(x) for x in row] for row in cam_T_obj],
                "mesh_scale": float(getattr(placed, "mesh_scale", 1.0)),
                "bbox": bbox,
                "visible_fraction": float(fraction),
            }
        )
    return labels
