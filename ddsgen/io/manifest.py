"""The JSON Lines manifest of a scan folder (README.md "Outputs"): one JSON object per frame.

Writing: :func:`append_record` validates a record, serialises it as canonical
JSON (sorted keys, fixed separators, no NaN; numpy values converted), and
appends it as one line with flush + fsync. Call it only after the frame's
files are complete, from a single writer process. A crash can leave at most
a partial last line; :func:`read_manifest` ignores it and
:func:`repair_manifest` (called by :func:`append_record` when needed) cuts it
off before the next append, so a resumed run re-renders that frame.

Reading: :func:`read_manifest` returns the records in file order and raises
:class:`InputError` ``"FILE: line N: KEY: problem"`` for a corrupt or invalid
line anywhere but a crash-truncated last one.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
from pathlib import Path, PurePosixPath, PureWindowsPath

import numpy as np

from ddsgen.errors import InputError

#: The file ``ddsgen render`` writes beside the manifest: what a resume must match. Its presence marks a folder
#: (in the BOP layout: the scans folder) as one ddsgen rendered.
RUN_FILE = "run.json"

MANIFEST_SCHEMA = """\
One JSON object per line; keys (units: metres, pixels; poses are 4x4 row-major nested lists):

  frame             int >= 0, unique within the manifest
  depth             str, path of the depth image relative to the folder (.png uint16 or .exr float32 m)
  intrinsics        {width: int > 0, height: int > 0, fx, fy, cx, cy: finite numbers > 0} (px)
  depth_scale       finite number > 0: metres per unit of the 16-bit depth PNG (0.001 = millimetres)
  world_T_cam       4x4 rigid transform (rotation orthonormal, det +1 within 1e-4, last row 0 0 0 1)
                    placing the OpenCV camera in the world; null allowed only in non-strict mode
  objects           list of {
                      id                int >= 1, the object's value in the instance mask, unique in the frame
                      mesh              str, mesh file (relative to the folder, or absolute) or "shape:NAME"
                      class             str, class name
                      cam_T_obj         4x4 rigid transform, object -> camera coordinates (m)
                      bbox              [x, y, w, h] ints >= 0 (px, of the visible part)
                      visible_fraction  number in [0, 1]
                      mesh_scale        optional, finite number > 0: metres per mesh file unit (default 1;
                                        0.001 for millimetre models such as BOP's)
                      obj_id            optional, int >= 1: the object's stable id (the same in every frame;
                                        the BOP model id; a row of classes.json beside the manifest)
                      class_id          optional, int >= 1: its class's id (the smallest obj_id of the class)
                    }
  seed              int, the run's seed (frame i's randomness comes from (seed, i))
  ir_white_counts   optional, finite number > 0: simulated IR counts shown as 255 in the 8-bit IR PNG
  ir_gamma          optional, finite number > 0: the IR PNG's encoding, counts = ir_white_counts x
                    (png / 255) ** ir_gamma (auto-exposed per frame; 255 = at or above ir_white_counts)

Optional keys are allowed and kept (e.g. depth_exr, clean, ir, mask: relative paths; checked to be
relative paths when present). Non-strict validation (real scans, `strict=False`) does not require
world_T_cam (may be null), seed, or the objects' bbox and visible_fraction, but checks them when present.
"""

REQUIRED_KEYS = ("frame", "depth", "intrinsics", "depth_scale", "world_T_cam", "objects", "seed")
OPTIONAL_PATH_KEYS = ("depth_exr", "depth_png", "clean", "ir", "mask")
RIGID_TOL = 1e-4


# ---------------------------------------------------------------- serialisation


def to_jsonable(value):
    """Convert numpy arrays/scalars, tuples and paths to plain JSON types (recursively)."""
    if isinstance(value, dict):
        return {str(k): to_jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [to_jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return to_jsonable(value.tolist())
    if isinstance(value, np.bool_):
        return bool(value)
    if isinstance(value, np.integer):
        return int(value)
    if isinstance(value, np.floating):
        return float(value)
    if isinstance(value, PurePosixPath | PureWindowsPath):
        return value.as_posix()
    if hasattr(value, "tolist") and callable(value.tolist):  # torch tensors
        return to_jsonable(value.tolist())
    return value


def dumps_record(record: dict) -> str:
    """Canonical one-line JSON of ``record`` (sorted keys, ``(",", ":")`` separators, no NaN), no newline."""
    return json.dumps(to_jsonable(record), sort_keys=True, separators=(",", ":"), ensure_ascii=False, allow_nan=False)


# ---------------------------------------------------------------- validation


def _fail(prefix: str, key: str, problem: str):
    raise InputError(f"{prefix}{key}: {problem}")


def _is_int(value) -> bool:
    return isinstance(value, int | np.integer) and not isinstance(value, bool | np.bool_)


def _is_number(value) -> bool:
    return isinstance(value, int | float | np.integer | np.floating) and not isinstance(value, bool | np.bool_)


def _positive_number(prefix, key, value):
    if not _is_number(value) or not math.isfinite(float(value)) or not float(value) > 0:
        _fail(prefix, key, f"must be a finite number > 0, got {value!r}")


def _relative_path(prefix, key, value):
    if not isinstance(value, str) or not value.strip():
        _fail(prefix, key, f"must be a non-empty relative path string, got {value!r}")
    if PurePosixPath(value).is_absolute() or PureWindowsPath(value).is_absolute() or value.startswith("\\"):
        _fail(prefix, key, f"must be a path relative to the folder, got absolute {value!r}")


def as_rigid(value, prefix: str = "", key: str = "pose") -> np.ndarray:
    """Check that ``value`` is a finite 4x4 rigid transform and return it as float64 (4, 4).

    Rotation orthonormal and det +1 within :data:`RIGID_TOL`, last row ``0 0 0 1``.
    Raises :class:`InputError` ``"{prefix}{key}: problem"``.
    """
    try:
        matrix = np.array(to_jsonable(value), dtype=np.float64)
    except (TypeError, ValueError):
        _fail(prefix, key, "must be a 4x4 matrix of numbers")
    if matrix.shape != (4, 4):
        _fail(prefix, key, f"must be a 4x4 matrix, got shape {matrix.shape}")
    if not np.isfinite(matrix).all():
        _fail(prefix, key, "has non-finite values")
    if np.abs(matrix[3] - [0, 0, 0, 1]).max() > 1e-9:
        _fail(prefix, key, f"last row must be 0 0 0 1, got {matrix[3].tolist()}")
    rotation = matrix[:3, :3]
    error = np.abs(rotation @ rotation.T - np.eye(3)).max()
    if error > RIGID_TOL:
        _fail(prefix, key, f"rotation is not orthonormal (max |R R^T - I| = {error:.2g} > {RIGID_TOL})")
    det = float(np.linalg.det(rotation))
    if abs(det - 1.0) > RIGID_TOL:
        _fail(prefix, key, f"rotation determinant is {det:.6g}, must be +1 (a reflection?)")
    return matrix


def _validate_object(prefix, key, obj, strict):
    if not isinstance(obj, dict):
        _fail(prefix, key, f"must be an object, got {type(obj).__name__}")
    needed = ("id", "mesh", "class", "cam_T_obj") + (("bbox", "visible_fraction") if strict else ())
    for name in needed:
        if name not in obj:
            _fail(prefix, f"{key}.{name}", "missing")
    if not _is_int(obj["id"]) or obj["id"] < 1:
        _fail(prefix, f"{key}.id", f"must be an int >= 1, got {obj['id']!r}")
    for name in ("mesh", "class"):
        if not isinstance(obj[name], str) or not obj[name].strip():
            _fail(prefix, f"{key}.{name}", f"must be a non-empty string, got {obj[name]!r}")
    as_rigid(obj["cam_T_obj"], prefix, f"{key}.cam_T_obj")
    if "bbox" in obj:
        bbox = obj["bbox"]
        if not isinstance(bbox, list | tuple) or len(bbox) != 4 or not all(_is_int(v) and v >= 0 for v in bbox):
            _fail(prefix, f"{key}.bbox", f"must be [x, y, w, h] of ints >= 0, got {bbox!r}")
    if "mesh_scale" in obj:
        _positive_number(prefix, f"{key}.mesh_scale", obj["mesh_scale"])
    for name in ("obj_id", "class_id"):
        if name in obj and (not _is_int(obj[name]) or obj[name] < 1):
            _fail(prefix, f"{key}.{name}", f"must be an int >= 1, got {obj[name]!r}")
    if "visible_fraction" in obj:
        frac = obj["visible_fraction"]
        if not _is_number(frac) or not 0.0 <= float(frac) <= 1.0:
            _fail(prefix, f"{key}.visible_fraction", f"must be a number in [0, 1], got {frac!r}")


def validate_record(record, source=None, line: int | None = None, strict: bool = True) -> None:
    """Check one manifest record against :data:`MANIFEST_SCHEMA`; raise :class:`InputError` if it breaks it.

    ``source``/``line`` only build the message prefix ``"FILE: line N: KEY: problem"``.
    ``strict=False`` is the real-scan variant (see the schema). Unknown keys are allowed.
    """
    prefix = (f"{source}: " if source else "") + (f"line {line}: " if line is not None else "")
    if not isinstance(record, dict):
        raise InputError(f"{prefix}record must be a JSON object, got {type(record).__name__}")
    required = REQUIRED_KEYS if strict else ("frame", "depth", "intrinsics", "depth_scale", "objects")
    for key in required:
        if key not in record:
            _fail(prefix, key, "missing")
    if not _is_int(record["frame"]) or record["frame"] < 0:
        _fail(prefix, "frame", f"must be an int >= 0, got {record['frame']!r}")
    _relative_path(prefix, "depth", record["depth"])
    for key in OPTIONAL_PATH_KEYS:
        if key in record:
            _relative_path(prefix, key, record[key])

    intr = record["intrinsics"]
    if not isinstance(intr, dict):
        _fail(prefix, "intrinsics", "must be an object {width, height, fx, fy, cx, cy}")
    for key in ("width", "height", "fx", "fy", "cx", "cy"):
        if key not in intr:
            _fail(prefix, f"intrinsics.{key}", "missing")
    for key in ("width", "height"):
        if not _is_int(intr[key]) or intr[key] <= 0:
            _fail(prefix, f"intrinsics.{key}", f"must be an int > 0, got {intr[key]!r}")
    for key in ("fx", "fy", "cx", "cy"):
        _positive_number(prefix, f"intrinsics.{key}", intr[key])

    _positive_number(prefix, "depth_scale", record["depth_scale"])
    for key in ("ir_white_counts", "ir_gamma"):
        if key in record:
            _positive_number(prefix, key, record[key])
    if record.get("world_T_cam") is not None:
        as_rigid(record["world_T_cam"], prefix, "world_T_cam")
    elif strict:
        _fail(prefix, "world_T_cam", "must be a 4x4 rigid transform, got null")
    if "seed" in record and (strict or record["seed"] is not None):
        if not _is_int(record["seed"]):
            _fail(prefix, "seed", f"must be an int, got {record['seed']!r}")

    objects = record["objects"]
    if not isinstance(objects, list):
        _fail(prefix, "objects", f"must be a list, got {type(objects).__name__}")
    seen: set[int] = set()
    for i, obj in enumerate(objects):
        _validate_object(prefix, f"objects[{i}]", obj, strict)
        if obj["id"] in seen:
            _fail(prefix, f"objects[{i}].id", f"duplicate id {obj['id']} in this frame")
        seen.add(obj["id"])


# ---------------------------------------------------------------- file access


def _split(data: bytes):
    """-> (complete lines as (line_no, bytes), trailing bytes without a newline)."""
    parts = data.split(b"\n")
    return list(enumerate(parts[:-1], start=1)), parts[-1]


def _tail_is_record(tail: bytes) -> bool:
    """A last line without newline counts if it is a whole JSON object (hand-written files)."""
    if not tail.strip():
        return False
    try:
        return isinstance(json.loads(tail.decode("utf-8")), dict)
    except (UnicodeDecodeError, ValueError):
        return False


def repair_manifest(path: str | Path) -> bool:
    """Make ``path`` end at a line boundary before appending: cut off a crash-truncated last line.

    A last line without newline that is a complete JSON object just gets its
    newline. Returns True if the file was changed. Missing file: nothing to do.
    """
    path = Path(path)
    if not path.is_file():
        return False
    data = path.read_bytes()
    if not data or data.endswith(b"\n"):
        return False
    _, tail = _split(data)
    with open(path, "r+b") as handle:
        if _tail_is_record(tail):
            handle.seek(0, os.SEEK_END)
            handle.write(b"\n")
        else:
            handle.truncate(len(data) - len(tail))
        handle.flush()
        os.fsync(handle.fileno())
    return True


def append_record(path: str | Path, record: dict, validate: bool = True) -> str:
    """Validate ``record`` and append it to the manifest as one canonical line (flush + fsync).

    Repairs a crash-truncated last line first. Single writer only. Returns the line written (no newline).
    """
    path = Path(path)
    if validate:
        validate_record(to_jsonable(record), source=path)
    try:
        line = dumps_record(record)
    except ValueError as exc:  # NaN/inf somewhere
        raise ValueError(f"{path}: record for frame {record.get('frame')!r} is not valid JSON: {exc}") from None
    path.parent.mkdir(parents=True, exist_ok=True)
    repair_manifest(path)
    with open(path, "ab") as handle:
        handle.write(line.encode("utf-8") + b"\n")
        handle.flush()
        os.fsync(handle.fileno())
    return line


def read_manifest(path: str | Path, validate: bool = True, strict: bool = True) -> list[dict]:
    """Read a manifest -> list of records in file order.

    Blank lines are skipped; a last line without newline that is not a whole
    JSON object (a crash while appending) is ignored. Any other unparsable
    line, an invalid record (with ``validate``; ``strict`` as in
    :func:`validate_record`) or a duplicate ``frame`` raises :class:`InputError`
    ``"FILE: line N: ..."``. A missing file raises :class:`InputError`.
    """
    path = Path(path)
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise InputError(f"{path}: manifest not found") from None
    except OSError as exc:
        raise InputError(f"{path}: cannot read manifest ({exc.strerror or exc})") from None
    lines, tail = _split(data)
    if _tail_is_record(tail):
        lines.append((len(lines) + 1, tail))
    records: list[dict] = []
    first_line: dict[int, int] = {}
    for number, raw in lines:
        if not raw.strip():
            continue
        try:
            record = json.loads(raw.decode("utf-8"))
        except UnicodeDecodeError:
            raise InputError(f"{path}: line {number}: not UTF-8 text") from None
        except ValueError as exc:
            raise InputError(f"{path}: line {number}: not valid JSON ({exc.msg} at column {exc.colno})") from None
        if validate:
            validate_record(record, source=path, line=number, strict=strict)
        elif not isinstance(record, dict):
            raise InputError(f"{path}: line {number}: record must be a JSON object")
        frame = record.get("frame")
        if _is_int(frame):
            if frame in first_line:
                raise InputError(
                    f"{path}: line {number}: frame: duplicate frame {frame} (first on line {first_line[frame]})"
                )
            first_line[frame] = number
        records.append(record)
    return records


def sorted_records(records: list[dict]) -> list[dict]:
    """Records sorted by ``frame`` (stable)."""
    return sorted(records, key=lambda r: r["frame"])


#: run.json's name for the built-in scene list (no file).
BUILT_IN_SCENES = "built-in"


def file_digest(path: str | Path | None) -> str:
    """The first 16 hex digits of a file's SHA-256, as run.json records a scene list's (``"built-in"`` for None)."""
    if path is None:
        return BUILT_IN_SCENES
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()[:16]
