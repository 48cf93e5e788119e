"""``classes.json``: the class table ``ddsgen render`` writes beside the manifest.

One row per labelled object of the scene list (see :mod:`ddsgen.scene.identity`), sorted by id::

    {"classes": [
      {"id": 6, "class": "cat", "class_id": 6, "mesh": "/abs/path/obj_000006.ply", "mesh_scale": 0.001},
      ...]}

``id`` is the object's ``obj_id`` (the BOP model id, also each manifest object's ``obj_id``), ``class_id`` the
id of its class (the smallest ``obj_id`` with that class name). The table depends only on the scene list, so a
resumed run rewrites the same bytes.
"""

from __future__ import annotations

import json
from pathlib import Path

from ddsgen.errors import InputError
from ddsgen.atomic import atomic_write_text

CLASS_TABLE_FILE = "classes.json"


def class_table_rows(entries) -> list[dict]:
    """JSON rows of :class:`ddsgen.scene.identity.ClassEntry` objects."""
    return [{"id": int(e.obj_id), "class": e.class_name, "class_id": int(e.class_id), "mesh": e.mesh_ref,
             "mesh_scale": float(e.mesh_scale)} for e in sorted(entries, key=lambda e: e.obj_id)]  # fmt: skip


def write_class_table(folder: str | Path, entries) -> Path:
    """Write ``folder/classes.json`` (atomically) from class-table entries; return its path."""
    path = Path(folder) / CLASS_TABLE_FILE
    atomic_write_text(path, json.dumps({"classes": class_table_rows(entries)}, indent=1, sort_keys=True) + "\n")
    return path


def read_class_table(folder: str | Path) -> list[dict] | None:
    """The rows of ``folder/classes.json``, or None when the folder has none (renders made before it existed,
    hand-written real-scan folders). A malformed file raises :class:`InputError`."""
    path = Path(folder) / CLASS_TABLE_FILE
    if not path.is_file():
        return None
    try:
        rows = json.loads(path.read_text())["classes"]
    except (OSError, ValueError, KeyError, TypeError) as error:
        raise InputError(f"{path}: not a class table ({type(error).__name__}: {error})") from None
    for index, row in enumerate(rows):
        if not isinstance(row, dict) or not all(k in row for k in ("id", "class", "mesh")):
            raise InputError(f"{path}: classes[{index}]: needs id, class and mesh")
    return rows
