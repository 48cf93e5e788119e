"""The BOP layout of a scan folder (the reader behind :func:`ddsgen.io.scanfolder.read_scan_folder`).

See :mod:`ddsgen.io.scanfolder` for the layout's rules (scene / split / dataset-root folders,
models, units, rounded rotations, scene_gt_info visibility, per-image depth_scale).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ddsgen.errors import InputError
from ddsgen.io.scan_frame import (
    ScanFrame,
    ScanObject,
    depth_image_size,
    finite_numbers,
    is_positive_number,
    load_json,
)
from ddsgen.preset import Intrinsics

#: How many parent levels above a BOP scene folder are searched for ``models/``.
BOP_MODEL_SEARCH_LEVELS = 3
BOP_SPLIT_PREFERENCE = ("test", "val", "train")
#: Largest max |R R^T - I| of a BOP rotation that is accepted (and re-orthonormalised). Published ground
#: truth is rounded (LineMOD-Occluded: 3e-4); a real error (a wrong matrix, a transposed row) is far above.
BOP_ROTATION_TOL = 1e-2


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
    camera = load_json(path)
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
    rotation = finite_numbers(path, key, value, 9).reshape(3, 3)
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


def read_bop_scene(scene: Path) -> list[ScanFrame]:
    camera_path, gt_path = scene / "scene_camera.json", scene / "scene_gt.json"
    for path in (camera_path, gt_path):
        if not path.is_file():
            raise InputError(f"{path}: not found (a BOP scene folder needs scene_camera.json and scene_gt.json)")
    cameras = _bop_image_ids(camera_path, load_json(camera_path))
    gts = _bop_image_ids(gt_path, load_json(gt_path))
    info_path = scene / "scene_gt_info.json"
    infos = _bop_image_ids(info_path, load_json(info_path)) if info_path.is_file() else None
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
        cam_k = finite_numbers(camera_path, f"{key}.cam_K", camera["cam_K"], 9).reshape(3, 3)
        fx, fy, cx, cy = cam_k[0, 0], cam_k[1, 1], cam_k[0, 2], cam_k[1, 2]
        if not (fx > 0 and fy > 0) or cam_k[0, 1] != 0 or np.any(cam_k[2] != [0, 0, 1]):
            raise InputError(
                f"{camera_path}: {key}.cam_K: not a pinhole matrix [fx 0 cx 0 fy cy 0 0 1]: {cam_k.ravel().tolist()}"
            )
        scale_mm = camera["depth_scale"]
        if not is_positive_number(scale_mm):
            raise InputError(f"{camera_path}: {key}.depth_scale: must be a finite number > 0, got {scale_mm!r}")

        depth_path = scene / "depth" / f"{image_id:06d}.png"
        if not depth_path.is_file():
            raise InputError(f"{depth_path}: depth image not found (listed in {camera_path.name} as {key})")
        height, width = depth_image_size(depth_path)
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
            cam_T_world[:3, 3] = finite_numbers(camera_path, f"{key}.cam_t_w2c", camera.get("cam_t_w2c"), 3) / 1000.0
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
            cam_T_obj[:3, 3] = finite_numbers(gt_path, f"{where}.cam_t_m2c", entry["cam_t_m2c"], 3) / 1000.0  # mm -> m
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


def bop_scene_folders(folder: Path) -> list[Path]:
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
