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
  :data:`BOP_ROTATION_TOL` of orthonormal is replaced by the nearest rotation
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

#: How many parent levels above a BOP scene folder are searched for ``models/``.
BOP_MODEL_SEARCH_LEVELS = 3
BOP_SPLIT_PREFERENCE = ("test", "val", "train")
#: Largest max |R R^T - I| of a BOP rotation that is accepted (and re-orthonormalised). Published ground
#: truth is rounded (LineMOD-Occluded: 3e-4); a real error (a wrong matrix, a transposed row) is far above.
BOP_ROTATION_TOL = 1e-2
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


@dataclasses.dataclass
class ScanObject:
    """One object instance in a frame.

    id: instance index >= 1 (its value in an instance mask; BOP: position in scene_gt + 1).
    class_name: class name (ddsgen: the record's ``class``; BOP: ``"obj_000006"``).
    obj_id: BOP object id (int), None for the ddsgen layout.
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


def _image_size(path: Path, what: str = "depth") -> tuple[int, int]:
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
    height, width = _image_size(path)
    if (height, width) != (intrinsics.height, intrinsics.width):
        raise InputError(
            f"{path}: depth image is {width}x{height} px, but {source} gives {intrinsics.width}x{intrinsics.height}"
        )


def _load_json(path: Path):
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise InputError(f"{path}: not found") from None
    except UnicodeDecodeError:
        raise InputError(f"{path}: not UTF-8 text") from None
    except ValueError as exc:
        raise InputError(f"{path}: not valid JSON ({exc})") from None


def _positive(value) -> bool:
    """A finite number > 0 (not a bool)."""
    return isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value) and value > 0


def _numbers(path, key, value, count) -> np.ndarray:
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
            if not _positive(scale):
                raise InputError(f"{where}: objects[{i}].mesh_scale: must be a finite number > 0, got {scale!r}")
            objects.append(
                ScanObject(
                    id=int(obj["id"]),
                    class_name=obj["class"],
                    mesh_path=mesh,
                    mesh_scale=float(scale),
                    cam_T_obj=np.array(obj["cam_T_obj"], dtype=np.float64),
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


# ---------------------------------------------------------------- BOP layout


def _is_bop_scene(folder: Path) -> bool:
    return (folder / "scene_camera.json").is_file() or (folder / "scene_gt.json").is_file()


def _bop_scenes_in(folder: Path) -> list[Path]:
    if not folder.is_dir():
        return []
    return sorted(p for p in folder.iterdir() if p.is_dir() and _is_bop_scene(p))


def _find_models(scene: Path) -> Path:
    here = scene.resolve()
    for _ in range(BOP_MODEL_SEARCH_LEVELS + 1):
        candidate = here / "models"
        if candidate.is_dir():
            return candidate
        if here.parent == here:
            break
        here = here.parent
    raise InputError(
        f"{scene}: models: no models/ folder in the scene folder or up to {BOP_MODEL_SEARCH_LEVELS} levels above it"
    )


def _bop_image_ids(path: Path, data) -> dict[int, object]:
    if not isinstance(data, dict):
        raise InputError(f"{path}: must map image ids to entries")
    out = {}
    for key, value in data.items():
        try:
            out[int(key)] = value
        except ValueError:
            raise InputError(f"{path}: {key}: image id must be an integer") from None
    return out


def _bop_camera_size(path: Path) -> tuple[int, int] | None:
    """(H, W) from the dataset's camera.json (BOP ships one at the root), None if absent."""
    if not path.is_file():
        return None
    camera = _load_json(path)
    if not isinstance(camera, dict) or "width" not in camera or "height" not in camera:
        return None
    width, height = camera["width"], camera["height"]
    if not all(isinstance(v, int) and not isinstance(v, bool) and v > 0 for v in (width, height)):
        raise InputError(f"{path}: width/height: must be ints > 0, got {width!r}x{height!r}")
    return height, width


def _bop_rotation(path: Path, key: str, value) -> np.ndarray:
    """A BOP rotation (9 numbers, row-major) -> the nearest rotation matrix float64 (3, 3).

    Accepted when max |R R^T - I| <= :data:`BOP_ROTATION_TOL` and det > 0; the polar factor
    U V^T of R's SVD is the orthonormal matrix closest to R (Frobenius norm).
    """
    rotation = _numbers(path, key, value, 9).reshape(3, 3)
    error = float(np.abs(rotation @ rotation.T - np.eye(3)).max())
    if error > BOP_ROTATION_TOL:
        raise InputError(f"{path}: {key}: rotation is not orthonormal (max |R R^T - I| = {error:.2g} > "
                         f"{BOP_ROTATION_TOL:g})")  # fmt: skip
    det = float(np.linalg.det(rotation))
    if det <= 0:
        raise InputError(f"{path}: {key}: rotation determinant is {det:.6g}, must be +1 (a reflection?)")
    u, _, vt = np.linalg.svd(rotation)
    return u @ vt


def _bop_visibility(info_path: Path, infos: dict | None, image_id: int, count: int) -> list[float | None]:
    """``visib_fract`` of each of the ``count`` ground-truth objects of an image (None without scene_gt_info)."""
    if infos is None:
        return [None] * count
    key = str(image_id)
    entries = infos.get(image_id)
    if not isinstance(entries, list) or len(entries) != count:
        got = "missing" if entries is None else f"{len(entries)} entries" if isinstance(entries, list) else "not a list"
        raise InputError(f"{info_path}: {key}: must list one entry per object of scene_gt.json ({count}), got {got}")
    fractions = []
    for index, entry in enumerate(entries):
        value = entry.get("visib_fract") if isinstance(entry, dict) else None
        if isinstance(value, bool) or not isinstance(value, int | float) or not 0.0 <= value <= 1.0:
            raise InputError(f"{info_path}: {key}[{index}].visib_fract: must be a number in [0, 1], got {value!r}")
        fractions.append(float(value))
    return fractions


def _read_bop_scene(scene: Path) -> list[ScanFrame]:
    camera_path, gt_path = scene / "scene_camera.json", scene / "scene_gt.json"
    for path in (camera_path, gt_path):
        if not path.is_file():
            raise InputError(f"{path}: not found (a BOP scene folder needs scene_camera.json and scene_gt.json)")
    cameras = _bop_image_ids(camera_path, _load_json(camera_path))
    gts = _bop_image_ids(gt_path, _load_json(gt_path))
    info_path = scene / "scene_gt_info.json"
    infos = _bop_image_ids(info_path, _load_json(info_path)) if info_path.is_file() else None
    if not cameras:
        raise InputError(f"{camera_path}: no images")
    models = _find_models(scene)
    expected_size = _bop_camera_size(models.parent / "camera.json")
    frames = []
    for image_id in sorted(cameras):
        camera = cameras[image_id]
        key = str(image_id)
        if not isinstance(camera, dict):
            raise InputError(f"{camera_path}: {key}: must be an object with cam_K and depth_scale")
        for name in ("cam_K", "depth_scale"):
            if name not in camera:
                raise InputError(f"{camera_path}: {key}.{name}: missing")
        cam_k = _numbers(camera_path, f"{key}.cam_K", camera["cam_K"], 9).reshape(3, 3)
        fx, fy, cx, cy = cam_k[0, 0], cam_k[1, 1], cam_k[0, 2], cam_k[1, 2]
        if not (fx > 0 and fy > 0) or cam_k[0, 1] != 0 or np.any(cam_k[2] != [0, 0, 1]):
            raise InputError(
                f"{camera_path}: {key}.cam_K: not a pinhole matrix [fx 0 cx 0 fy cy 0 0 1]: {cam_k.ravel().tolist()}"
            )
        scale_mm = camera["depth_scale"]
        if not _positive(scale_mm):
            raise InputError(f"{camera_path}: {key}.depth_scale: must be a finite number > 0, got {scale_mm!r}")

        depth_path = scene / "depth" / f"{image_id:06d}.png"
        if not depth_path.is_file():
            raise InputError(f"{depth_path}: depth image not found (listed in {camera_path.name} as {key})")
        height, width = _image_size(depth_path)
        if expected_size is not None and (height, width) != expected_size:
            raise InputError(
                f"{depth_path}: depth image is {width}x{height} px, but {models.parent / 'camera.json'} gives "
                f"{expected_size[1]}x{expected_size[0]}"
            )
        if not (0 < cx < width and 0 < cy < height):
            raise InputError(
                f"{depth_path}: depth image is {width}x{height} px, but {camera_path.name} {key}.cam_K puts the "
                f"principal point at ({cx:g}, {cy:g}): wrong image size?"
            )
        intrinsics = Intrinsics(width=width, height=height, fx=float(fx), fy=float(fy), cx=float(cx), cy=float(cy))

        world_T_cam = None
        if "cam_R_w2c" in camera or "cam_t_w2c" in camera:
            cam_T_world = np.eye(4)
            cam_T_world[:3, :3] = _bop_rotation(camera_path, f"{key}.cam_R_w2c", camera.get("cam_R_w2c"))
            cam_T_world[:3, 3] = _numbers(camera_path, f"{key}.cam_t_w2c", camera.get("cam_t_w2c"), 3) / 1000.0
            world_T_cam = np.eye(4)  # the rigid inverse
            world_T_cam[:3, :3] = cam_T_world[:3, :3].T
            world_T_cam[:3, 3] = -cam_T_world[:3, :3].T @ cam_T_world[:3, 3]

        if image_id not in gts:
            raise InputError(f"{gt_path}: {key}: missing (image {key} of {camera_path.name} has no ground truth)")
        entries = gts[image_id]
        if not isinstance(entries, list):
            raise InputError(f"{gt_path}: {key}: must be a list of {{obj_id, cam_R_m2c, cam_t_m2c}}")
        visibility = _bop_visibility(info_path, infos, image_id, len(entries))
        objects = []
        for index, entry in enumerate(entries):
            where = f"{key}[{index}]"
            if not isinstance(entry, dict):
                raise InputError(f"{gt_path}: {where}: must be an object {{obj_id, cam_R_m2c, cam_t_m2c}}")
            for name in ("obj_id", "cam_R_m2c", "cam_t_m2c"):
                if name not in entry:
                    raise InputError(f"{gt_path}: {where}.{name}: missing")
            obj_id = entry["obj_id"]
            if isinstance(obj_id, bool) or not isinstance(obj_id, int) or obj_id < 0:
                raise InputError(f"{gt_path}: {where}.obj_id: must be an int >= 0, got {obj_id!r}")
            cam_T_obj = np.eye(4)
            cam_T_obj[:3, :3] = _bop_rotation(gt_path, f"{where}.cam_R_m2c", entry["cam_R_m2c"])
            cam_T_obj[:3, 3] = _numbers(gt_path, f"{where}.cam_t_m2c", entry["cam_t_m2c"], 3) / 1000.0  # mm -> m
            mesh = models / f"obj_{obj_id:06d}.ply"
            if not mesh.is_file():
                raise InputError(f"{mesh}: model of obj_id {obj_id} not found ({gt_path.name} {where})")
            if visibility[index] == 0.0:
                continue  # fully occluded or out of view: nothing of it is in the image (ids keep BOP's index)
            objects.append(
                ScanObject(
                    id=index + 1,
                    class_name=f"obj_{obj_id:06d}",
                    mesh_path=str(mesh),
                    mesh_scale=0.001,
                    cam_T_obj=cam_T_obj,
                    obj_id=obj_id,
                    visible_fraction=visibility[index],
                )
            )
        frames.append(
            ScanFrame(
                name=f"{scene.resolve().name}/{image_id:06d}",
                intrinsics=intrinsics,
                objects=objects,
                world_T_cam=world_T_cam,
                source_depth_path=str(depth_path),
                depth_scale=float(scale_mm) / 1000.0,
                layout="bop",
                frame=image_id,
            )
        )
    return frames


def _bop_scene_folders(folder: Path) -> list[Path]:
    """Scene folders for a BOP scene, split or dataset-root folder; [] if none of those."""
    if _is_bop_scene(folder):
        return [folder]
    scenes = _bop_scenes_in(folder)
    if scenes:
        return scenes
    splits = {p.name: _bop_scenes_in(p) for p in sorted(folder.iterdir()) if p.is_dir()}
    splits = {name: scenes for name, scenes in splits.items() if scenes}
    if not splits:
        return []
    if len(splits) == 1:
        return next(iter(splits.values()))
    for wanted in BOP_SPLIT_PREFERENCE:
        if wanted in splits:
            return splits[wanted]
    raise InputError(
        f"{folder}: several BOP splits ({', '.join(splits)}); pass one of them (e.g. {folder / next(iter(splits))})"
    )


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
    if _bop_scene_folders(folder):
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
        frames = [frame for scene in _bop_scene_folders(folder) for frame in _read_bop_scene(scene)]
    if eager:
        for frame in frames:
            _ = frame.depth
    return frames
