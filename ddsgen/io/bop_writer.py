"""Write a rendered dataset in the BOP layout (``ddsgen render ... --format bop``).

BOP (Hodan et al., https://bop.felk.cvut.cz) is how public 6-DoF pose datasets such as
LineMOD ship, and what BOP-toolkit-based training code reads. ``--format bop --out ROOT``
renders through ddsgen's own layout in ``ROOT/ddsgen/`` (so resume, determinism and the
manifest work as usual; it is also a valid scan folder) and then writes, from its manifest::

    ROOT/
      camera.json                    {cx, cy, depth_scale, fx, fy, height, width}
      models/obj_NNNNNN.ply          one model per obj_id (the manifest objects' obj_id, see
                                     ddsgen/scene/identity.py), millimetres, binary PLY with
                                     vertex normals, triangles
      models/models_info.json        {obj_id: {diameter, min_x, min_y, min_z, size_x, size_y, size_z}} (mm)
      models/models_names.json       (ddsgen extra) {obj_id: {class, mesh, mesh_scale}}
      train_pbr/SSSSSS/              one BOP scene per 1000 frames (scene = frame // 1000)
        scene_camera.json            {im_id: {cam_K, depth_scale, cam_R_w2c, cam_t_w2c (mm)}}
        scene_gt.json                {im_id: [{obj_id, cam_R_m2c, cam_t_m2c (mm)}, ...]}
        scene_gt_info.json           {im_id: [{bbox_obj, bbox_visib, px_count_all, px_count_valid,
                                               px_count_visib, visib_fract}, ...]}
        depth/IIIIII.png             uint16, depth (mm) = value * depth_scale; 0 = invalid
        mask_visib/IIIIII_GGGGGG.png uint8 0/255: the visible pixels of GT entry GGGGGG
      ddsgen/                        the ddsgen-layout render (manifest.jsonl, EXR, IR, instance masks)

``im_id`` is the frame number; entry ``g`` of ``scene_gt[im_id]`` is the object with
instance id ``g + 1`` in ddsgen's mask. ``bbox_visib`` is ``[-1, -1, -1, -1]`` for an
object with no visible pixel (BOP's convention); ``bbox_obj`` is the box of the model's
projected vertices (not clipped to the image); ``px_count_all`` = visible pixels /
visible fraction (0 when nothing is visible). The full (unoccluded) ``mask/`` images and
RGB are not written: ddsgen simulates depth sensors.

Writing is idempotent and resumable: per-frame images that exist are kept (each is
written atomically), the JSON files are rewritten atomically from the whole manifest.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np

from ddsgen.atomic import atomic_path, atomic_write_bytes, atomic_write_text
from ddsgen.errors import InputError
from ddsgen.io.manifest import RUN_FILE, read_manifest
from ddsgen.io.png import read_depth_png, read_png16, write_png8
from ddsgen.scene.meshes import load_mesh

SCANS_DIR = "ddsgen"
SPLIT = "train_pbr"
FRAMES_PER_SCENE = 1000


def scans_folder(root: str | Path) -> Path:
    """Where the ddsgen-layout render of a BOP output lives."""
    return Path(root) / SCANS_DIR


def check_bop_root(root: str | Path) -> None:
    """``root`` must be new, empty, or an earlier ``--format bop`` render (to resume it)."""
    root = Path(root)
    if not root.exists():
        return
    if not root.is_dir():
        raise InputError(f"{root}: exists and is not a folder; use a new --out folder")
    if any(root.iterdir()) and not (scans_folder(root) / RUN_FILE).is_file():
        raise InputError(f"{root}: folder exists and is not a ddsgen BOP render; use a new --out folder")


# ---------------------------------------------------------------- JSON in BOP's style


def bop_json(content: dict) -> str:
    """BOP toolkit's ``save_json`` layout: one line per top-level key (sorted numerically), values compact."""
    items = sorted(content.items(), key=lambda kv: (int(kv[0]) if str(kv[0]).isdigit() else kv[0]))
    lines = [f'  "{key}": {json.dumps(value, sort_keys=True)}' for key, value in items]
    return "{\n" + ",\n".join(lines) + "\n}\n"


# ---------------------------------------------------------------- models


def ply_bytes(vertices_mm: np.ndarray, faces: np.ndarray, normals: np.ndarray) -> bytes:
    """Binary little-endian PLY (x y z nx ny nz float, ``list uchar int vertex_indices``) that BOP's load_ply reads."""
    header = (
        "ply\nformat binary_little_endian 1.0\ncomment made by ddsgen (millimetres)\n"
        f"element vertex {len(vertices_mm)}\n"
        "property float x\nproperty float y\nproperty float z\n"
        "property float nx\nproperty float ny\nproperty float nz\n"
        f"element face {len(faces)}\nproperty list uchar int vertex_indices\nend_header\n"
    )
    vertex = np.empty(len(vertices_mm), dtype=[("p", "<f4", 3), ("n", "<f4", 3)])
    vertex["p"], vertex["n"] = vertices_mm, normals
    face = np.empty(len(faces), dtype=[("k", "u1"), ("i", "<i4", 3)])
    face["k"], face["i"] = 3, faces
    return header.encode("ascii") + vertex.tobytes() + face.tobytes()


def _model_info(vertices_mm: np.ndarray) -> dict:
    low, high = vertices_mm.min(axis=0), vertices_mm.max(axis=0)
    points = vertices_mm
    if len(points) > 3:
        try:
            from scipy.spatial import ConvexHull

            points = points[ConvexHull(points).vertices]
        except Exception:  # noqa: BLE001 - flat or degenerate model: use every vertex
            pass
    if len(points) > 4000:
        points = points[:: len(points) // 4000 + 1]
    diffs = points[:, None, :] - points[None, :, :]
    diameter = float(np.sqrt((diffs**2).sum(-1)).max()) if len(points) > 1 else 0.0
    size = high - low
    return {
        "diameter": round(diameter, 6),
        "min_x": round(float(low[0]), 6), "min_y": round(float(low[1]), 6), "min_z": round(float(low[2]), 6),
        "size_x": round(float(size[0]), 6), "size_y": round(float(size[1]), 6), "size_z": round(float(size[2]), 6),
    }  # fmt: skip


def _load_model_mm(mesh_ref: str, mesh_scale: float, scans: Path):
    """(vertices mm, faces, vertex normals) of a manifest mesh reference."""
    ref = mesh_ref
    if not ref.startswith("shape:") and not Path(ref).is_absolute():
        ref = str(scans / ref)
    mesh = load_mesh(ref, mesh_scale)  # metres
    vertices = np.asarray(mesh.vertices, dtype=np.float64) * 1000.0
    return vertices, np.asarray(mesh.faces, dtype=np.int64), np.asarray(mesh.vertex_normals, dtype=np.float64)


def _identity(obj: dict) -> tuple[str, float, str]:
    return (obj["mesh"], float(obj.get("mesh_scale", 1.0)), obj["class"])


def model_ids(records: list[dict]) -> dict[tuple[str, float, str], int]:
    """obj_id of every distinct (mesh, mesh_scale, class) in the manifest: the objects' own ``obj_id`` (what
    ``render`` records from the scene list's class table); a manifest without them (an older render) numbers
    them 1, 2, ... in sorted order."""
    keys = sorted({_identity(o) for r in records for o in r["objects"]})
    recorded = {_identity(o): int(o["obj_id"]) for r in records for o in r["objects"] if "obj_id" in o}
    if recorded and set(recorded) == set(keys):
        return recorded
    return {key: i + 1 for i, key in enumerate(keys)}


# ---------------------------------------------------------------- per frame


def _bbox(xs: np.ndarray, ys: np.ndarray) -> list[int]:
    if xs.size == 0:
        return [-1, -1, -1, -1]
    x0, y0, x1, y1 = int(np.floor(xs.min())), int(np.floor(ys.min())), int(np.floor(xs.max())), int(np.floor(ys.max()))
    return [x0, y0, x1 - x0 + 1, y1 - y0 + 1]


def _projected_bbox(vertices_mm: np.ndarray, cam_T_obj: np.ndarray, intr: dict) -> list[int]:
    points = vertices_mm / 1000.0 @ cam_T_obj[:3, :3].T + cam_T_obj[:3, 3]
    points = points[points[:, 2] > 1e-6]
    if not len(points):
        return [-1, -1, -1, -1]
    xs = intr["fx"] * points[:, 0] / points[:, 2] + intr["cx"]
    ys = intr["fy"] * points[:, 1] / points[:, 2] + intr["cy"]
    return _bbox(xs, ys)


def _copy_atomic(source: Path, target: Path) -> None:
    with atomic_path(target) as tmp:
        shutil.copyfile(source, tmp)


def write_bop_dataset(scans: str | Path, root: str | Path) -> Path:
    """Write (or complete) the BOP layout at ``root`` from the ddsgen render in ``scans``. Returns the split folder."""
    scans, root = Path(scans), Path(root)
    records = read_manifest(scans / "manifest.jsonl")
    split = root / SPLIT
    split.mkdir(parents=True, exist_ok=True)
    if not records:
        return split

    # models
    ids = model_ids(records)
    models_dir = root / "models"
    models_dir.mkdir(parents=True, exist_ok=True)
    vertices_of: dict[int, np.ndarray] = {}
    info, names = {}, {}
    for (mesh_ref, scale, class_name), obj_id in ids.items():
        vertices, faces, normals = _load_model_mm(mesh_ref, scale, scans)
        vertices_of[obj_id] = vertices
        path = models_dir / f"obj_{obj_id:06d}.ply"
        if not path.is_file():
            atomic_write_bytes(path, ply_bytes(vertices, faces, normals))
        info[str(obj_id)] = _model_info(vertices)
        names[str(obj_id)] = {"class": class_name, "mesh": mesh_ref, "mesh_scale": scale}
    atomic_write_text(models_dir / "models_info.json", bop_json(info))
    atomic_write_text(models_dir / "models_names.json", bop_json(names))

    intr0 = records[0]["intrinsics"]
    depth_scale_mm = float(records[0]["depth_scale"]) * 1000.0  # mm per PNG unit
    camera = {"cx": intr0["cx"], "cy": intr0["cy"], "depth_scale": depth_scale_mm, "fx": intr0["fx"],
              "fy": intr0["fy"], "height": intr0["height"], "width": intr0["width"]}  # fmt: skip
    atomic_write_text(root / "camera.json", json.dumps(camera, sort_keys=True, indent=2) + "\n")

    scenes: dict[int, list[dict]] = {}
    for record in records:
        scenes.setdefault(int(record["frame"]) // FRAMES_PER_SCENE, []).append(record)
    for scene_id, scene_records in sorted(scenes.items()):
        scene = split / f"{scene_id:06d}"
        (scene / "depth").mkdir(parents=True, exist_ok=True)
        (scene / "mask_visib").mkdir(parents=True, exist_ok=True)
        scene_camera, scene_gt, scene_gt_info = {}, {}, {}
        for record in scene_records:
            im_id = int(record["frame"])
            intr = record["intrinsics"]
            cam_T_world = np.linalg.inv(np.asarray(record["world_T_cam"], dtype=np.float64))
            scene_camera[str(im_id)] = {
                "cam_K": [intr["fx"], 0.0, intr["cx"], 0.0, intr["fy"], intr["cy"], 0.0, 0.0, 1.0],
                "depth_scale": float(record["depth_scale"]) * 1000.0,
                "cam_R_w2c": cam_T_world[:3, :3].ravel().tolist(),
                "cam_t_w2c": (cam_T_world[:3, 3] * 1000.0).tolist(),
            }
            depth_target = scene / "depth" / f"{im_id:06d}.png"
            if not depth_target.is_file():
                _copy_atomic(scans / record["depth"], depth_target)  # same encoding: uint16, depth_scale
            shape = (intr["height"], intr["width"])
            instance = read_png16(scans / record["mask"], expected_shape=shape)
            valid = read_depth_png(scans / record["depth"], float(record["depth_scale"])) > 0
            gts, gt_infos = [], []
            for gt_id, obj in enumerate(sorted(record["objects"], key=lambda o: o["id"])):
                obj_id = ids[_identity(obj)]
                cam_T_obj = np.asarray(obj["cam_T_obj"], dtype=np.float64)
                gts.append({
                    "obj_id": obj_id,
                    "cam_R_m2c": cam_T_obj[:3, :3].ravel().tolist(),
                    "cam_t_m2c": (cam_T_obj[:3, 3] * 1000.0).tolist(),
                })  # fmt: skip
                visible = instance == int(obj["id"])
                count = int(visible.sum())
                fraction = float(obj.get("visible_fraction", 1.0 if count else 0.0))
                ys, xs = np.nonzero(visible)
                gt_infos.append({
                    "bbox_obj": _projected_bbox(vertices_of[obj_id], cam_T_obj, intr),
                    "bbox_visib": _bbox(xs, ys),
                    "px_count_all": int(round(count / fraction)) if count and fraction > 0 else 0,
                    "px_count_valid": int((visible & valid).sum()),
                    "px_count_visib": count,
                    "visib_fract": fraction if count else 0.0,
                })  # fmt: skip
                mask_path = scene / "mask_visib" / f"{im_id:06d}_{gt_id:06d}.png"
                if not mask_path.is_file():
                    write_png8(mask_path, visible.astype(np.uint8) * 255)
            scene_gt[str(im_id)] = gts
            scene_gt_info[str(im_id)] = gt_infos
        atomic_write_text(scene / "scene_camera.json", bop_json(scene_camera))
        atomic_write_text(scene / "scene_gt.json", bop_json(scene_gt))
        atomic_write_text(scene / "scene_gt_info.json", bop_json(scene_gt_info))
    return split
