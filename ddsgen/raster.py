"""Primary hits of a pinhole camera on triangle meshes by an exact ray-cast raster (csrc/raster.c).

:func:`raster_hits` walks each triangle's projected bounding box (of its part in front of the camera) and ray-casts the pixel centres inside it (Moller-Trumbore, double precision): the same
hits as Embree's rays through those pixels (depth within float32 rounding; a pixel on an edge shared by
two faces may name the other face), several times faster, because embreex pays a Python-level cost per
ray. :mod:`ddsgen.raycast` uses it for its primary rays and keeps Embree for the shadow segments. Without a C compiler (or with ``DDSGEN_NO_C_KERNEL``)
:func:`raster_available` is False and Embree casts every ray.
"""

from __future__ import annotations

import ctypes
import dataclasses
import functools

import numpy as np

from ddsgen.ckernel import c_source, load_c_library
from ddsgen.preset import Intrinsics


@functools.cache
def _library():
    """The compiled raster (once per process), or None without a C compiler or with ``DDSGEN_NO_C_KERNEL``."""
    # No -march=native and no FMA contraction: the same hits on every x86-64 CPU.
    flags = ["-O2", "-ffp-contract=off", "-fPIC", "-shared", "-std=gnu11"]
    lib = load_c_library(c_source("ddsgen", "csrc", "raster.c"), "raster", flags, "ray caster", "Embree path")
    if lib is not None:
        p, i, d, q = ctypes.c_void_p, ctypes.c_int, ctypes.c_double, ctypes.c_int64
        lib.ddsgen_raster_hits.argtypes = [p, p, p, p, i, i, i, d, d, d, d, p, p, p, p, p, p, p]
        lib.ddsgen_raster_hits.restype = None
        lib.ddsgen_raster_shadow.argtypes = [p, p, q, p, p, q, d, d, d, d, d, p, p]
        lib.ddsgen_raster_shadow.restype = ctypes.c_int
        lib.ddsgen_take_rows.argtypes = [p, q, q, p, q, p]
        lib.ddsgen_take_rows.restype = None
        lib.ddsgen_hit_attributes.argtypes = [p, p, p, q, p, p, p, q, p, p, p, p, p, p]
        lib.ddsgen_hit_attributes.restype = None
        lib.ddsgen_plane_zbuffer.argtypes = [ctypes.c_float, p, p, p, p, q, q, q, ctypes.c_int32, p, p]
        lib.ddsgen_plane_zbuffer.restype = None
    return lib


def _required_library():
    lib = _library()
    if lib is None:
        raise RuntimeError("the C ray caster is unavailable (no C compiler, or DDSGEN_NO_C_KERNEL is set)")
    return lib


def raster_available() -> bool:
    """True when the C raster is compiled and loaded (else the caller casts every ray with Embree)."""
    return _library() is not None


#: Shadow-segment starts nearer than this to the camera plane (m) are the caller's (csrc/raster.c NEAR_CLIP_M).
NEAR_CLIP_M = 1e-4
#: csrc/raster.c's CELLS_PER_POINT: the projector-image grid has at most this many cells per start point.
_CELLS_PER_POINT = 4


@dataclasses.dataclass(frozen=True)
class RasterMeshes:
    """Meshes in one camera's frame, concatenated for the kernels (built once per cast: both kernels read it)."""

    vertices: np.ndarray  # float32 (V, 3), camera frame (m)
    faces: np.ndarray  # int32 (F, 3), rows of ``vertices``
    face_start: np.ndarray  # int64 (M + 1,): mesh m owns faces face_start[m] .. face_start[m + 1] - 1
    owners: np.ndarray  # int32 (M,): the owner index written for each mesh's hits


def raster_meshes(meshes: list[tuple[int, np.ndarray, np.ndarray]]) -> RasterMeshes:
    """``(owner index, vertices, faces)`` per mesh (float32 (V, 3) in the camera frame, int32 (F, 3)), drawn in this
    order (a tie keeps the earlier hit), as one :class:`RasterMeshes`."""
    if not meshes:
        empty = np.zeros((0, 3))
        return RasterMeshes(empty.astype(np.float32), empty.astype(np.int32), np.zeros(1, np.int64), np.zeros(0, np.int32))
    offsets = np.cumsum([0] + [len(v) for _, v, _ in meshes[:-1]])
    return RasterMeshes(
        vertices=np.ascontiguousarray(np.concatenate([v for _, v, _ in meshes]), dtype=np.float32),
        faces=np.ascontiguousarray(np.concatenate([f + o for (_, _, f), o in zip(meshes, offsets)]), dtype=np.int32),
        face_start=np.cumsum([0] + [len(f) for _, _, f in meshes]).astype(np.int64),
        owners=np.array([k for k, _, _ in meshes], dtype=np.int32),
    )


def raster_hits(meshes: RasterMeshes, intrinsics: Intrinsics, depth: np.ndarray,
                owner: np.ndarray, triangle: np.ndarray, barycentric: np.ndarray, normals: np.ndarray) -> dict[int, int]:
    """Cast the pixel-centre rays at ``meshes`` into the per-pixel buffers, in place; return the pixels each
    mesh covers alone.

    Args:
        meshes: :func:`raster_meshes` in the camera frame.
        intrinsics: the camera (pixel centres at integer (u, v)).
        depth: float32 (H*W,) nearest depth so far (m, inf = none); replaced where a mesh is nearer.
        owner: int32 (H*W,) owner index of that nearest surface (-1 = none).
        triangle: int32 (H*W,) face index in the owner's mesh; barycentric: float32 (H*W, 2) Embree's (u, v)
            on that face; normals: float32 (H*W, 3) unit geometric normal facing the camera. Written where a
            mesh wins, untouched elsewhere.

    Returns:
        {owner index: pixels whose ray hits that mesh when it is cast alone}.
    """
    lib = _required_library()
    if not len(meshes.owners):
        return {}
    for name, array, dtype in (("depth", depth, np.float32), ("owner", owner, np.int32), ("triangle", triangle, np.int32),
                               ("barycentric", barycentric, np.float32), ("normals", normals, np.float32)):  # fmt: skip
        if array.dtype != dtype or not array.flags.c_contiguous:
            raise ValueError(f"raster_hits: {name} must be a C-contiguous {np.dtype(dtype).name} array")
    if depth.shape[0] != int(intrinsics.width) * int(intrinsics.height):
        raise ValueError(f"raster_hits: buffers hold {depth.shape[0]} pixels, the image {intrinsics.width}x{intrinsics.height}")
    m = meshes
    coverage = np.zeros(len(m.owners), dtype=np.int64)
    stamp = np.full(depth.shape[0], -1, dtype=np.int32)
    i = intrinsics
    lib.ddsgen_raster_hits(m.vertices.ctypes.data, m.faces.ctypes.data, m.face_start.ctypes.data, m.owners.ctypes.data,
                           len(m.owners), int(i.width), int(i.height), float(i.fx), float(i.fy), float(i.cx),
                           float(i.cy), depth.ctypes.data, owner.ctypes.data, triangle.ctypes.data,
                           barycentric.ctypes.data, normals.ctypes.data, coverage.ctypes.data, stamp.ctypes.data)  # fmt: skip
    return dict(zip(m.owners.tolist(), coverage.tolist()))


def raster_shadow(meshes: RasterMeshes, starts: np.ndarray, projector_x_m: float, intrinsics: Intrinsics,
                  rays: np.ndarray | None = None) -> np.ndarray:  # fmt: skip
    """(M,) bool: the segments from ``starts`` to the projector at (``projector_x_m``, 0, 0) that cross a mesh.

    ``meshes`` as for :func:`raster_hits`; ``starts``: float32 (M, 3), camera frame, every z >= NEAR_CLIP_M.
    ``rays``: int64 indices into ``starts`` of the only segments to test (the others come out False; no copy of
    their starts is made), or None for all. Exact: the segments are bucketed by where they project in the
    projector's image (a camera at the projector with the camera's orientation and intrinsics) and each triangle
    tests the buckets its projection covers.
    """
    lib = _required_library()
    starts = np.ascontiguousarray(starts, dtype=np.float32)
    blocked = np.zeros(len(starts), dtype=np.uint8)
    if rays is not None:
        rays = np.ascontiguousarray(rays, dtype=np.int64)
    n_rays = len(starts) if rays is None else len(rays)
    if not len(meshes.faces) or not n_rays:
        return blocked.view(bool)
    scratch = np.empty((2 + _CELLS_PER_POINT) * n_rays + 2, dtype=np.int64)
    i = intrinsics
    status = lib.ddsgen_raster_shadow(meshes.vertices.ctypes.data, meshes.faces.ctypes.data, len(meshes.faces),
                                      starts.ctypes.data, None if rays is None else rays.ctypes.data,
                                      n_rays, float(projector_x_m), float(i.fx), float(i.fy), float(i.cx),
                                      float(i.cy), blocked.ctypes.data, scratch.ctypes.data)  # fmt: skip
    if status == -2:
        raise MemoryError("raster_shadow: out of memory")
    if status != 0:
        raise ValueError(f"raster_shadow: a segment starts nearer than {NEAR_CLIP_M} m to the camera plane")
    return blocked.view(bool)


def take_rows(table: np.ndarray, owner: np.ndarray) -> np.ndarray:
    """``np.take(table, owner, axis=0)`` for a float32 (R, C) table and int32 owners (-1 reads the last row), in one
    C pass where the raster is compiled (same values)."""
    lib = _library()
    table = np.ascontiguousarray(table, dtype=np.float32)
    if lib is None or owner.dtype != np.int32:
        return np.take(table, owner, axis=0)
    owner = np.ascontiguousarray(owner)
    out = np.empty((len(owner), table.shape[1]), dtype=np.float32)
    lib.ddsgen_take_rows(table.ctypes.data, table.shape[0], table.shape[1], owner.ctypes.data, len(owner),
                         out.ctypes.data)  # fmt: skip
    return out


def hit_attributes(owner: np.ndarray, best_t: np.ndarray, directions: np.ndarray, triangle: np.ndarray,
                   ids: np.ndarray, albedos: np.ndarray, is_polygon: np.ndarray):  # fmt: skip
    """``(hit, depth, points, instance, albedo)`` of the primary hits (N,) from their owners (int32, -1: none), ray
    parameters ``best_t`` (float32) and ``directions`` (float32 (N, 3), z = 1); ``triangle`` (int32) is set to 0 in
    place where the owner is a polygon. ``ids`` (uint16), ``albedos`` (float32), ``is_polygon`` (bool): per owner,
    plus a last entry for no hit. One C pass where the raster is compiled, numpy otherwise (same values)."""
    lib = _library()
    if lib is None:
        hit = owner >= 0
        depth = np.where(hit, best_t, np.float32(0.0))
        triangle[np.take(is_polygon, owner)] = 0
        return hit, depth, directions * depth[:, None], np.take(ids, owner), np.take(albedos, owner)
    n = len(owner)
    hit, depth = np.empty(n, dtype=bool), np.empty(n, dtype=np.float32)
    points, instance, albedo = np.empty((n, 3), np.float32), np.empty(n, np.uint16), np.empty(n, np.float32)
    arrays = [np.ascontiguousarray(a, dtype=t) for a, t in ((owner, np.int32), (best_t, np.float32),
                                                             (directions, np.float32))]  # fmt: skip
    tables = [np.ascontiguousarray(ids, np.uint16), np.ascontiguousarray(albedos, np.float32),
              np.ascontiguousarray(is_polygon, bool)]  # fmt: skip
    if not triangle.flags.c_contiguous or triangle.dtype != np.int32:
        raise ValueError("hit_attributes: triangle must be a C-contiguous int32 array")
    lib.ddsgen_hit_attributes(*(a.ctypes.data for a in arrays), n, *(t.ctypes.data for t in tables), len(ids),
                              hit.ctypes.data, depth.ctypes.data, points.ctypes.data, triangle.ctypes.data,
                              instance.ctypes.data, albedo.ctypes.data)  # fmt: skip
    return hit, depth, points, instance, albedo


def plane_zbuffer(offset: float, row_term: np.ndarray, col_term: np.ndarray, lo: np.ndarray, hi: np.ndarray, v0: int,
                  index: int, best_t: np.ndarray, owner: np.ndarray) -> bool:  # fmt: skip
    """A planar polygon's primary hits into the z-buffer ``best_t`` / ``owner`` ((H, W) float32 / int32, in place)
    in one C pass (:func:`ddsgen.raycast_planes.write_primary_depth` describes the terms). False, with nothing
    written, where the raster is not compiled."""
    lib = _library()
    if lib is None:
        return False
    if not (best_t.flags.c_contiguous and owner.flags.c_contiguous and best_t.dtype == np.float32
            and owner.dtype == np.int32 and best_t.shape == owner.shape):  # fmt: skip
        raise ValueError("plane_zbuffer: best_t and owner must be C-contiguous (H, W) float32 and int32 arrays")
    row_term, col_term = np.ascontiguousarray(row_term, np.float32), np.ascontiguousarray(col_term, np.float32)
    lo, hi = np.ascontiguousarray(lo, np.float64), np.ascontiguousarray(hi, np.float64)
    lib.ddsgen_plane_zbuffer(float(np.float32(offset)), row_term.ctypes.data, col_term.ctypes.data, lo.ctypes.data,
                             hi.ctypes.data, int(v0), len(row_term), best_t.shape[1], int(index), best_t.ctypes.data,
                             owner.ctypes.data)  # fmt: skip
    return True
