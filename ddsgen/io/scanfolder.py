"""Read a folder of (real or simulated) depth scans: ddsgen's own layout or the BOP layout.

:func:`read_scan_folder` auto-detects the layout:

* **ddsgen** (DESIGN.md §3): ``DIR/manifest.jsonl`` (validated non-strictly, so
  hand-written real-scan manifests need no ``seed``/``bbox``/``visible_fraction``
  and may have ``world_T_cam: null``); each record's ``depth`` file (16-bit PNG
  scaled by ``depth_scale``, or float32 EXR in metres); meshes are file paths
  relative to ``DIR`` or absolute, or ``"shape:NAME"`` procedural references,
  returned as-is for the caller to resolve. An optional per-object
  ``mesh_scale`` key (default 1.0) gives metres per mesh unit.
* **BOP** (e.g. LineMOD): ``DIR`` is a scene folder (``scene_camera.json``,
  ``scene_gt.json``, ``depth/NNNNNN.png``), a split folder holding scene
  folders, or a dataset root holding a split (``test/``, ``train/``, ...;
  with several splits, ``test`` is used). Models ``models/obj_NNNNNN.ply``
  (millimetres -> ``mesh_scale`` 0.001) are found next to the scene folder or
  up to 3 parent levels above it. ``cam_t_m2c`` is in mm and is converted to
  metres; depth in metres is ``png * depth_scale / 1000`` with each image's own
  ``depth_scale``. ``world_T_cam`` comes from ``cam_R_w2c``/``cam_t_w2c`` when
  present, else None. Read as BOP datasets are published: every scene of a split
  is read (frame names keep scene and image id, ``"000002/000017"``); ``rgb/`` is
  never needed; rotations are stored rounded, so any within
  :data:`ddsgen.io.bop_reader.BOP_ROTATION_TOL` of orthonormal is replaced by the nearest rotation
  (polar decomposition); ``scene_gt_info.json``, when present, gives each
  object's ``visible_fraction`` (``visib_fract``), and objects with
  ``visib_fract`` 0 (fully occluded or out of view) are left out of the frame.

Depth images are loaded **lazily**: reading a folder checks that every depth
file exists, is a readable 16-bit single-channel PNG (or EXR) and has the
size of its intrinsics, from the file headers only; the pixels are decoded
on the first access to ``ScanFrame.depth`` and cached on the frame
(``ScanFrame.release()`` drops the cache; ``read_scan_folder(..., eager=True)``
decodes everything up front). Every problem raises :class:`InputError` naming
the file and the problem.
"""

from __future__ import annotations

import dataclasses
import json
import math
import struct
from pathlib import Path

import numpy as np

from ddsgen.errors import InputError
from ddsgen.io.exr import read_exr
from ddsgen.io.manifest import read_manifest
from ddsgen.io.png import read_depth_png
from ddsgen.preset import Intrinsics

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


@dataclasses.dataclass
class ScanObject:
    """One object instance in a frame.

    id: instance index >= 1 (its value in an instance mask; BOP: position in scene_gt + 1).
    class_name: class name (ddsgen: the record's ``class``; BOP: ``"obj_000006"``).
    obj_id: the stable object id (BOP: ``obj_id``; ddsgen: the record's ``obj_id``), None when not given.
    mesh_path: mesh file (absolute path) or a ``"shape:NAME"`` procedural reference.
    mesh_scale: metres per mesh unit (0.001 for BOP's millimetre models, else 1.0 unless the manifest says).
    cam_T_obj: float64 (4, 4) rigid transform, object -> camera, translation in metres.
    visible_fraction: share of the object's silhouette that is visible in [0, 1] (BOP: ``visib_fract``
        of scene_gt_info.json; ddsgen: the record's ``visible_fraction``), None if not given.
    """

    id: int
    class_name: str
    mesh_path: str
    mesh_scale: float
    cam_T_obj: np.ndarray
    obj_id: int | None = None
    visible_fraction: float | None = None


class _LazyDepth:
    """Data descriptor: ``frame.depth`` decodes the depth file on first access and caches it."""

    def __set_name__(self, owner, name):
        self.attr = "_" + name

    def __get__(self, obj, objtype=None):
        if obj is None:
            return None  # the dataclass default: not loaded yet
        value = obj.__dict__.get(self.attr)
        if value is None:
            value = obj.load_depth()
            obj.__dict__[self.attr] = value
        return value

    def __set__(self, obj, value):
        obj.__dict__[self.attr] = None if value is None else np.asarray(value, dtype=np.float32)


@dataclasses.dataclass(repr=False, eq=False)
class ScanFrame:
    """One depth scan with what is known about its scene.

    name: ``"SCENE/NNNNNN"`` (BOP: scene folder name / image id; ddsgen: folder name / frame).
    depth: float32 (H, W) metres, 0 = invalid. Lazy: decoded from ``source_depth_path`` on first
        access and cached (pass an array to the constructor to skip the file).
    intrinsics: :class:`ddsgen.preset.Intrinsics` (width/height are the depth image's).
    objects: list of :class:`ScanObject`.
    world_T_cam: float64 (4, 4) camera pose in the world, or None if unknown.
    source_depth_path: the depth file (PNG or EXR).
    depth_scale: metres per PNG unit used to decode a PNG.
    layout: ``"ddsgen"`` or ``"bop"``; frame: frame number / BOP image id.
    record: the raw manifest record (ddsgen layout), else None.
    """

    name: str
    intrinsics: Intrinsics
    objects: list[ScanObject]
    world_T_cam: np.ndarray | None
    source_depth_path: str
    depth_scale: float = 0.001
    layout: str = "ddsgen"
    frame: int = 0
    record: dict | None = None
    depth: np.ndarray | None = _LazyDepth()

    def load_depth(self) -> np.ndarray:
        """Decode the depth file -> float32 (H, W) metres (not cached; ``depth`` caches)."""
        path = Path(self.source_depth_path)
        shape = (self.intrinsics.height, self.intrinsics.width)
        if path.suffix.lower() == ".exr":
            depth = read_exr(path)
            if depth.shape != shape:
                raise InputError(
                    f"{path}: depth EXR is {depth.shape[1]}x{depth.shape[0]} px, expected {shape[1]}x{shape[0]}"
                )
            return depth
        return read_depth_png(path, self.depth_scale, expected_shape=shape)

    def release(self) -> None:
        """Drop the cached depth image (it is decoded again on the next access)."""
        self.__dict__["_depth"] = None

    def __repr__(self) -> str:
        loaded = self.__dict__.get("_depth") is not None
        return (
            f"ScanFrame(name={self.name!r}, layout={self.layout!r}, {self.intrinsics.width}x{self.intrinsics.height}, "
            f"objects={len(self.objects)}, depth={'loaded' if loaded else 'lazy'}, source={self.source_depth_path!r})"
        )


# ---------------------------------------------------------------- helpers


def depth_image_size(path: Path, what: str = "depth") -> tuple[int, int]:
    """(H, W) of a depth PNG (must be 16-bit grey) or EXR, from its header; InputError if absent/unreadable."""
    if not path.is_file():
        raise InputError(f"{path}: {what} image not found")
    if path.suffix.lower() == ".exr":
        try:
            import OpenEXR

            header = OpenEXR.File(str(path), header_only=True).header()
            (x0, y0), (x1, y1) = header["dataWindow"]
            return int(y1 - y0 + 1), int(x1 - x0 + 1)
        except Exception as exc:
            raise InputError(f"{path}: cannot read EXR ({type(exc).__name__}: {exc})") from None
    with open(path, "rb") as handle:
        head = handle.read(26)
    if len(head) < 26 or head[:8] != PNG_SIGNATURE or head[12:16] != b"IHDR":
        raise InputError(f"{path}: cannot read {what} PNG (not a PNG file)")
    width, height = struct.unpack(">II", head[16:24])
    bit_depth, colour_type = head[24], head[25]
    if colour_type != 0:
        kind = {2: "colour (RGB)", 3: "palette", 4: "grey+alpha", 6: "colour (RGBA)"}.get(colour_type, "multi-channel")
        raise InputError(f"{path}: {what} PNG must be 16-bit single-channel, got {kind}")
    if bit_depth != 16:
        raise InputError(f"{path}: {what} PNG must be 16-bit single-channel, got {bit_depth}-bit")
    return int(height), int(width)


def _check_size(path: Path, intrinsics: Intrinsics, source) -> None:
    height, width = depth_image_size(path)
    if (height, width) != (intrinsics.height, intrinsics.width):
        raise InputError(
            f"{path}: depth image is {width}x{height} px, but {source} gives {intrinsics.width}x{intrinsics.height}"
        )


def load_json(path: Path):
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise InputError(f"{path}: not found") from None
    except UnicodeDecodeError:
        raise InputError(f"{path}: not UTF-8 text") from None
    except ValueError as exc:
        raise InputError(f"{path}: not valid JSON ({exc})") from None


def is_positive_number(value) -> bool:
    """A finite number > 0 (not a bool)."""
    return isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value) and value > 0


def finite_numbers(path, key, value, count) -> np.ndarray:
    try:
        array = np.asarray(value, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise InputError(f"{path}: {key}: must be a list of {count} numbers") from None
    if array.size != count or isinstance(value, str):
        raise InputError(f"{path}: {key}: must be a list of {count} numbers, got {array.size}")
    if not np.isfinite(array).all():
        raise InputError(f"{path}: {key}: has non-finite values")
    return array


# ---------------------------------------------------------------- ddsgen layout


def _read_ddsgen(folder: Path) -> list[ScanFrame]:
    manifest = folder / "manifest.jsonl"
    records = read_manifest(manifest, strict=False)
    if not records:
        raise InputError(f"{manifest}: no complete records")
    frames = []
    for record in sorted(records, key=lambda r: r["frame"]):
        where = f"{manifest}: frame {record['frame']}"
        intr = record["intrinsics"]
        intrinsics = Intrinsics(
            width=int(intr["width"]),
            height=int(intr["height"]),
            fx=float(intr["fx"]),
            fy=float(intr["fy"]),
            cx=float(intr["cx"]),
            cy=float(intr["cy"]),
        )
        depth_path = folder / record["depth"]
        if not depth_path.is_file():
            raise InputError(f"{where}: depth: file not found: {depth_path}")
        _check_size(depth_path, intrinsics, f"{manifest} (frame {record['frame']})")
        objects = []
        for i, obj in enumerate(record["objects"]):
            mesh = obj["mesh"]
            if not mesh.startswith("shape:"):
                mesh_file = Path(mesh) if Path(mesh).is_absolute() else folder / mesh
                if not mesh_file.is_file():
                    raise InputError(f"{where}: objects[{i}].mesh: file not found: {mesh_file}")
                mesh = str(mesh_file)
            scale = obj.get("mesh_scale", 1.0)
            if not is_positive_number(scale):
                raise InputError(f"{where}: objects[{i}].mesh_scale: must be a finite number > 0, got {scale!r}")
            objects.append(
                ScanObject(
                    id=int(obj["id"]),
                    class_name=obj["class"],
                    mesh_path=mesh,
                    mesh_scale=float(scale),
                    cam_T_obj=np.array(obj["cam_T_obj"], dtype=np.float64),
                    obj_id=None if obj.get("obj_id") is None else int(obj["obj_id"]),
                    visible_fraction=None if obj.get("visible_fraction") is None else float(obj["visible_fraction"]),
                )
            )
        world = record.get("world_T_cam")
        frames.append(
            ScanFrame(
                name=f"{folder.resolve().name}/{record['frame']:06d}",
                intrinsics=intrinsics,
                objects=objects,
                world_T_cam=None if world is None else np.array(world, dtype=np.float64),
                source_depth_path=str(depth_path),
                depth_scale=float(record["depth_scale"]),
                layout="ddsgen",
                frame=int(record["frame"]),
                record=record,
            )
        )
    return frames


# ---------------------------------------------------------------- entry point


def detect_layout(path: str | Path) -> str:
    """``"ddsgen"`` or ``"bop"``; :class:`InputError` if ``path`` is neither."""
    folder = Path(path)
    if folder.is_file() and folder.name == "manifest.jsonl":
        return "ddsgen"
    if not folder.is_dir():
        raise InputError(f"{folder}: scan folder not found")
    if (folder / "manifest.jsonl").is_file():
        return "ddsgen"
    from ddsgen.io.bop_reader import bop_scene_folders

    if bop_scene_folders(folder):
        return "bop"
    raise InputError(
        f"{folder}: not a scan folder: no manifest.jsonl (ddsgen layout) and no scene_camera.json/scene_gt.json "
        f"in it, its subfolders or a split folder (BOP layout)"
    )


def read_scan_folder(path: str | Path, eager: bool = False) -> list[ScanFrame]:
    """Read every frame of a scan folder (layout auto-detected, see the module docstring).

    Frames are sorted (ddsgen: by frame; BOP: by scene, then image id). Depth
    is lazy unless ``eager``. Raises :class:`InputError` for any problem.
    """
    folder = Path(path)
    if folder.is_file() and folder.name == "manifest.jsonl":
        folder = folder.parent
    layout = detect_layout(folder)
    if layout == "ddsgen":
        frames = _read_ddsgen(folder)
    else:
        from ddsgen.io.bop_reader import bop_scene_folders, read_bop_scene

        frames = [frame for scene in bop_scene_folders(folder) for frame in read_bop_scene(scene)]
    if eager:
        for frame in frames:
            _ = frame.depth
    return frames
