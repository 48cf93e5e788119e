"""Ray casting with Embree (embreex), one BVH per mesh in its own object frame, with exact image-space culls.

Each mesh's BVH is built once per process and cached; rays are rotated into the object frame (``t`` is
unchanged, so it stays the depth for the primary rays ``K^-1 [u, v, 1]``). Exact culls:

* a mesh can only be hit by primary rays inside its projected box;
* a shadow segment S -> projector (+b, 0, 0) projects onto image row v_S for u >= u_S, so it can only meet a
  mesh whose box spans that row to the right of u_S; nor a mesh whose bounding sphere it passes by.

:func:`ddsgen.raycast.cast` uses the C raster (ddsgen/raster.py) for the primary rays and the shadow segments
when it is built, and these functions where it is not (no C compiler); object labels cast an object alone here.
(embreex's ``run`` does not release the GIL in this build: threads do not help.)
"""

from __future__ import annotations

import dataclasses
import weakref

import numpy as np

from ddsgen.preset import Intrinsics


@dataclasses.dataclass
class MeshBVH:
    mesh_ref: "weakref.ref"
    fingerprint: tuple
    embree: object  # EmbreeScene with the mesh in its own object frame
    hull: np.ndarray  # (K, 3) float64 convex-hull vertices (for image boxes)
    centre: np.ndarray  # (3,) float64 centre of the hull's bounding box (object frame) ...
    radius: float  # ... and the radius of the sphere about it that holds every vertex (m)


_BVH_CACHE: dict[int, MeshBVH] = {}


def mesh_bvh(mesh) -> MeshBVH:
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
    entry = MeshBVH(weakref.ref(mesh), fingerprint, embree, hull, centre, radius)
    _BVH_CACHE[id(mesh)] = entry
    return entry


def primary_hits_embree(meshes, placed, directions: np.ndarray, width: int, height: int, best_t: np.ndarray,
                        owner: np.ndarray, triangle: np.ndarray, barycentric: np.ndarray,
                        normals: np.ndarray) -> dict[int, int]:  # fmt: skip
    """Cast the primary rays at ``meshes`` (``(index into placed, cam_T_obj, BVH, image box)``) into the per-pixel
    buffers (flat, (H*W,) / (H*W, k); as :func:`ddsgen.raster.raster_hits`), in place; ``directions`` (H*W, 3).
    Returns {object id >= 1: pixels it covers when cast alone}."""
    coverage: dict[int, int] = {}
    for k, cam_T_obj, bvh, box in meshes:
        # Rays go into the object frame (rotation only: t stays the depth); only rays in its image box can hit it.
        rays = rays_in_box(box, width, height)
        if rays is None or not len(rays):
            if placed[k].id > 0:
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
        normals[index] = n
        triangle[index] = result["primID"][closer]
        barycentric[index, 0] = result["u"][closer]
        barycentric[index, 1] = result["v"][closer]
    return coverage


def shadow_blocked_embree(start: np.ndarray, open_rays: np.ndarray, meshes, intrinsics: Intrinsics,
                          projector: np.ndarray) -> np.ndarray:  # fmt: skip
    """(H*W,) bool: which of the ``open_rays`` segments ``start`` (H*W, 3) -> ``projector`` (3,) Embree finds
    blocked by a mesh (one object-frame BVH per mesh, with exact culls)."""
    blocked = np.zeros(len(start), dtype=bool)
    open_rays = open_rays.copy()
    baseline_m = float(projector[0])
    # The segment S -> projector projects onto image row v_S, columns u >= u_S (a half-line), so it can only
    # meet a mesh whose projected box spans that row to the right of u_S (exact, conservative cull).
    with np.errstate(divide="ignore", invalid="ignore"):
        inv_z = np.float32(1.0) / start[:, 2]
        u_s = start[:, 0] * inv_z * np.float32(intrinsics.fx) + np.float32(intrinsics.cx)
        v_s = start[:, 1] * inv_z * np.float32(intrinsics.fy) + np.float32(intrinsics.cy)
    start_xyz = [np.ascontiguousarray(start[:, axis]) for axis in range(3)]  # 1-D gathers for the sphere cull
    no_cull = open_rays & ~(start[:, 2] > 0)  # start at/behind the camera plane (or nan): no cull
    for k, cam_T_obj, bvh, box in meshes:
        if box is None:
            todo = np.flatnonzero(open_rays)
        else:
            u0, v0, u1, v1 = box
            todo = np.flatnonzero((open_rays & (v_s >= v0 - 1.0) & (v_s <= v1 + 1.0) & (u_s <= u1 + 1.0)) | no_cull)
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
    return blocked


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


def image_box(vertices_cam: np.ndarray, intrinsics: Intrinsics):
    """Continuous pixel box (u0, v0, u1, v1) of the projection of a mesh entirely in front of the camera;
    None if some vertex is at or behind the camera plane (then no image-space cull is valid)."""
    z = vertices_cam[:, 2].astype(np.float64)
    if not np.all(z > 1e-6):
        return None
    u = intrinsics.fx * vertices_cam[:, 0] / z + intrinsics.cx
    v = intrinsics.fy * vertices_cam[:, 1] / z + intrinsics.cy
    return float(u.min()) - 0.5, float(v.min()) - 0.5, float(u.max()) + 0.5, float(v.max()) + 0.5


def rays_in_box(box, width: int, height: int) -> np.ndarray | None:
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
