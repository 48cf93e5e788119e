"""Resting poses and footprints of the objects a layout drops (:mod:`ddsgen.scene.sampling`).

A mesh rests on the ground in one of its stable poses (or upright, as modelled); seen from above its convex hull
gives a 2-D footprint, a convex polygon. Two footprints keep a gap when the separating-axis test finds an edge
normal along which they are that far apart. The poses are cached per process and per mesh (the stable poses also on
disk: :mod:`ddsgen.scene.stable_poses`); each pose's footprint is computed when a layout first draws it.
"""

from __future__ import annotations

import dataclasses
import functools

import numpy as np

from ddsgen.scene.meshes import load_mesh
from ddsgen.scene.stable_poses import stable_poses


@dataclasses.dataclass(frozen=True)
class RestPose:
    """One resting pose of a mesh. Its offset and footprint are computed when a layout first draws it: a mesh
    can have hundreds of stable poses (a tessellated torus), and a 2-D convex hull for each of them cost ~0.2 s
    per mesh in every worker (most poses are never drawn)."""

    rotation: np.ndarray  # (4, 4) rotation only
    hull_vertices: np.ndarray  # (V, 3) the mesh's convex hull in its own frame (shared by its poses)

    @functools.cached_property
    def _rotated(self) -> np.ndarray:
        return self.hull_vertices @ self.rotation[:3, :3].T

    @functools.cached_property
    def offset(self) -> np.ndarray:
        """(3,) subtract after rotation: xy centre of the footprint box, lowest z."""
        lo, hi = self._rotated.min(axis=0), self._rotated.max(axis=0)
        return np.array([(lo[0] + hi[0]) / 2.0, (lo[1] + hi[1]) / 2.0, lo[2]])

    @functools.cached_property
    def height(self) -> float:
        """Height of the resting mesh (m)."""
        return float(self._rotated[:, 2].max() - self._rotated[:, 2].min())

    @functools.cached_property
    def footprint(self) -> np.ndarray:
        """(K, 2) convex polygon, counter-clockwise, centred (after offset)."""
        return _convex_polygon(self._rotated[:, :2] - self.offset[:2])


def _convex_polygon(points: np.ndarray) -> np.ndarray:
    from scipy.spatial import ConvexHull

    hull = ConvexHull(points)
    return points[hull.vertices]  # counter-clockwise in 2-D


@functools.lru_cache(maxsize=256)
def rest_poses(mesh_ref: str, scale: float, rest: str) -> tuple[tuple[RestPose, ...], np.ndarray]:
    """Resting poses of a mesh and their probabilities."""
    mesh = load_mesh(mesh_ref, scale)
    hull = mesh.convex_hull
    if rest == "upright":
        rotations, probs = np.eye(4)[None], np.ones(1)
    else:
        center = mesh.center_mass if (mesh.is_watertight and mesh.volume > 0) else hull.center_mass
        rotations, probs = stable_poses(mesh, center)
        keep = probs > 1e-3  # tiny-probability facets (e.g. the rim of a tessellated cylinder) are not useful
        if np.any(keep):
            rotations, probs = rotations[keep], probs[keep]
        probs = probs / probs.sum()
    poses = []
    for T in rotations:
        R = np.eye(4)
        R[:3, :3] = T[:3, :3]
        poses.append(RestPose(rotation=R, hull_vertices=hull.vertices))
    return tuple(poses), np.asarray(probs, dtype=np.float64)


def _polygon_axes(polygon: np.ndarray) -> np.ndarray:
    edges = np.roll(polygon, -1, axis=0) - polygon
    normals = np.stack([edges[:, 1], -edges[:, 0]], axis=1)
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    return normals[length[:, 0] > 1e-12] / length[length[:, 0] > 1e-12]


@dataclasses.dataclass(frozen=True)
class Footprint:
    """A convex (K, 2) world polygon with what the separation test needs of it, computed once: a layout tests
    every try against every placed footprint, and recomputing these per pair was most of a layout's time."""

    polygon: np.ndarray  # (K, 2) m
    centre: np.ndarray  # (2,) mean of the vertices
    radius: float  # distance of the farthest vertex from the centre
    axes: np.ndarray  # (A, 2) unit edge normals

    @classmethod
    def of(cls, polygon) -> "Footprint":
        polygon = np.asarray(polygon, dtype=np.float64)
        centre = polygon.mean(axis=0)
        radius = np.sqrt(((polygon - centre) ** 2).sum(axis=1).max())
        return cls(polygon, centre, radius, _polygon_axes(polygon))


def footprints_separated(a: Footprint, b: Footprint, gap: float = 0.0) -> bool:
    """True if footprints ``a`` and ``b`` are at least ``gap`` apart along some edge normal.

    (Separating-axis theorem; a separation of ``gap`` along an axis implies a distance >= ``gap``.)
    """
    if np.hypot(*(a.centre - b.centre)) >= a.radius + b.radius + gap:
        return True  # bounding circles apart: separated along the line of centres
    axes = np.concatenate([a.axes, b.axes])
    pa, pb = a.polygon @ axes.T, b.polygon @ axes.T  # (K, A), (M, A)
    separation = np.maximum(pb.min(axis=0) - pa.max(axis=0), pa.min(axis=0) - pb.max(axis=0))
    return bool(np.any(separation >= gap))


def polygons_separated(a: np.ndarray, b: np.ndarray, gap: float = 0.0) -> bool:
    """True if convex polygons ``a`` (K, 2) and ``b`` (M, 2) are at least ``gap`` apart along some edge normal."""
    return footprints_separated(Footprint.of(a), Footprint.of(b), gap)
