"""Ray casting with Embree (embreex): clean depth, hit points, normals, instance ids, projector shadow.

Primary rays use the *unnormalised* directions ``K^-1 [u, v, 1]`` (z = 1), so the hit
parameter ``t`` is the depth z itself. Pixel centres are at integer ``(u, v)`` (OpenCV).

* Planar convex background pieces (ground, table top, walls, floor) are intersected analytically
  (ddsgen/raycast_planes.py); a BVH holding the huge ground triangles slows every ray.
* Every other mesh has one Embree BVH in its own object frame, built once per process
  and cached; rays are rotated into the object frame (t is unchanged).
* Exact image-space culls: a mesh can only be hit by rays inside its projected box, and
  a shadow segment S -> projector (+b, 0, 0) projects onto image row v_S for u >= u_S, so it
  can only meet a mesh whose box spans that row to the right of u_S.

Projector shadow: from each hit point P (camera frame), offset by the shadow bias ``xi``
along the camera-facing normal, one occlusion ray towards the projector centre, capped
just before it. ``shadow`` is True where that ray is blocked or where the surface faces
away from the projector (n . (t_p - P) <= 0). No per-pixel Python loops.
(embreex's ``run`` does not release the GIL in this build: threads do not help.)
"""

from __future__ import annotations

import dataclasses
import functools
import weakref

import numpy as np

from ddsgen.preset import Intrinsics
from ddsgen.raycast_planes import Polygon, as_polygon, primary_depth, segments_blocked


@dataclasses.dataclass
class RayHits:
    """Per-pixel ray-cast results, all numpy, image shape (H, W); see docs/ARCHITECTURE.md."""

    depth: np.ndarray  # float32 (H, W): z of the first hit (m), 0 where no hit
    points: np.ndarray  # float32 (H, W, 3): hit point in the camera frame (m), 0 where no hit
    normals: np.ndarray  # float32 (H, W, 3): unit normal, camera frame, towards the camera; 0 where no hit
    instance: np.ndarray  # uint16 (H, W): object id, 0 = background / nothing
    hit: np.ndarray  # bool (H, W)
    shadow: np.ndarray | None  # bool (H, W): hit point not seen by the projector at (+b, 0, 0); None if not cast
    albedo: np.ndarray  # float32 (H, W): IR reflectance of the hit surface, 0 where no hit
    coverage: dict = dataclasses.field(default_factory=dict)  # object id -> pixels it covers when cast alone
    # Which triangle each ray hit, for recomputing the hits from posed vertices (ddsgen.scene_gradients):
    owner: np.ndarray | None = None  # int32 (H, W): index into scene.objects + scene.background, -1 where no hit
    triangle: np.ndarray | None = None  # int32 (H, W): face index in the owner's mesh, -1 where no hit
    # float32 (H, W, 2): Embree's (u, v) on that face, P = (1 - u - v) V0 + u V1 + v V2; 0 where no hit.
    # Analytic planar polygons (ground, walls) report face 0 (their faces are coplanar) and (u, v) = (0, 0).
    barycentric: np.ndarray | None = None


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


@dataclasses.dataclass
class _MeshBVH:
    mesh_ref: "weakref.ref"
    fingerprint: tuple
    embree: object  # EmbreeScene with the mesh in its own object frame
    hull: np.ndarray  # (K, 3) float64 convex-hull vertices (for image boxes)
    centre: np.ndarray  # (3,) float64 centre of the hull's bounding box (object frame) ...
    radius: float  # ... and the radius of the sphere about it that holds every vertex (m)


_BVH_CACHE: dict[int, _MeshBVH] = {}


def _mesh_bvh(mesh) -> _MeshBVH:
    """Embree BVH of a mesh in its object frame, built once per process per mesh object."""
    from embreex import rtcore_scene
    from embreex.mesh_construction import TriangleMesh

    vertices = np.asarray(mesh.vertices)
    faces = np.asarray(mesh.faces)
    fingerprint = (vertices.shape, faces.shape, float(vertices[::97].sum()), int(faces[::97].sum()))
    entry = _BVH_CACHE.get(id(mesh))
    if entry is not None and entry.mesh_ref() is mesh and entry.fingerprint == fingerprint:
        return entry
    if len(_BVH_CACHE) > 256:
        for key in [k for k, e in _BVH_CACHE.items() if e.mesh_ref() is None]:
            del _BVH_CACHE[key]
    embree = rtcore_scene.EmbreeScene()
    TriangleMesh(embree, np.ascontiguousarray(vertices, dtype=np.float32), np.ascontiguousarray(faces, dtype=np.int32))
    try:
        with np.errstate(invalid="ignore", divide="ignore"):  # a flat mesh's hull: trimesh divides by its 0 volume
            hull = np.asarray(mesh.convex_hull.vertices, dtype=np.float64)
    except Exception:  # degenerate (flat) meshes: all vertices do
        hull = np.asarray(vertices, dtype=np.float64)
    centre = (hull.min(axis=0) + hull.max(axis=0)) / 2.0
    radius = float(np.sqrt(((np.asarray(vertices, dtype=np.float64) - centre) ** 2).sum(axis=1).max()))
    entry = _MeshBVH(weakref.ref(mesh), fingerprint, embree, hull, centre, radius)
    _BVH_CACHE[id(mesh)] = entry
    return entry


def cast(scene, intrinsics: Intrinsics, baseline_m: float, shadow_bias_m: float, shadows: bool = True) -> RayHits:
    """Ray-cast a :class:`~ddsgen.scene.sampling.FrameScene` for a pinhole camera.

    Args:
        scene: FrameScene (objects with id >= 1, background with id 0, ``world_T_cam``).
        intrinsics: image size and K (px); pixel centres at integer coordinates.
        baseline_m: projector offset b along the camera's +x axis (m).
        shadow_bias_m: shadow-ray origin offset xi along the normal (m).
        shadows: False skips the shadow rays (``RayHits.shadow`` is then None): for a view the sensor does
            not run on (the RGB camera of a registered device).

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

    polygons: list[tuple[int, Polygon]] = []  # (index into placed, polygon in the camera frame)
    meshes: list[tuple[int, np.ndarray, _MeshBVH, tuple | None]] = []  # (index, cam_T_obj, BVH, image box)
    for k, p in enumerate(placed):
        cam_T_obj = cam_T_world @ np.asarray(p.world_T_obj, dtype=np.float64)
        if p.id == 0 and len(p.mesh.faces) <= 64:
            polygon = as_polygon(*_camera_vertices(p, cam_T_world))
            if polygon is not None:
                polygons.append((k, polygon))
                continue
        bvh = _mesh_bvh(p.mesh)
        hull = bvh.hull @ cam_T_obj[:3, :3].T + cam_T_obj[:3, 3]
        meshes.append((k, cam_T_obj, bvh, _image_box(hull, intrinsics)))

    # --- primary rays: nearest of the analytic polygons and the meshes
    best_t = np.full((height, width), np.inf, dtype=np.float32)
    owner = np.full((height, width), -1, dtype=np.int32)
    for k, polygon in polygons:
        t = primary_depth(polygon, intrinsics)
        owner = np.where(t < best_t, np.int32(k), owner)
        best_t = np.minimum(best_t, t)
    best_t, owner = best_t.reshape(-1), owner.reshape(-1)
    # Normals: a plane seen from the origin shows one side (n . x = c, t > 0 -> sign(n . d) = sign(c)).
    table = np.zeros((len(placed) + 1, 3), dtype=np.float32)  # last row: no hit (owner -1)
    for k, polygon in polygons:
        table[k] = -polygon.normal if polygon.offset > 0 else polygon.normal
    is_mesh = np.zeros(len(placed) + 1, dtype=bool)
    mesh_normals = np.zeros((n_rays, 3), dtype=np.float32) if meshes else None
    triangle = np.full(n_rays, -1, dtype=np.int32)
    barycentric = np.zeros((n_rays, 2), dtype=np.float32)
    coverage: dict[int, int] = {}
    for k, cam_T_obj, bvh, box in meshes:
        # Rays go into the object frame (rotation only: t stays the depth); only rays in its image box can hit it.
        is_mesh[k] = True
        rays = _rays_in_box(box, width, height)
        if rays is None or not len(rays):
            coverage[placed[k].id] = 0
            continue
        R = cam_T_obj[:3, :3].astype(np.float32)
        origin = (-(cam_T_obj[:3, :3].T @ cam_T_obj[:3, 3])).astype(np.float32)
        d = directions[rays]
        result = bvh.embree.run(np.broadcast_to(origin, d.shape).copy(), d @ R, output=1)
        geom = result["geomID"]
        if placed[k].id > 0:
            coverage[placed[k].id] = int(np.count_nonzero(geom >= 0))
        closer = np.flatnonzero((geom >= 0) & (result["tfar"] < best_t[rays]))
        index = rays[closer]
        best_t[index] = result["tfar"][closer]
        owner[index] = k
        n = result["Ng"][closer] @ R.T
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), np.float32(1e-30))
        n[np.einsum("ij,ij->i", n, d[closer]) > 0] *= -1.0
        mesh_normals[index] = n
        triangle[index] = result["primID"][closer]
        barycentric[index, 0] = result["u"][closer]
        barycentric[index, 1] = result["v"][closer]
    # np.take, not table[owner]: several times faster for these small tables (owner -1 takes the last row)
    normals = np.take(table, owner, axis=0)
    if meshes:
        from_mesh = np.take(is_mesh, owner)
        normals[from_mesh] = mesh_normals[from_mesh]

    hit = owner >= 0
    depth = np.where(hit, best_t, np.float32(0.0))
    points = directions * depth[:, None]
    if polygons:  # coplanar faces: face 0's plane is the hit's plane (barycentrics left 0: not needed, not cheap)
        is_polygon = np.zeros(len(placed) + 1, dtype=bool)
        is_polygon[[k for k, _ in polygons]] = True
        triangle = np.where(np.take(is_polygon, owner), np.int32(0), triangle)
    ids = np.append(np.array([o.id for o in placed], dtype=np.uint16), np.uint16(0))
    albedos = np.append(np.array([o.albedo for o in placed], dtype=np.float32), np.float32(0.0))
    instance = np.take(ids, owner)
    albedo = np.take(albedos, owner)

    shadow = None
    if shadows:
        shadow = _shadow_rays(points, normals, hit, polygons, meshes, intrinsics, baseline_m, shadow_bias_m)

    shape2, shape3 = (height, width), (height, width, 3)
    return RayHits(
        depth=depth.reshape(shape2),
        points=points.reshape(shape3),
        normals=normals.reshape(shape3),
        instance=instance.reshape(shape2),
        hit=hit.reshape(shape2),
        shadow=None if shadow is None else shadow.reshape(shape2),
        albedo=albedo.reshape(shape2),
        coverage=coverage,
        owner=owner.reshape(shape2),
        triangle=triangle.reshape(shape2),
        barycentric=barycentric.reshape(height, width, 2),
    )


def _shadow_rays(points, normals, hit, polygons, meshes, intrinsics: Intrinsics, baseline_m: float,
                 shadow_bias_m: float) -> np.ndarray:  # fmt: skip
    """(H*W,) bool: hit points the projector at (+b, 0, 0) does not see (facing away, or a segment from the
    biased point S towards the projector, capped before it, crosses a polygon or mesh). ``points``, ``normals``:
    (H*W, 3) float32 in the camera frame; ``hit`` (H*W,) bool."""
    # Computed on all pixels (no gathers) and masked with `hit` at the end.
    projector = np.array([baseline_m, 0.0, 0.0], dtype=np.float64)
    start = points + np.float32(shadow_bias_m) * normals
    # surface facing away from the projector: n . (t_p - P) <= 0
    n_dot_p = normals[:, 0] * points[:, 0] + normals[:, 1] * points[:, 1] + normals[:, 2] * points[:, 2]
    blocked = normals[:, 0] * np.float32(baseline_m) - n_dot_p <= 0.0
    for _, polygon in polygons:
        blocked |= segments_blocked(polygon, start, projector)
    if meshes:
        # The segment S -> projector projects onto image row v_S, columns u >= u_S (a half-line), so it can only
        # meet a mesh whose projected box spans that row to the right of u_S (exact, conservative cull).
        with np.errstate(divide="ignore", invalid="ignore"):
            inv_z = np.float32(1.0) / start[:, 2]
            u_s = start[:, 0] * inv_z * np.float32(intrinsics.fx) + np.float32(intrinsics.cx)
            v_s = start[:, 1] * inv_z * np.float32(intrinsics.fy) + np.float32(intrinsics.cy)
        open_rays = hit & ~blocked
        start_xyz = [np.ascontiguousarray(start[:, axis]) for axis in range(3)]  # 1-D gathers for the sphere cull
        no_cull = open_rays & ~(start[:, 2] > 0)  # start at/behind the camera plane (or nan): no cull
        for k, cam_T_obj, bvh, box in meshes:
            if box is None:
                todo = np.flatnonzero(open_rays)
            else:
                u0, v0, u1, v1 = box
                todo = np.flatnonzero(
                    (open_rays & (v_s >= v0 - 1.0) & (v_s <= v1 + 1.0) & (u_s <= u1 + 1.0)) | no_cull
                )
            if not len(todo):
                continue
            todo = todo[_segments_near_sphere(*(axis[todo] for axis in start_xyz), np.float32(baseline_m),
                                              cam_T_obj[:3, :3] @ bvh.centre + cam_T_obj[:3, 3], bvh.radius)]  # fmt: skip
            if not len(todo):
                continue
            R = cam_T_obj[:3, :3].astype(np.float32)
            s = start[todo]
            occluded = bvh.embree.run(
                np.ascontiguousarray((s - cam_T_obj[:3, 3].astype(np.float32)) @ R),
                np.ascontiguousarray((projector.astype(np.float32)[None, :] - s) @ R),
                dists=np.full(len(todo), 1.0 - 1e-6, dtype=np.float32),
                query="OCCLUDED",
            )
            blocked[todo] |= occluded >= 0
            open_rays[todo] &= ~(occluded >= 0)
    return blocked & hit


def _segments_near_sphere(x: np.ndarray, y: np.ndarray, z: np.ndarray, projector_x: np.float32, centre: np.ndarray,
                          radius: float) -> np.ndarray:  # fmt: skip
    """(M,) bool: the segments from the points (x, y, z) (float32 (M,) each, camera frame) to the projector at
    (projector_x, 0, 0) that come within ``radius`` (plus a margin far above float32 rounding) of ``centre``: the
    only ones that can meet a mesh inside that sphere (an exact cull: Embree is asked about the others for nothing).
    Written per coordinate: numpy's sums over a length-3 axis are several times slower."""
    ax, ay, az = projector_x - x, -y, -z  # along the segment
    cx, cy, cz = (np.float32(c) for c in centre)
    tx, ty, tz = cx - x, cy - y, cz - z  # to the centre
    length_sq = np.maximum(ax * ax + ay * ay + az * az, np.float32(1e-30))
    fraction = np.clip((tx * ax + ty * ay + tz * az) / length_sq, np.float32(0.0), np.float32(1.0))
    gx, gy, gz = tx - fraction * ax, ty - fraction * ay, tz - fraction * az
    reach = np.float32(radius * (1.0 + 1e-3) + 1e-4)
    return gx * gx + gy * gy + gz * gz <= reach * reach


def _image_box(vertices_cam: np.ndarray, intrinsics: Intrinsics):
    """Continuous pixel box (u0, v0, u1, v1) of the projection of a mesh entirely in front of the camera;
    None if some vertex is at or behind the camera plane (then no image-space cull is valid)."""
    z = vertices_cam[:, 2].astype(np.float64)
    if not np.all(z > 1e-6):
        return None
    u = intrinsics.fx * vertices_cam[:, 0] / z + intrinsics.cx
    v = intrinsics.fy * vertices_cam[:, 1] / z + intrinsics.cy
    return float(u.min()) - 0.5, float(v.min()) - 0.5, float(u.max()) + 0.5, float(v.max()) + 0.5


def _rays_in_box(box, width: int, height: int) -> np.ndarray | None:
    """Flat indices of the pixels whose centres lie in a continuous box (all pixels for None)."""
    if box is None:
        return np.arange(width * height)
    u0, v0, u1, v1 = box
    iu0, iv0 = max(int(np.ceil(u0)), 0), max(int(np.ceil(v0)), 0)
    iu1, iv1 = min(int(np.floor(u1)), width - 1), min(int(np.floor(v1)), height - 1)
    if iu0 > iu1 or iv0 > iv1:
        return np.empty(0, dtype=np.int64)
    cols = np.arange(iu0, iu1 + 1)
    rows = np.arange(iv0, iv1 + 1)
    return (rows[:, None] * width + cols[None, :]).reshape(-1)


def _alone_pixel_count(placed, cam_T_world: np.ndarray, intrinsics: Intrinsics) -> int:
    """Pixels the object covers when ray-cast alone (only rays inside its projected box are cast)."""
    cam_T_obj = cam_T_world @ np.asarray(placed.world_T_obj, dtype=np.float64)
    bvh = _mesh_bvh(placed.mesh)
    box = _image_box(bvh.hull @ cam_T_obj[:3, :3].T + cam_T_obj[:3, 3], intrinsics)
    rays = _rays_in_box(box, int(intrinsics.width), int(intrinsics.height))
    if not len(rays):
        return 0
    R = cam_T_obj[:3, :3].astype(np.float32)
    d = ray_directions(intrinsics).reshape(-1, 3)[rays] @ R
    origin = (-(cam_T_obj[:3, :3].T @ cam_T_obj[:3, 3])).astype(np.float32)
    geom = bvh.embree.run(np.broadcast_to(origin, d.shape).copy(), d, query="OCCLUDED")  # any hit will do
    return int(np.count_nonzero(geom >= 0))


def object_labels(scene, hits: RayHits, intrinsics: Intrinsics) -> list[dict]:
    """Manifest ``objects`` entries, one per placed object (ids ascending).

    Each: ``id``, ``mesh`` (mesh_ref), ``class``, ``cam_T_obj`` (4x4 nested list, metres, maps the mesh in
    metres = file units x ``mesh_scale``), ``mesh_scale``, ``bbox`` [x, y, w, h] of the visible mask pixels
    ([0, 0, 0, 0] when not visible; like BOP's bbox_visib), ``visible_fraction`` = visible pixels / pixels the
    object would cover alone (0 when it is out of view).
    """
    cam_T_world = np.linalg.inv(np.asarray(scene.world_T_cam, dtype=np.float64))
    instance = np.asarray(hits.instance)
    width = instance.shape[1]
    # one pass over the object pixels: per id, the pixel count and the min / max row and column
    flat = np.flatnonzero(instance.reshape(-1))
    ids = instance.reshape(-1)[flat]
    order = np.argsort(ids, kind="stable")
    flat, ids = flat[order], ids[order]
    present, first, counts = np.unique(ids, return_index=True, return_counts=True)
    rows, cols = flat // width, flat % width
    stats = {}
    if len(present):
        stats = dict(
            zip(
                present.tolist(),
                zip(
                    counts.tolist(),
                    np.minimum.reduceat(cols, first).tolist(),
                    np.minimum.reduceat(rows, first).tolist(),
                    np.maximum.reduceat(cols, first).tolist(),
                    np.maximum.reduceat(rows, first).tolist(),
                ),
            )
        )
    labels = []
    for placed in sorted(scene.objects, key=lambda o: o.id):
        visible = 0
        bbox = [0, 0, 0, 0]
        if placed.id in stats:
            visible, x0, y0, x1, y1 = stats[placed.id]
            bbox = [int(x0), int(y0), int(x1 - x0 + 1), int(y1 - y0 + 1)]
        fraction = 0.0
        if visible:
            alone = hits.coverage.get(placed.id) if hits.coverage else None
            if alone is None:
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
