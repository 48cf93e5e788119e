"""Training data for PyTorch: a rendered (or BOP) folder, or frames rendered on the fly, as tensors.

* :class:`ScanFolderDataset` -- a ``torch.utils.data.Dataset`` over a folder ``ddsgen render`` wrote (or any folder
  :func:`ddsgen.io.scanfolder.read_scan_folder` reads: ddsgen's layout or BOP's, e.g. ``render --format bop`` or a
  published BOP dataset).
* :class:`RenderedFrames` -- a ``torch.utils.data.IterableDataset`` that renders frames inside the DataLoader's
  workers (each worker takes every k-th frame). Frame ``i`` of seed ``s`` gives exactly the tensors that
  :class:`ScanFolderDataset` reads from frame ``i`` of ``ddsgen render --seed s``: the same simulation, and the IR
  image passed through the same 8-bit encoding the IR PNG stores.
* :func:`collate_frames` -- the ``collate_fn`` for both: frames hold different numbers of objects.

One frame is a dict of tensors (H, W = image size, N = objects in the frame)::

    depth        float32 (H, W)   simulated depth (m), 0 = invalid (the depth EXR; the 16-bit PNG when there is none)
    valid        bool    (H, W)   depth > 0
    clean        float32 (H, W)   noise-free depth (m), 0 = no surface          (ddsgen layout only)
    ir           float32 (H, W)   IR image (detector counts, decoded from the 8-bit PNG)   (ddsgen layout only)
    instance     int64   (H, W)   instance id of each pixel, 0 = background (BOP: from mask_visib/, all 0 without)
    instance_ids int64   (N,)     each object's value in ``instance`` (ids ascending)
    obj_ids      int64   (N,)     stable object ids (classes.json / BOP obj_id; 0 = not recorded)
    class_ids    int64   (N,)     class ids (classes.json's class_id; BOP: the obj_id; 0 = not recorded)
    rotations    float32 (N, 3, 3) object -> camera rotation (OpenCV camera axes)
    translations float32 (N, 3)   object origin in the camera frame (m)
    boxes        int64   (N, 4)   [x, y, w, h] (px) of the object's visible pixels in ``instance``, 0s if none
    visible_fraction float32 (N,) visible share of the object's silhouette (NaN when not recorded)
    intrinsics   float32 (3, 3)   K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] (px)
    frame        int64   ()       frame number (BOP: image id)

:func:`collate_frames` stacks the per-pixel tensors and ``intrinsics`` to (B, ...), pads the per-object tensors to
the batch's largest N (``instance_ids``/``obj_ids``/``class_ids`` 0, poses identity, boxes 0) and adds
``object_valid`` bool (B, N_max) saying which entries are real.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from torch.utils.data import Dataset, IterableDataset, get_worker_info

from ddsgen.io.class_table import read_class_table
from ddsgen.io.exr import read_exr
from ddsgen.io.ir_png import GAMMA as IR_GAMMA
from ddsgen.io.ir_png import decode_ir, encode_ir, ir_white_counts, read_ir_counts
from ddsgen.io.png import read_png8, read_png16
from ddsgen.io.scanfolder import ScanFrame, read_scan_folder
from ddsgen.preset import load_preset
from ddsgen.runner import RenderJob, apply_camera, one_thread, parse_camera, simulate_frame
from ddsgen.scene.scenelist import load_scene_list, models_folder

#: Keys :func:`collate_frames` pads (one entry per object) and the value padding gets.
OBJECT_KEYS = ("instance_ids", "obj_ids", "class_ids", "rotations", "translations", "boxes", "visible_fraction")


# ---------------------------------------------------------------- one frame -> tensors


def visible_boxes(instance: np.ndarray, ids) -> np.ndarray:
    """int64 (N, 4) [x, y, w, h] of the pixels of each id in ``instance`` (H, W); [0, 0, 0, 0] for an absent id."""
    boxes = np.zeros((len(ids), 4), dtype=np.int64)
    for k, value in enumerate(ids):
        ys, xs = np.nonzero(instance == value)
        if xs.size:
            boxes[k] = [xs.min(), ys.min(), xs.max() - xs.min() + 1, ys.max() - ys.min() + 1]
    return boxes


def frame_tensors(frame: int, intrinsics: dict, objects: list[dict], depth: np.ndarray, instance: np.ndarray,
                  clean: np.ndarray | None = None, ir: np.ndarray | None = None) -> dict:  # fmt: skip
    """The tensors of one frame (see the module docstring) from its arrays and its manifest-style record parts.

    Args:
        intrinsics: ``{fx, fy, cx, cy, ...}`` (px). objects: manifest objects (``id``, ``cam_T_obj``, optional
        ``obj_id``, ``class_id``, ``visible_fraction``). depth, clean: float32 (H, W) m. instance: (H, W) ints.
        ir: float32 (H, W) counts.
    """
    objects = sorted(objects, key=lambda o: int(o["id"]))
    instance = np.asarray(instance).astype(np.int64)
    poses = np.array([o["cam_T_obj"] for o in objects], dtype=np.float64).reshape(-1, 4, 4)
    ids = [int(o["id"]) for o in objects]
    out = {
        "depth": torch.from_numpy(np.asarray(depth, dtype=np.float32)),
        "valid": torch.from_numpy(np.asarray(depth) > 0),
        "instance": torch.from_numpy(instance),
        "instance_ids": torch.tensor(ids, dtype=torch.int64),
        "obj_ids": torch.tensor([int(o.get("obj_id") or 0) for o in objects], dtype=torch.int64),
        "class_ids": torch.tensor([int(o.get("class_id") or 0) for o in objects], dtype=torch.int64),
        "rotations": torch.from_numpy(poses[:, :3, :3].astype(np.float32)),
        "translations": torch.from_numpy(poses[:, :3, 3].astype(np.float32)),
        "boxes": torch.from_numpy(visible_boxes(instance, ids)),
        "visible_fraction": torch.tensor([float("nan") if o.get("visible_fraction") is None
                                          else float(o["visible_fraction"]) for o in objects], dtype=torch.float32),
        "intrinsics": torch.tensor([[intrinsics["fx"], 0.0, intrinsics["cx"]], [0.0, intrinsics["fy"], intrinsics["cy"]],
                                    [0.0, 0.0, 1.0]], dtype=torch.float32),
        "frame": torch.tensor(int(frame), dtype=torch.int64),
    }  # fmt: skip
    if clean is not None:
        out["clean"] = torch.from_numpy(np.asarray(clean, dtype=np.float32))
    if ir is not None:
        out["ir"] = torch.from_numpy(np.asarray(ir, dtype=np.float32))
    return out


def collate_frames(batch: list[dict]) -> dict:
    """``collate_fn`` for frames with different numbers of objects: stack images, pad objects (module docstring)."""
    out = {key: torch.stack([item[key] for item in batch]) for key in batch[0] if key not in OBJECT_KEYS}
    counts = [len(item["instance_ids"]) for item in batch]
    most = max(counts)
    out["object_valid"] = torch.tensor([[k < n for k in range(most)] for n in counts], dtype=torch.bool)
    for key in OBJECT_KEYS:
        first = batch[0][key]
        padded = torch.zeros((len(batch), most, *first.shape[1:]), dtype=first.dtype)
        if key == "rotations":
            padded[:] = torch.eye(3)
        if key == "visible_fraction":
            padded[:] = float("nan")
        for row, item in enumerate(batch):
            padded[row, : counts[row]] = item[key]
        out[key] = padded
    return out


# ---------------------------------------------------------------- a folder on disk


def _bop_instance(frame: ScanFrame) -> np.ndarray:
    """The instance image of a BOP frame from its ``mask_visib/IIIIII_GGGGGG.png`` files (all 0 without them)."""
    shape = (frame.intrinsics.height, frame.intrinsics.width)
    instance = np.zeros(shape, dtype=np.int64)
    masks = Path(frame.source_depth_path).parent.parent / "mask_visib"
    for obj in frame.objects:
        path = masks / f"{frame.frame:06d}_{obj.id - 1:06d}.png"
        if path.is_file():
            instance[(read_png8(path, shape) > 0) & (instance == 0)] = obj.id
    return instance


class ScanFolderDataset(Dataset):
    """The frames of a scan folder (ddsgen or BOP layout) as tensor dicts (see the module docstring).

    Args:
        folder: a ``ddsgen render`` output (``manifest.jsonl``), a ``render --format bop`` root, or a BOP dataset,
            split or scene folder. Read with :func:`ddsgen.io.scanfolder.read_scan_folder` (errors are
            :class:`ddsgen.errors.InputError` naming the file).

    Attributes:
        classes: the rows of the folder's ``classes.json`` (``id`` = obj_id, ``class``, ``class_id``, ``mesh``,
            ``mesh_scale``; a ``--format bop`` root's are in its ``ddsgen/`` folder), or None without one.
    """

    def __init__(self, folder: str | Path):
        self.frames = read_scan_folder(folder)
        folder = Path(folder)
        self.classes = read_class_table(folder) or read_class_table(folder / "ddsgen")

    def __len__(self) -> int:
        return len(self.frames)

    def __getitem__(self, index: int) -> dict:
        frame = self.frames[index]
        shape = (frame.intrinsics.height, frame.intrinsics.width)
        intrinsics = {"fx": frame.intrinsics.fx, "fy": frame.intrinsics.fy, "cx": frame.intrinsics.cx,
                      "cy": frame.intrinsics.cy}  # fmt: skip
        if frame.layout == "bop":
            objects = [{"id": o.id, "cam_T_obj": o.cam_T_obj, "obj_id": o.obj_id, "class_id": o.obj_id,
                        "visible_fraction": o.visible_fraction} for o in frame.objects]  # fmt: skip
            return frame_tensors(frame.frame, intrinsics, objects, frame.load_depth(), _bop_instance(frame))
        record = frame.record
        folder = Path(frame.source_depth_path).parent.parent
        depth = read_exr(folder / record["depth_exr"]) if "depth_exr" in record else frame.load_depth()
        instance = read_png16(folder / record["mask"], shape, "mask") if "mask" in record else np.zeros(shape)
        clean = read_exr(folder / record["clean"]) if "clean" in record else None
        ir = None
        if "ir" in record and "ir_white_counts" in record:
            ir = read_ir_counts(folder / record["ir"], float(record["ir_white_counts"]),
                                float(record.get("ir_gamma", IR_GAMMA)), shape)  # fmt: skip
        return frame_tensors(frame.frame, record["intrinsics"], record["objects"], depth, instance, clean, ir)


# ---------------------------------------------------------------- frames rendered on the fly


class RenderedFrames(IterableDataset):
    """Frames ``frames`` of the dataset (preset, scene list, seed) rendered as they are asked for.

    Each DataLoader worker renders every ``num_workers``-th frame of ``frames`` (worker w: positions w, w + k, ...),
    with one torch thread as ``ddsgen render`` does, so the tensors do not depend on the number of workers. In the
    main process (``num_workers=0``) rendering also runs with one torch thread; the thread count is restored after.

    Args:
        preset: sensor preset file or shipped name (as ``ddsgen render PRESET``).
        frames: how many frames (0..n-1) or which frame numbers.
        scenes: scene list YAML, or None for the built-in default.
        seed: dataset seed (frame i depends only on (seed, i)).
        camera: ``"fx,fy,cx,cy"`` or a 4-tuple (px) overriding the preset's intrinsics (``render --camera``).
        models_dir: folder where mesh files not found at their scene-list path are looked up (``render --models``).
    """

    def __init__(self, preset: str | Path, frames, scenes: str | Path | None = None, seed: int = 0,
                 camera=None, models_dir: str | Path | None = None):  # fmt: skip
        super().__init__()
        self.frames = list(range(frames)) if isinstance(frames, int) else [int(f) for f in frames]
        camera = parse_camera(camera) if isinstance(camera, str) else camera
        resolved = apply_camera(load_preset(preset), camera)  # bad input fails here, not in a worker
        models = models_folder(models_dir)
        load_scene_list(scenes, models)
        self.job = RenderJob(str(Path(resolved.source).resolve()), str(Path(scenes).resolve()) if scenes else None,
                             "", int(seed), camera, str(models.resolve()) if models else None)  # fmt: skip

    def __len__(self) -> int:
        return len(self.frames)

    def render(self, frame: int) -> dict:
        """The tensors of frame ``frame`` (what :class:`ScanFolderDataset` reads from the rendered files)."""
        with one_thread():  # as every render worker; the training loop gets its threads back after
            simulated = simulate_frame(self.job, frame)
        record = simulated.record
        white = ir_white_counts(simulated.ir, simulated.ir_full_scale)  # the IR PNG's exposure and 8-bit encoding
        ir = decode_ir(encode_ir(simulated.ir, white), white)
        instance = np.asarray(simulated.instance).astype(np.uint16)  # the mask PNG's type
        return frame_tensors(frame, record["intrinsics"], record["objects"], simulated.depth, instance,
                             simulated.clean, ir)  # fmt: skip

    def __iter__(self):
        worker = get_worker_info()
        mine = self.frames if worker is None else self.frames[worker.id :: worker.num_workers]
        for frame in mine:
            yield self.render(frame)
