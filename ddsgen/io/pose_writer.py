"""Write refined object poses in the layout they were read from (``ddsgen refine``).

* BOP: ``OUT/<split>/<scene>/scene_gt.json`` -- the source file with the same keys and entries,
  ``cam_R_m2c`` (row-major, 9 numbers) and ``cam_t_m2c`` (mm) replaced for the refined frames;
  ``scene_camera.json`` is copied next to it. Images and models are not copied.
* ddsgen folders: ``OUT/manifest.jsonl`` -- the source records with each object's ``cam_T_obj``
  (metres) replaced; the depth and other file paths point back at the source files (relative to
  OUT), meshes by absolute path.

An object whose refined pose equals the pose read (within float rounding: 1e-9 m, 1e-9 per rotation entry; a
refinement that kept its start) keeps its entry exactly as read.
Every file is written atomically; nothing is written when the input is inconsistent.
"""

from __future__ import annotations

import copy
import json
import os
from pathlib import Path

import numpy as np

from ddsgen.errors import InputError
from ddsgen.atomic import atomic_write_text
from ddsgen.io.manifest import OPTIONAL_PATH_KEYS, dumps_record


def write_refined_poses(frames, refined: dict, out: str | Path, final: str | Path | None = None) -> list[Path]:
    """Write the refined poses of ``frames`` under ``out``; returns the files written (under ``final``).

    Args:
        frames: the :class:`~ddsgen.io.scan_frame.ScanFrame` list read from one folder (one layout).
        refined: frame name -> {object id (ScanObject.id) -> (4, 4) refined ``cam_T_obj`` (m)}.
            Frames or objects not in it keep their poses.
        out: output folder.
        final: where ``out`` will be once complete, when it is built under a temporary name
            (:func:`ddsgen.atomic.atomic_folder`): the manifest's paths to the source files are relative to it.
            Default: ``out``.
    """
    out = Path(out)
    final = out if final is None else Path(final)
    layouts = {f.layout for f in frames}
    if layouts == {"bop"}:
        written = _write_bop(frames, refined, out)
    elif layouts == {"ddsgen"}:
        written = [_write_manifest(frames, refined, out, final)]
    else:
        raise InputError(f"{final}: frames of layouts {sorted(layouts)}: cannot write one folder for them")
    return [final / path.relative_to(out) for path in written]


def _changed(frame, poses: dict) -> dict:
    """The entries of ``poses`` ({object id: (4, 4)}) that differ from the frame's pose of that object as read."""
    read = {o.id: o.cam_T_obj for o in frame.objects}
    return {obj_id: T for obj_id, T in poses.items()
            if obj_id not in read or not np.allclose(np.asarray(T, dtype=np.float64), read[obj_id], rtol=0.0, atol=1e-9)}


def _write_bop(frames, refined: dict, out: Path) -> list[Path]:
    scenes: dict[Path, list] = {}
    for f in frames:
        scenes.setdefault(Path(f.source_depth_path).resolve().parent.parent, []).append(f)
    contents = {}
    for scene, scene_frames in scenes.items():
        gt_path = scene / "scene_gt.json"
        try:
            gt = json.loads(gt_path.read_text())
        except (OSError, ValueError) as error:
            raise InputError(f"{gt_path}: cannot read: {error}") from None
        for f in scene_frames:
            entries = gt.get(str(f.frame))
            for obj_id, T in _changed(f, refined.get(f.name, {})).items():
                if entries is None or not 1 <= int(obj_id) <= len(entries):
                    raise InputError(f"{gt_path}: image {f.frame}: no entry {int(obj_id) - 1} to refine")
                T = np.asarray(T, dtype=np.float64)
                entry = entries[int(obj_id) - 1]
                entry["cam_R_m2c"] = [float(x) for x in T[:3, :3].reshape(-1)]
                entry["cam_t_m2c"] = [float(x) for x in T[:3, 3] * 1000.0]
        target = out / scene.parent.name / scene.name
        contents[target / "scene_gt.json"] = json.dumps(gt, indent=2) + "\n"
        camera = scene / "scene_camera.json"
        if camera.is_file():
            contents[target / "scene_camera.json"] = camera.read_text()
    for path, text in contents.items():
        path.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_text(path, text)
    return list(contents)


def _write_manifest(frames, refined: dict, out: Path, final: Path) -> Path:
    lines = []
    for f in frames:
        if f.record is None:
            raise InputError(f"{f.source_depth_path}: frame {f.name} has no manifest record to rewrite")
        record = copy.deepcopy(f.record)
        source = Path(f.source_depth_path).resolve()  # = folder / record["depth"]
        for _ in Path(record["depth"]).parts:
            source = source.parent
        for key in ("depth",) + OPTIONAL_PATH_KEYS:
            if isinstance(record.get(key), str):
                record[key] = Path(os.path.relpath(source / record[key], final.resolve())).as_posix()
        poses = _changed(f, refined.get(f.name, {}))
        for obj, scan_obj in zip(record["objects"], f.objects):
            obj["mesh"] = scan_obj.mesh_path
            if scan_obj.id in poses:
                obj["cam_T_obj"] = [[float(x) for x in row] for row in np.asarray(poses[scan_obj.id], dtype=np.float64)]
        lines.append(dumps_record(record))
    out.mkdir(parents=True, exist_ok=True)
    path = out / "manifest.jsonl"
    atomic_write_text(path, "".join(line if line.endswith("\n") else line + "\n" for line in lines))
    return path
