"""Stable object identity: the ``obj_id`` and ``class_id`` of every object a scene list can place.

A training set needs ids that mean the same object in every frame, every run and every export (a synthetic BOP
``train_pbr`` next to a real ``test`` split). Every labelled pool entry of a scene list (mesh or shape, scale and
class; distractors are unlabelled and get none) has one ``obj_id``, taken in this order:

1. the entry's ``obj_id:`` key;
2. a BOP-style mesh file name: ``obj_000006.ply`` -> 6;
3. otherwise the smallest id no other entry uses, in the order the entries first appear in the scene list
   (so it depends only on the scene list, never on the frame or the seed).

An entry that appears in several scenes (a YAML anchor) is one entry with one id. Two different entries may not
claim the same id. ``class_id`` is the smallest ``obj_id`` of the entries with the same class name: it equals the
``obj_id`` unless several meshes share a class.
"""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path
from typing import Iterable

from ddsgen.errors import InputError, where

#: A BOP model file stem: ``obj_000006`` -> 6.
BOP_MODEL_NAME = re.compile(r"obj_(\d+)")


@dataclasses.dataclass(frozen=True)
class ClassEntry:
    """One row of the class table (``classes.json``)."""

    obj_id: int
    class_id: int
    class_name: str
    mesh_ref: str  # absolute mesh file path or "shape:NAME(params)"
    mesh_scale: float  # file units -> metres

    @property
    def key(self) -> tuple[str, float, str]:
        return identity_key(self.mesh_ref, self.mesh_scale, self.class_name)


def identity_key(mesh_ref: str, mesh_scale: float, class_name: str) -> tuple[str, float, str]:
    """What makes two placed objects the same object: mesh, scale and class."""
    return (str(mesh_ref), float(mesh_scale), str(class_name))


def obj_id_from_mesh_name(mesh_ref: str) -> int | None:
    """The id a BOP-style model file name states (``.../obj_000006.ply`` -> 6), else None."""
    if mesh_ref.startswith("shape:"):
        return None
    match = BOP_MODEL_NAME.fullmatch(Path(mesh_ref).stem)
    return int(match.group(1)) if match and int(match.group(1)) >= 1 else None


def class_table(entries: Iterable[tuple[str, object]], source: str = "") -> tuple[ClassEntry, ...]:
    """The class table of a scene list's labelled pool entries, sorted by ``obj_id``.

    Args:
        entries: ``(key, spec)`` in scene-list order; ``key`` names the entry in messages
            (``scenes[0].objects[2]``), ``spec`` has ``mesh_ref``, ``scale``, ``class_name`` and ``obj_id``
            (the explicit ``obj_id:`` key or None).
        source: the scene-list file, for messages.

    Raises:
        InputError: two different entries claim one id, or one entry is given two ids.
    """
    order: list[tuple[str, float, str]] = []
    first_key: dict[tuple, str] = {}
    claimed: dict[tuple, tuple[int, str]] = {}  # identity -> (id, where it comes from)
    for key, spec in entries:
        identity = identity_key(spec.mesh_ref, spec.scale, spec.class_name)
        if identity not in first_key:
            order.append(identity)
            first_key[identity] = key
        if spec.obj_id is not None:
            earlier = claimed.get(identity)
            if earlier is not None and earlier[0] != spec.obj_id:
                raise InputError(f"{where(source, key + '.obj_id')}{spec.obj_id} but the same object has obj_id"
                                 f" {earlier[0]} at {earlier[1]}")  # fmt: skip
            claimed[identity] = (spec.obj_id, f"{key}.obj_id")
    for identity in order:  # a BOP model name gives the id when no `obj_id:` does
        named = obj_id_from_mesh_name(identity[0])
        if identity not in claimed and named is not None:
            claimed[identity] = (named, f"{first_key[identity]}.mesh (its file name)")
    owner: dict[int, tuple] = {}
    for identity in order:
        if identity in claimed:
            obj_id, origin = claimed[identity]
            if obj_id in owner:
                other = owner[obj_id]
                raise InputError(
                    f"{where(source, first_key[identity])}obj_id {obj_id} (from {origin}) is already the id of"
                    f" {first_key[other]} ({other[2]}); give one of them its own `obj_id:`"
                )
            owner[obj_id] = identity
    ids = {identity: claimed[identity][0] for identity in order if identity in claimed}
    next_free = 1
    for identity in order:
        if identity not in ids:
            while next_free in owner:
                next_free += 1
            ids[identity] = next_free
            owner[next_free] = identity
    class_ids: dict[str, int] = {}
    for identity, obj_id in ids.items():
        class_ids[identity[2]] = min(obj_id, class_ids.get(identity[2], obj_id))
    table = [ClassEntry(obj_id=ids[i], class_id=class_ids[i[2]], class_name=i[2], mesh_ref=i[0], mesh_scale=i[1])
             for i in order]  # fmt: skip
    return tuple(sorted(table, key=lambda entry: entry.obj_id))
