"""Ray casting: clean depth, hit points, normals, instance ids, projector shadow.

Primary rays use the *unnormalised* directions ``K^-1 [u, v, 1]`` (z = 1), so the hit
parameter ``t`` is the depth z itself. Pixel centres are at integer ``(u, v)`` (OpenCV).

* Planar convex background pieces (ground, table top, walls, floor) are intersected analytically
  (ddsgen/raycast_planes.py); a BVH holding the huge ground triangles slows every ray.
* Every other mesh: the C raster (ddsgen/raster.py) ray-casts the pixel centres inside each triangle's
  projection, several times faster than embreex's per-ray calls; without a C compiler, Embree
  (ddsgen/raycast_embree.py: one BVH per mesh, exact culls). Both give the same hits (tests/test_raster.py).

Projector shadow: from each hit point P (camera frame), offset by the shadow bias ``xi``
along the camera-facing normal, one segment towards the projector centre, capped just before
it. ``shadow`` is True where that segment is blocked or where the surface faces away from the
projector (n . (t_p - P) <= 0). No per-pixel Python loops.
"""

from __future__ import annotations

import dataclasses
import functools

import numpy as np

from ddsgen.preset import Intrinsics
from ddsgen.raster import (NEAR_CLIP_M, hit_attributes, raster_available, raster_hits, raster_meshes, raster_shadow,
                           take_rows)
from ddsgen.raycast_embree import MeshBVH, image_box, mesh_bvh, primary_hits_embree, rays_in_box, shadow_blocked_embree
from ddsgen.raycast_planes import Polygon, as_polygon, segments_blocked, write_primary_depth


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

    def columns(self, start: int, stop: int) -> "RayHits":
        """Image columns ``start:stop`` (contiguous copies). Rays are cast one per pixel, so this equals a cast of
        those columns alone, pixel for pixel, except ``coverage`` (counted over the whole cast): left empty."""
        part = {}
        for field in dataclasses.fields(self):
            value = getattr(self, field.name)
            if isinstance(value, np.ndarray):
                value = np.ascontiguousarray(value[:, start:stop])
            part[field.name] = value
        return RayHits(**{**part, "coverage": {}})


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
    meshes: list[tuple[int, np.ndarray, MeshBVH, tuple | None]] = []  # (index, cam_T_obj, BVH, image box)
    for k, p in enumerate(placed):
        cam_T_obj = cam_T_world @ np.asarray(p.world_T_obj, dtype=np.float64)
        if p.id == 0 and len(p.mesh.faces) <= 64:
            polygon = as_polygon(*_camera_vertices(p, cam_T_world))
            if polygon is not None:
                polygons.append((k, polygon))
                continue
        bvh = mesh_bvh(p.mesh)
        hull = bvh.hull @ cam_T_obj[:3, :3].T + cam_T_obj[:3, 3]
        meshes.append((k, cam_T_obj, bvh, image_box(hull, intrinsics)))

    # --- primary rays: nearest of the analytic polygons and the meshes
    best_t = np.full((height, width), np.inf, dtype=np.float32)
    owner = np.full((height, width), -1, dtype=np.int32)
    for k, polygon in polygons:  # on the rows each spans (the others miss it)
        write_primary_depth(polygon, intrinsics, k, best_t, owner)
    best_t, owner = best_t.reshape(-1), owner.reshape(-1)
    # Normals: a plane seen from the origin shows one side (n . x = c, t > 0 -> sign(n . d) = sign(c)).
    table = np.zeros((len(placed) + 1, 3), dtype=np.float32)  # last row: no hit (owner -1)
    for k, polygon in polygons:
        table[k] = -polygon.normal if polygon.offset > 0 else polygon.normal
    # The polygons' normals (no hit: 0, the last row); a mesh writes its own where it is nearer.
    normals = take_rows(table, owner)
    triangle = np.full(n_rays, -1, dtype=np.int32)
    barycentric = np.zeros((n_rays, 2), dtype=np.float32)
    camera_meshes = None  # the meshes in the camera frame (RasterMeshes) when the C raster casts them
    if meshes and raster_available():
        camera_meshes = raster_meshes([(k, *_camera_vertices(placed[k], cam_T_world)) for k, _, _, _ in meshes])
        alone = raster_hits(camera_meshes, intrinsics, best_t, owner, triangle, barycentric, normals)
        coverage = {placed[k].id: n for k, n in alone.items() if placed[k].id > 0}
    else:  # no C compiler: Embree
        coverage = primary_hits_embree(meshes, placed, directions, width, height, best_t, owner, triangle, barycentric,
                                       normals)  # fmt: skip

    # Per-owner tables, the last entry for no hit. A polygon's hits name face 0 (coplanar faces: face 0's plane is
    # the hit's plane; barycentrics left 0: not needed, not cheap).
    is_polygon = np.zeros(len(placed) + 1, dtype=bool)
    is_polygon[[k for k, _ in polygons]] = True
    ids = np.append(np.array([o.id for o in placed], dtype=np.uint16), np.uint16(0))
    albedos = np.append(np.array([o.albedo for o in placed], dtype=np.float32), np.float32(0.0))
    hit, depth, points, instance, albedo = hit_attributes(owner, best_t, directions, triangle, ids, albedos, is_polygon)

    shadow = None
    if shadows:
        shadow = _shadow_rays(points, normals, hit, polygons, meshes, camera_meshes, intrinsics, baseline_m,
                              shadow_bias_m)

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


def _shadow_rays(points, normals, hit, polygons, meshes, camera_meshes, intrinsics: Intrinsics, baseline_m: float,
                 shadow_bias_m: float) -> np.ndarray:  # fmt: skip
    """(H*W,) bool: hit points the projector at (+b, 0, 0) does not see (facing away, or a segment from the
    biased point S towards the projector, capped before it, crosses a polygon or mesh). ``points``, ``normals``:
    (H*W, 3) float32 in the camera frame; ``hit`` (H*W,) bool. ``camera_meshes``: the meshes in the camera
    frame for the C raster (:class:`ddsgen.raster.RasterMeshes`, built once by :func:`cast`), or None: Embree tests
    every segment."""
    # Computed on all pixels (no gathers) and masked with `hit` at the end.
    projector = np.array([baseline_m, 0.0, 0.0], dtype=np.float64)
    start = points + np.float32(shadow_bias_m) * normals
    # surface facing away from the projector: n . (t_p - P) <= 0
    n_dot_p = normals[:, 0] * points[:, 0] + normals[:, 1] * points[:, 1] + normals[:, 2] * points[:, 2]
    blocked = normals[:, 0] * np.float32(baseline_m) - n_dot_p <= 0.0
    for _, polygon in polygons:
        blocked |= segments_blocked(polygon, start, projector)
    if not meshes:
        return blocked & hit
    open_rays = hit & ~blocked
    if camera_meshes is not None:
        # The raster takes the segments that start in front of the camera plane; Embree any others (or nan).
        near = open_rays & ~(start[:, 2] >= np.float32(NEAR_CLIP_M))
        ahead = np.flatnonzero(open_rays & ~near)
        blocked |= raster_shadow(camera_meshes, start, baseline_m, intrinsics, rays=ahead)
        open_rays = near
    if open_rays.any():
        blocked |= shadow_blocked_embree(start, open_rays, meshes, intrinsics, projector)
    return blocked & hit


def _alone_pixel_count(placed, cam_T_world: np.ndarray, intrinsics: Intrinsics) -> int:
    """Pixels the object covers when ray-cast alone (only rays inside its projected box are cast)."""
    cam_T_obj = cam_T_world @ np.asarray(placed.world_T_obj, dtype=np.float64)
    bvh = mesh_bvh(placed.mesh)
    box = image_box(bvh.hull @ cam_T_obj[:3, :3].T + cam_T_obj[:3, 3], intrinsics)
    rays = rays_in_box(box, int(intrinsics.width), int(intrinsics.height))
    if not len(rays):
        return 0
    R = cam_T_obj[:3, :3].astype(np.float32)
    d = ray_directions(intrinsics).reshape(-1, 3)[rays] @ R
    origin = (-(cam_T_obj[:3, :3].T @ cam_T_obj[:3, 3])).astype(np.float32)
    geom = bvh.embree.run(np.broadcast_to(origin, d.shape).copy(), d, query="OCCLUDED")  # any hit will do
    return int(np.count_nonzero(geom >= 0))


def object_labels(scene, hits: RayHits, intrinsics: Intrinsics, instance: np.ndarray | None = None) -> list[dict]:
    """Manifest ``objects`` entries, one per placed object (ids ascending); ``instance``: the (H, W) instance ids the
    masks are written from, when not the cast's own (a warped pixel grid).

    Each: ``id``, ``mesh`` (mesh_ref), ``class``, ``cam_T_obj`` (4x4 nested list, metres, maps the mesh in
    metres = file units x ``mesh_scale``), ``mesh_scale``, ``bbox`` [x, y, w, h] of the visible mask pixels
    ([0, 0, 0, 0] when not visible; like BOP's bbox_visib), ``visible_fraction`` = visible pixels / pixels the
    object would cover alone (0 when it is out of view).
    """
    cam_T_world = np.linalg.inv(np.asarray(scene.world_T_cam, dtype=np.float64))
    instance = np.asarray(hits.instance if instance is None else instance)
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
