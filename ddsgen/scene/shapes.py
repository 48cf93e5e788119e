"""Built-in procedural meshes (metres), made with :mod:`trimesh.creation`.

Every shape is a plain function of a few sizes in metres and returns a
:class:`trimesh.Trimesh` in its own object frame: z up, resting on z = 0 is *not*
assumed (placement computes the resting pose). A shape has a text reference
``shape:NAME(key=value,...)`` (vectors as ``AxBxC``) that the manifest stores as the
object's ``mesh`` and that :func:`mesh_from_ref` turns back into the same mesh.

Shapes: box, cylinder, sphere, capsule, cone, torus, plus two non-convex ones,
mug (open cup with a handle) and l_bracket (an L profile extruded).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Callable

import numpy as np
import trimesh
from trimesh import creation


@dataclasses.dataclass(frozen=True)
class ShapeParam:
    """One size parameter of a shape: length of the vector (1 = scalar), default, help (with unit)."""

    length: int
    default: tuple[float, ...]
    help: str


def _box(size):
    return creation.box(extents=size)


def _cylinder(radius, height):
    return creation.cylinder(radius=radius, height=height, sections=48)


def _sphere(radius):
    return creation.icosphere(subdivisions=3, radius=radius)


def _capsule(radius, height, arc_points: int = 16, sections: int = 32):
    """A capsule of total height ``height`` (cap to cap), as a surface of revolution of an explicit
    profile: trimesh's own ``creation.capsule`` tessellates differently from one major version to the
    next (4.x: 962 vertices, 5.x: 1026 for the same ``count``), which changed rendered datasets."""
    half = max(height / 2.0 - radius, 0.0)  # the cap centres are at z = +-half
    angles = np.linspace(-np.pi / 2.0, np.pi / 2.0, 2 * arc_points + 1)  # pole to pole through the equator
    r, z = radius * np.cos(angles), radius * np.sin(angles)
    lower, upper = angles <= 0.0, angles >= 0.0
    profile = np.concatenate([np.stack([r[lower], z[lower] - half], 1), np.stack([r[upper], z[upper] + half], 1)])
    profile[[0, -1], 0] = 0.0  # the poles exactly on the axis
    return creation.revolve(profile, sections=sections)


def _cone(radius, height):
    mesh = creation.cone(radius=radius, height=height, sections=48)
    mesh.apply_translation([0.0, 0.0, -height / 2.0])  # centred like the others
    return mesh


def _torus(major_radius, minor_radius):
    return creation.torus(major_radius=major_radius, minor_radius=minor_radius, major_sections=48, minor_sections=24)


def _mug(radius, height, wall, handle):
    """An open cup (outer radius, height, wall thickness) with a half-ring handle of outer reach ``handle``."""
    body = creation.annulus(r_min=radius - wall, r_max=radius, height=height, sections=48)
    bottom = creation.cylinder(radius=radius - wall * 0.5, height=wall, sections=48)
    bottom.apply_translation([0.0, 0.0, -height / 2.0 + wall / 2.0])
    minor = max(min(wall * 1.5, handle * 0.3), 1e-4)
    major = max(handle * 0.5 + wall, minor * 1.5)
    ring = creation.torus(major_radius=major, minor_radius=minor, major_sections=32, minor_sections=12)
    # stand the ring upright (in the x-z plane) and move it to the +x side so that half of it sticks out
    ring.apply_transform(trimesh.transformations.rotation_matrix(math.pi / 2.0, [1.0, 0.0, 0.0]))
    ring.apply_translation([radius - wall * 0.5, 0.0, 0.0])
    inside = np.linalg.norm(ring.triangles_center[:, :2], axis=1) < radius - wall * 0.5
    ring.update_faces(~inside)
    ring.remove_unreferenced_vertices()
    return trimesh.util.concatenate([body, bottom, ring])


def _l_bracket(length, width, height, thickness):
    """An L profile: a base plate (length x width x thickness) and an upright plate (thickness x width x height)."""
    base = creation.box(bounds=[[0.0, 0.0, 0.0], [length, width, thickness]])
    upright = creation.box(bounds=[[0.0, 0.0, thickness], [thickness, width, height]])
    mesh = trimesh.util.concatenate([base, upright])
    mesh.apply_translation(-mesh.bounds.mean(axis=0))
    return mesh


SHAPES: dict[str, tuple[Callable, dict[str, ShapeParam]]] = {
    "box": (_box, {"size": ShapeParam(3, (0.1, 0.1, 0.1), "edge lengths x, y, z (m)")}),
    "cylinder": (
        _cylinder,
        {"radius": ShapeParam(1, (0.04,), "radius (m)"), "height": ShapeParam(1, (0.12,), "height (m)")},
    ),
    "sphere": (_sphere, {"radius": ShapeParam(1, (0.05,), "radius (m)")}),
    "capsule": (
        _capsule,
        {"radius": ShapeParam(1, (0.03,), "radius (m)"), "height": ShapeParam(1, (0.14,), "total height, cap to cap (m)")},
    ),
    "cone": (_cone, {"radius": ShapeParam(1, (0.05,), "base radius (m)"), "height": ShapeParam(1, (0.12,), "height (m)")}),
    "torus": (
        _torus,
        {
            "major_radius": ShapeParam(1, (0.06,), "ring radius (m)"),
            "minor_radius": ShapeParam(1, (0.02,), "tube radius (m)"),
        },
    ),
    "mug": (
        _mug,
        {
            "radius": ShapeParam(1, (0.04,), "outer radius (m)"),
            "height": ShapeParam(1, (0.10,), "height (m)"),
            "wall": ShapeParam(1, (0.006,), "wall thickness (m)"),
            "handle": ShapeParam(1, (0.035,), "how far the handle sticks out (m)"),
        },
    ),
    "l_bracket": (
        _l_bracket,
        {
            "length": ShapeParam(1, (0.14,), "base length (m)"),
            "width": ShapeParam(1, (0.06,), "width (m)"),
            "height": ShapeParam(1, (0.10,), "upright height (m)"),
            "thickness": ShapeParam(1, (0.015,), "plate thickness (m)"),
        },
    ),
}


def shape_params(name: str) -> dict[str, ShapeParam]:
    """The parameter schema of shape ``name`` (KeyError if unknown)."""
    return SHAPES[name][1]


def check_shape_params(name: str, params: dict[str, tuple[float, ...]]) -> str | None:
    """Geometric sanity of a complete parameter set; returns a problem (one line) or None."""
    p = {k: v[0] if len(v) == 1 else v for k, v in params.items()}
    if name == "capsule" and p["height"] < 2 * p["radius"]:
        return f"height must be >= 2 * radius ({p['height']} < {2 * p['radius']})"
    if name == "torus" and p["minor_radius"] >= p["major_radius"]:
        return f"minor_radius must be smaller than major_radius ({p['minor_radius']} >= {p['major_radius']})"
    if name == "mug" and p["wall"] >= p["radius"]:
        return f"wall must be thinner than radius ({p['wall']} >= {p['radius']})"
    if name == "mug" and p["wall"] >= p["height"]:
        return f"wall must be thinner than height ({p['wall']} >= {p['height']})"
    if name == "l_bracket" and (p["thickness"] >= p["length"] or p["thickness"] >= p["height"]):
        return f"thickness must be smaller than length and height ({p['thickness']})"
    return None


def _fmt(value: float) -> str:
    return f"{float(value):.6g}"


def shape_ref(name: str, params: dict[str, tuple[float, ...]]) -> str:
    """``shape:NAME(key=value,...)`` with vectors written ``AxBxC`` (keys in schema order)."""
    schema = shape_params(name)
    parts = [f"{key}={'x'.join(_fmt(v) for v in params[key])}" for key in schema]
    return f"shape:{name}({','.join(parts)})"


def parse_shape_ref(ref: str) -> tuple[str, dict[str, tuple[float, ...]]]:
    """Inverse of :func:`shape_ref`; ValueError on a malformed reference."""
    if not ref.startswith("shape:"):
        raise ValueError(f"not a shape reference: {ref!r}")
    body = ref[len("shape:"):]
    name, _, rest = body.partition("(")
    if name not in SHAPES:
        raise ValueError(f"unknown shape {name!r} in {ref!r}")
    params = {k: p.default for k, p in shape_params(name).items()}
    rest = rest.rstrip(")")
    for item in filter(None, rest.split(",")):
        key, _, value = item.partition("=")
        if key not in params:
            raise ValueError(f"unknown parameter {key!r} of shape {name!r}")
        params[key] = tuple(float(v) for v in value.split("x"))
    return name, params


def make_shape(name: str, params: dict[str, tuple[float, ...]] | None = None) -> trimesh.Trimesh:
    """Build shape ``name`` (metres) with ``params`` (missing keys take defaults)."""
    function, schema = SHAPES[name]
    values = {k: p.default for k, p in schema.items()}
    values.update(params or {})
    args = {k: (np.asarray(v, dtype=float) if schema[k].length > 1 else float(v[0])) for k, v in values.items()}
    mesh = function(**args)
    mesh = trimesh.Trimesh(vertices=np.asarray(mesh.vertices, dtype=np.float64), faces=mesh.faces, process=False)
    return mesh


def mesh_from_ref(ref: str) -> trimesh.Trimesh:
    """The mesh of a ``shape:...`` reference as written in a manifest."""
    name, params = parse_shape_ref(ref)
    return make_shape(name, params)


def plane_mesh(size_x: float, size_y: float) -> trimesh.Trimesh:
    """A rectangle in the z = 0 plane centred on the origin, normal +z (two triangles)."""
    hx, hy = size_x / 2.0, size_y / 2.0
    vertices = np.array([[-hx, -hy, 0.0], [hx, -hy, 0.0], [hx, hy, 0.0], [-hx, hy, 0.0]])
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    return trimesh.Trimesh(vertices=vertices, faces=faces, process=False)
