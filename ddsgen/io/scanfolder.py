"""Read a folder of (real or simulated) depth scans: ddsgen's own layout or the BOP layout.

:func:`read_scan_folder` auto-detects the layout:

* **ddsgen** (README.md "Outputs"): ``DIR/manifest.jsonl`` (validated non-strictly, so
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

import json
from pathlib import Path

import numpy as np

from ddsgen.errors import InputError
from ddsgen.io.bop_reader import bop_scene_folders, read_bop_scene
from ddsgen.io.manifest import BUILT_IN_SCENES, RUN_FILE, file_digest, read_manifest
from ddsgen.io.scan_frame import RenderedScene, ScanFrame, ScanObject, check_size, is_positive_number
from ddsgen.preset import Intrinsics

def rendered_scene(folder: Path) -> RenderedScene | None:
    """The :class:`RenderedScene` of a ddsgen render folder (None without a readable run.json)."""
    try:
        run = json.loads((folder / RUN_FILE).read_text())
        scenes, digest, seed = run["scenes"], run["scenes_sha"], int(run["seed"])
    except (OSError, ValueError, KeyError, TypeError):
        return None
    if scenes == BUILT_IN_SCENES:
        return RenderedScene(None, seed)
    path = Path(scenes)
    if not path.is_file():
        return RenderedScene(scenes, seed, missing=f"the scene list it was rendered from is gone ({scenes})")
    if file_digest(path) != digest:
        return RenderedScene(scenes, seed, missing=f"the scene list it was rendered from has changed ({scenes})")
    return RenderedScene(scenes, seed)


def _read_ddsgen(folder: Path) -> list[ScanFrame]:
    manifest = folder / "manifest.jsonl"
    rendered = rendered_scene(folder)
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
        check_size(depth_path, intrinsics, f"{manifest} (frame {record['frame']})")
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
                rendered=rendered,
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

        frames = [frame for scene in bop_scene_folders(folder) for frame in read_bop_scene(scene)]
    if eager:
        for frame in frames:
            _ = frame.depth
    return frames
