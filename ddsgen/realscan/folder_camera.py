"""The camera of a plain folder of depth images (``ddsgen fit --unpaired``): given, read from a BOP file, or none.

A folder of depth images carries no optics, so the unpaired fit renders with the preset's camera unless told
otherwise. The camera comes from, in this order:

* ``--camera FX,FY,CX,CY``: four numbers, px of the frames' own size;
* ``--camera FILE.json``: a BOP ``camera.json`` (``fx``, ``fy``, ``cx``, ``cy``) or ``scene_camera.json`` (per image
  ``cam_K``, row-major 3 x 3);
* without ``--camera``: the folder's own BOP file, if it has one -- ``camera.json`` or ``scene_camera.json`` in the
  folder, or ``scene_camera.json`` in its sequence folders (a BOP split: ``test/000001/``, ...).

An unpaired fit renders with one camera, so every image of every file found must have the same one; if they differ
the input is refused (naming the first two that differ) rather than averaged. A BOP file's ``depth_scale`` (mm per
PNG unit) is read with it, and is the folder's depth scale unless ``--depth-scale`` is given; images whose scales
differ are refused the same way.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ddsgen.errors import InputError
from ddsgen.io.scan_frame import finite_numbers, load_json
from ddsgen.runner import parse_camera

#: BOP camera files, in the order they are looked for.
CAMERA_FILES = ("camera.json", "scene_camera.json")
#: Two cameras are one when every value agrees within this share (BOP files round to a few decimals).
SAME_CAMERA_RTOL = 1e-6


@dataclass(frozen=True)
class FolderCamera:
    """What a folder's camera says: ``intrinsics`` (fx, fy, cx, cy) px or None (the preset's); ``source``, in words;
    ``depth_scale_m``: metres per PNG unit from a BOP file, or None (not said)."""

    intrinsics: tuple[float, float, float, float] | None = None
    source: str | None = None
    depth_scale_m: float | None = None


def folder_camera(option: str | None, real_dir: str | Path) -> FolderCamera:
    """The camera of the folder ``real_dir`` given ``--camera``'s text ``option`` (see the module docstring).

    InputError when ``option`` is neither four numbers nor a readable BOP camera file, or when the cameras (or depth
    scales) of the images differ.
    """
    if option is not None:
        path = Path(option)
        if path.suffix.lower() == ".json":
            if not path.is_file():
                raise InputError(f"--camera: {path}: not found")
            return read_camera_file(path, f"read from {path}")
        return FolderCamera(parse_camera(option), "given by --camera")
    folder = Path(real_dir)
    found = [folder / name for name in CAMERA_FILES if (folder / name).is_file()]
    if not found and folder.is_dir():
        found = sorted(p / "scene_camera.json" for p in folder.iterdir() if (p / "scene_camera.json").is_file())
    if not found:
        return FolderCamera()
    more = f" and {len(found) - 1} more like it" if len(found) > 1 else ""
    cameras = [read_camera_file(path, f"read from the folder's {found[0]}{more}") for path in found]
    for path, camera in zip(found[1:], cameras[1:]):
        _check_same(cameras[0].intrinsics, camera.intrinsics, f"{path}", f"{found[0]}'s")
        _check_same_scale(cameras[0].depth_scale_m, camera.depth_scale_m, f"{path}", f"{found[0]}'s")
    return cameras[0]


def read_camera_file(path: Path, source: str = "") -> FolderCamera:
    """The camera of a BOP ``camera.json`` or ``scene_camera.json`` (every image's the same) and its depth scale."""
    data = load_json(path)
    if not isinstance(data, dict) or not data:
        raise InputError(f"{path}: must be a BOP camera.json (fx, fy, cx, cy) or scene_camera.json (image id -> cam_K)")
    if all(key in data for key in ("fx", "fy", "cx", "cy")):  # camera.json
        camera = finite_numbers(path, "fx, fy, cx, cy", [data[key] for key in ("fx", "fy", "cx", "cy")], 4)
        return FolderCamera(tuple(float(v) for v in camera), source, _scale_m(path, "depth_scale", data))
    cameras = []
    for image_id, entry in data.items():
        if not isinstance(entry, dict) or "cam_K" not in entry:
            raise InputError(f"{path}: {image_id}.cam_K: missing (a BOP scene_camera.json gives each image's cam_K)")
        k = finite_numbers(path, f"{image_id}.cam_K", entry["cam_K"], 9).reshape(3, 3)
        camera = (float(k[0, 0]), float(k[1, 1]), float(k[0, 2]), float(k[1, 2]))
        cameras.append((image_id, camera, _scale_m(path, f"{image_id}.depth_scale", entry)))
    first_id, first, first_scale = cameras[0]
    for image_id, camera, scale in cameras[1:]:
        _check_same(first, camera, f"{path}: {image_id}.cam_K", f"image {first_id}'s")
        _check_same_scale(first_scale, scale, f"{path}: {image_id}.depth_scale", f"image {first_id}'s")
    return FolderCamera(first, source, first_scale)


def _scale_m(path: Path, key: str, entry: dict) -> float | None:
    """A BOP depth_scale (mm per PNG unit) in metres per unit; None when the entry has none."""
    if "depth_scale" not in entry:
        return None
    value = entry["depth_scale"]
    if isinstance(value, bool) or not isinstance(value, int | float) or not np.isfinite(value) or value <= 0:
        raise InputError(f"{path}: {key}: must be a number > 0 (mm per PNG unit), got {value!r}")
    return float(value) / 1000.0


def _check_same_scale(first: float | None, other: float | None, where: str, first_where: str) -> None:
    if first != other:
        raise InputError(f"{where}: depth scale {other} m per unit differs from {first_where} {first}: the images of "
                         f"one folder are read with one scale; fit them apart, or give --depth-scale")  # fmt: skip


def _check_same(first, other, where: str, first_where: str) -> None:
    if not np.allclose(first, other, rtol=SAME_CAMERA_RTOL, atol=0.0):
        raise InputError(f"{where}: camera (fx, fy, cx, cy) {tuple(round(v, 3) for v in other)} differs from "
                         f"{first_where} {tuple(round(v, 3) for v in first)}: an unpaired fit renders with one "
                         f"camera; fit the images of each camera apart, or give --camera")  # fmt: skip
