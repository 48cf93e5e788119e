"""``compare --save-sim DIR``: the simulated version of every compared real frame, as a ddsgen scan folder.

Frame ``i`` of DIR is the simulation of the ``i``-th frame of the real folder (its order), written
with the files and names ``render`` uses (:mod:`ddsgen.io.framefiles`: depth PNG in mm + EXR,
clean EXR, IR PNG, instance mask) and a manifest record holding the real frame's camera, objects
and poses, its name (``source``) and the fitted support plane. A ``--crop`` simulation is pasted
into its full frame (no depth outside the crop). The folder is built under a hidden temporary
name next to DIR and renamed to DIR once complete, so DIR is either absent or whole; it reads
back with :func:`ddsgen.io.scanfolder.read_scan_folder`.
"""

from __future__ import annotations

import contextlib
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from ddsgen.atomic import atomic_folder, check_new_folder
from ddsgen.errors import InputError
from ddsgen.io.framefiles import DEPTH_SCALE, write_frame_files
from ddsgen.io.manifest import append_record
from ddsgen.preset import SensorPreset, save_preset
from ddsgen.raycast import object_labels
from ddsgen.realscan.realism import full_frame
from ddsgen.realscan.simulate import frame_scene

MANIFEST = "manifest.jsonl"


def check_target(out: str | Path, inputs: tuple[str | Path, ...] = ()) -> Path:
    """DIR must not exist yet (or be an empty folder), nor be one of ``inputs`` (the real folder): call before any
    work. Returns it as a Path."""
    return check_new_folder(out, "--save-sim", inputs)


class SimFolderWriter:
    """Collects simulated frames into a scan folder; use as a context manager.

    ``with SimFolderWriter(out, preset, seed) as writer: writer.add(frame, sim, scan)`` -- the frames go to a
    hidden temporary folder (:func:`ddsgen.atomic.atomic_folder`) that a clean exit renames to ``out``; an
    exception (Ctrl-C included) removes it, so an unfinished command leaves no ``out`` and can be re-run.
    """

    def __init__(self, out: str | Path, preset: SensorPreset, seed: int):
        self.out = check_target(out)
        self.preset = preset
        self.seed = int(seed)
        self.count = 0
        self.tmp: Path | None = None
        self._stack = contextlib.ExitStack()

    def __enter__(self) -> SimFolderWriter:
        self.tmp = self._stack.enter_context(atomic_folder(self.out, "--save-sim", merge=False))
        try:
            save_preset(self.preset, self.tmp / "sensor.yaml", comment=f"resolved from {self.preset.source}; "
                        "the camera is the real scans'")  # fmt: skip
        except BaseException as error:
            self._stack.__exit__(type(error), error, error.__traceback__)  # removes the folder: nothing is left
            if isinstance(error, OSError):
                raise InputError(f"{self.out}: --save-sim: cannot write ({error.strerror or error})") from None
            raise
        return self

    def __exit__(self, kind, error, trace) -> bool:
        return self._stack.__exit__(kind, error, trace)

    def add(self, frame, sim, scan) -> dict:
        """Write the simulation ``sim`` (SensorOutput) of ``frame`` (FrameData) of the real ``scan`` (ScanFrame)."""
        index = self.count
        intrinsics = frame.full_intrinsics or frame.intrinsics
        depth = full_frame(sim.depth.detach().numpy(), frame, 0.0).astype(np.float32)
        instance = full_frame(frame.instance.numpy(), frame, 0)
        files = write_frame_files(self.tmp, index, depth, full_frame(frame.clean_depth.numpy(), frame, 0.0),
                                  full_frame(sim.ir.detach().numpy(), frame, 0.0), 2.0**self.preset.ir_bits - 1.0,
                                  instance)  # fmt: skip
        # bbox and visible_fraction as render labels them (the support plane is background, id 0).
        objects = object_labels(frame_scene(scan), SimpleNamespace(instance=instance, coverage=None), intrinsics)
        for label, obj in zip(objects, sorted(scan.objects, key=lambda o: o.id)):
            label["mesh"] = obj.mesh_path  # absolute path or "shape:NAME", as the real folder gives it
        record = {
            "frame": index,
            **files,
            "intrinsics": intrinsics.as_dict(),
            "depth_scale": DEPTH_SCALE,
            # the simulation's scene is the camera frame; keep the real camera's world pose when known
            "world_T_cam": np.eye(4) if scan.world_T_cam is None else scan.world_T_cam,
            "objects": objects,
            "seed": self.seed,
            "source": scan.name,
            "source_depth": str(Path(scan.source_depth_path).resolve()),
            "crop": list(frame.crop),
            "support_plane": None if frame.plane is None else frame.plane.as_dict(),
            "valid_fraction": round(float((depth > 0).mean()), 6),
        }
        append_record(self.tmp / MANIFEST, record)
        self.count += 1
        return record
