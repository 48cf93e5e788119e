"""One scan frame as the readers return it (:class:`ScanFrame`, :class:`ScanObject`), its lazily decoded depth, and
the small checks both layouts' readers share (:mod:`ddsgen.io.scanfolder`, :mod:`ddsgen.io.bop_reader`)."""

from __future__ import annotations

import dataclasses
import json
import math
import struct
from pathlib import Path

import numpy as np

from ddsgen.errors import InputError
from ddsgen.io.exr import read_exr
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
@dataclasses.dataclass(frozen=True)
class RenderedScene:
    """How ddsgen rendered a frame, from its folder's run.json: the scene list (None: the built-in one) and the seed.
    ``ddsgen.scene.sampling.sample_frame(load_scene_list(scenes_path), frame, seed)`` makes the whole scene again:
    distractors, table, floor and walls, which the manifest does not list. ``missing`` says why it cannot be made
    again (the scene list moved or changed since the render); empty when it can."""

    scenes_path: str | None
    seed: int
    missing: str = ""


@dataclasses.dataclass
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
    rendered: a ddsgen render's :class:`RenderedScene` (its folder has run.json), else None.
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
    rendered: RenderedScene | None = None
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


def check_size(path: Path, intrinsics: Intrinsics, source) -> None:
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
