"""Distractors: unlabelled objects a scene adds around its clutter (the scene-list key ``distractors:``).

Real captures of a table top see more than the labelled objects: boxes, bins and furniture on the floor
around the table, binders and screens along the wall behind it. Their depth edges, projector shadows and
far holes are missing from a bare table before a bare wall, and a network trained without them sees an
emptier world than the sensor does. Distractors are drawn like the clutter (a random stable pose of the
convex hull, a random yaw, footprints kept apart) but belong to the background: instance id 0 in the mask,
no pose in the manifest or the BOP ground truth.

Schema (one entry per group; the groups are drawn after everything else, each from its own random stream, so
adding groups leaves the clutter, the planes and the camera where they were)::

    distractors:
      - surface: floor            # floor: stand on the floor around the table (needs `floor:`; their tops stay
                                  #   below the table top) | ground: stand on the ground plane / table top
                                  # (not `on:`, which YAML 1.1 reads as true)
        count: [4, 8]             # per layout (integers)
        area: [5.0, 5.0]          # x, y extent of the region they stand in (m) ...
        centre: [0.0, 0.0]        # ... centred here (x, y, m)
        min_gap: 0.02             # footprint gap to each other, the clutter and the table's edge (m)
        max_tries: 100            # placement attempts per object before it is left out
        objects:                  # the group's pool: the same entries as a scene's `objects`
          - {shape: box, size: [0.6, 0.4, 0.3], albedo: [0.05, 0.8]}
"""

from __future__ import annotations

import dataclasses
from typing import Any, Callable

from ddsgen.errors import InputError, where
from ddsgen.scene.fields import (
    check_keys,
    describe,
    field_number,
    field_range,
    field_size2,
    field_vector,
)
from ddsgen.scene.object_spec import ObjectSpec

#: Where a distractor group stands.
SURFACES = ("floor", "ground")


@dataclasses.dataclass(frozen=True)
class DistractorSpec:
    """One group of unlabelled objects: ``count`` drawn from ``objects`` onto ``surface`` within ``area`` about ``centre``."""

    surface: str  # "floor" | "ground"
    objects: tuple[ObjectSpec, ...]
    count: tuple[int, int] = (4, 8)
    area: tuple[float, float] = (5.0, 5.0)
    centre: tuple[float, float] = (0.0, 0.0)
    min_gap: float = 0.02
    max_tries: int = 100


def parse_distractors(source, key: str, data: Any, parse_object: Callable[[str, Any], ObjectSpec],
                      has_floor: bool, has_ground: bool) -> tuple[DistractorSpec, ...]:  # fmt: skip
    """Validate a scene's ``distractors:`` list (None: none).

    Args:
        parse_object: ``(key, entry) -> ObjectSpec``, the scene list's own object-entry parser.
        has_floor, has_ground: whether the scene has a floor / a ground plane (what ``surface`` may name).
    """
    if data is None:
        return ()
    if not isinstance(data, list):
        raise InputError(f"{where(source, key)}expected a list of distractor groups, got {describe(data)}")
    groups = []
    for i, entry in enumerate(data):
        sub = f"{key}[{i}]"
        if isinstance(entry, dict) and True in entry:
            raise InputError(f"{where(source, sub)}YAML reads the key `on` as true: the key is `surface:`")
        check_keys(source, sub, entry, ("surface", "count", "area", "centre", "min_gap", "max_tries", "objects"),
                   "a distractor group")  # fmt: skip
        surface = entry.get("surface")
        if surface not in SURFACES:
            raise InputError(f"{where(source, sub + '.surface')}expected one of {', '.join(SURFACES)}, got"
                             f" {describe(surface)}")  # fmt: skip
        if surface == "floor" and not has_floor:
            raise InputError(f"{where(source, sub + '.surface')}distractors on the floor need the scene's `floor:`")
        if surface == "ground" and not has_ground:
            raise InputError(f"{where(source, sub + '.surface')}distractors on the ground need the scene's `ground:`")
        pool = entry.get("objects")
        if not isinstance(pool, list) or not pool:
            raise InputError(f"{where(source, sub + '.objects')}expected a non-empty list of objects, got {describe(pool)}")
        default = DistractorSpec(surface=surface, objects=())
        groups.append(DistractorSpec(
            surface=surface,
            objects=tuple(parse_object(f"{sub}.objects[{j}]", o) for j, o in enumerate(pool)),
            count=field_range(source, f"{sub}.count", entry.get("count", list(default.count)), low=0, high=1000,
                              integer=True),
            area=field_size2(source, f"{sub}.area", entry.get("area", list(default.area))),
            centre=tuple(field_vector(source, f"{sub}.centre", entry.get("centre", list(default.centre)), 2,
                                      low=-1e3, high=1e3)),
            min_gap=field_number(source, f"{sub}.min_gap", entry.get("min_gap", default.min_gap), low=0, high=10),
            max_tries=field_number(source, f"{sub}.max_tries", entry.get("max_tries", default.max_tries), low=1,
                                   high=100000, integer=True),
        ))  # fmt: skip
    return tuple(groups)
