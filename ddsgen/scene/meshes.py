"""Meshes of scene objects: built-in procedural shapes (``shape:NAME``) or mesh files read with trimesh, in metres.

Loaded meshes are cached per process (worker processes load each mesh once) and read-only.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from ddsgen.errors import InputError, where
from ddsgen.scene import shapes

MESH_SUFFIXES = (".obj", ".ply", ".stl", ".glb", ".gltf", ".off")

_MESH_CACHE: dict[tuple[str, float], Any] = {}


def _load_mesh_file(path: str, scale: float, source: str = "", key: str | None = None):
    """Load a mesh file with trimesh; InputError naming the file on any problem."""
    import trimesh

    label = f"{where(source, key)}{path}: " if source else f"{path}: "
    if not os.path.isfile(path):
        raise InputError(f"{label}mesh file not found")
    suffix = Path(path).suffix.lower()
    if suffix not in MESH_SUFFIXES:
        raise InputError(f"{label}not a mesh file (expected one of {', '.join(MESH_SUFFIXES)})")
    try:
        loaded = trimesh.load(path, force="mesh", process=False)
    except Exception as error:  # trimesh raises many kinds of errors on garbage
        first = str(error).splitlines()[0] if str(error) else ""
        raise InputError(f"{label}cannot read mesh ({error.__class__.__name__}: {first})") from None
    if not isinstance(loaded, trimesh.Trimesh):
        raise InputError(f"{label}not a triangle mesh (trimesh read a {type(loaded).__name__})")
    faces = np.asarray(loaded.faces)
    vertices = np.asarray(loaded.vertices, dtype=np.float64)
    if faces.ndim != 2 or len(faces) == 0:
        raise InputError(f"{label}mesh has no faces")
    if not np.all(np.isfinite(vertices)):
        raise InputError(f"{label}mesh has non-finite vertex coordinates")
    mesh = trimesh.Trimesh(vertices=vertices * scale, faces=faces, process=False)
    # Drop degenerate triangles (zero area): they only confuse normals.
    area_ok = mesh.area_faces > 0
    if not np.any(area_ok):
        raise InputError(f"{label}mesh has no faces with non-zero area")
    if not np.all(area_ok):
        mesh.update_faces(area_ok)
        mesh.remove_unreferenced_vertices()
    return mesh


def load_mesh(mesh_ref: str, scale: float = 1.0, source: str = "", key: str | None = None):
    """The mesh of a reference (``shape:...`` or a file path), in metres; cached per process."""
    cache_key = (mesh_ref, float(scale))
    mesh = _MESH_CACHE.get(cache_key)
    if mesh is None:
        if mesh_ref.startswith("shape:"):
            mesh = shapes.mesh_from_ref(mesh_ref)
            if scale != 1.0:
                mesh.apply_scale(scale)
        else:
            mesh = _load_mesh_file(mesh_ref, scale, source, key)
        mesh.vertices.flags.writeable = False
        _MESH_CACHE[cache_key] = mesh
    return mesh
