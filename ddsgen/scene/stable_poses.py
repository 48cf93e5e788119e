"""A mesh's stable resting poses (``trimesh.poses.compute_stable_poses``), kept in ddsgen's cache folder.

Computing them takes about a second per mesh (a topple graph over the convex hull's facets), and every render
worker of every run needs them for every mesh of its scene list that rests on a support: with the built-in scene
list 2-4 s before a worker's first frame. They depend only on the mesh's vertices, faces and centre of mass (and
trimesh's version), so they are stored under a digest of those bytes (``<cache>/stable_poses/<digest>.npz``).
A stored result is the computed float64 arrays bit for bit, so a dataset does not depend on whether the cache was
warm. An unreadable cache file is recomputed and rewritten; a read-only cache folder only costs the time.
"""

from __future__ import annotations

import hashlib
import io

import numpy as np

from ddsgen.cache import cache_dir
from ddsgen.atomic import atomic_write_bytes


def _digest(mesh, center_mass: np.ndarray) -> str:
    import trimesh

    digest = hashlib.blake2b(digest_size=16)
    digest.update(trimesh.__version__.encode())
    for array in (mesh.vertices, mesh.faces, center_mass):
        a = np.ascontiguousarray(array)
        digest.update(f"{a.dtype}{a.shape}".encode())
        digest.update(a.tobytes())
    return digest.hexdigest()


def stable_poses(mesh, center_mass: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(rotations (N, 4, 4), probabilities (N,))`` of ``mesh`` resting on a plane, as
    ``trimesh.poses.compute_stable_poses(mesh, center_mass=center_mass)`` returns them (float64)."""
    import trimesh

    center_mass = np.asarray(center_mass, dtype=np.float64)
    path = cache_dir() / "stable_poses" / f"{_digest(mesh, center_mass)}.npz"
    try:
        with np.load(path) as stored:
            return stored["rotations"], stored["probabilities"]
    except Exception:  # missing, truncated or foreign file: compute it again (never trust a bad cache)
        pass
    rotations, probabilities = trimesh.poses.compute_stable_poses(mesh, center_mass=center_mass)
    rotations = np.asarray(rotations, dtype=np.float64)
    probabilities = np.asarray(probabilities, dtype=np.float64)
    buffer = io.BytesIO()
    np.savez(buffer, rotations=rotations, probabilities=probabilities)
    try:
        atomic_write_bytes(path, buffer.getvalue())
    except OSError:  # a read-only cache: the poses are still right, only not kept
        pass
    return rotations, probabilities
