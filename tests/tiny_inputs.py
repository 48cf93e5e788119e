"""Tiny inputs shared by the CLI-level tests: a low-resolution Kinect-V1-like preset and a small scene list.

The sensor keeps kinect_v1's field of view (focal length 572.41 px scaled by width / 640), its baseline, range and
block size, so a few frames render in a second or two. The scene list has upright shapes in front of a back wall.
"""

from __future__ import annotations

import hashlib
import os
from contextlib import contextmanager
from pathlib import Path

#: kinect_v1's focal length at 640 px wide.
KINECT_FOCAL_PX_AT_640 = 572.41


def tiny_preset_yaml(width: int, height: int, name: str = "tiny") -> str:
    """A preset of ``width`` x ``height`` px with kinect_v1's field of view, 1/4 px sub-pixel steps, its depth
    registered to an RGB camera as kinect_v1's (a second ray cast per frame, the gather and the splat)."""
    focal = KINECT_FOCAL_PX_AT_640 * width / 640
    shift = 17.4 * width / 640
    return f"""\
name: {name}
width_px: {width}
height_px: {height}
focal_px: {focal:.4f}          # kinect_v1's 572.41 px x {width}/640
baseline_m: 0.075
z_min_m: 0.4
z_max_m: 4.0
block_size_px: 9
emitted_intensity: 1.5e6
shadow_bias_m: 0.005
softargmax_beta: 15.0
subpixel_level: 2
registration_ir_offset_m: 0.027
registration_shift_px: {shift:.4f}
registration_dense: true
"""


def tiny_scenes_yaml(frames: int, clutter: tuple[int, int]) -> str:
    """One scene of three upright shapes, ``clutter`` (min, max) clutter objects and a back wall."""
    return f"""\
scenes:
  - name: tiny
    frames: {frames}
    objects:
      - {{shape: box, size: [0.12, 0.08, 0.06], rest: upright}}
      - {{shape: cylinder, rest: upright}}
      - {{shape: sphere, rest: upright}}
    clutter: {{count: [{clutter[0]}, {clutter[1]}], area: [0.3, 0.3]}}
    wall: {{distance: 0.5}}
    camera: {{distance: [0.7, 1.0], elevation_deg: [30, 50], azimuth_deg: [-40, 40]}}
"""


@contextmanager
def written_inputs(folder: Path, preset_yaml: str, scenes_yaml: str):
    """Write the preset and scene list into ``folder``; yield their paths with torch.compile off.

    DDSGEN_NO_COMPILE=1 (in this process and its children): compiling costs seconds per process and is not what
    these tests are about. The variable is restored on exit.
    """
    old = os.environ.get("DDSGEN_NO_COMPILE")
    os.environ["DDSGEN_NO_COMPILE"] = "1"
    (folder / "tiny.yaml").write_text(preset_yaml)
    (folder / "tiny_scenes.yaml").write_text(scenes_yaml)
    try:
        yield str(folder / "tiny.yaml"), str(folder / "tiny_scenes.yaml")
    finally:
        if old is None:
            os.environ.pop("DDSGEN_NO_COMPILE", None)
        else:
            os.environ["DDSGEN_NO_COMPILE"] = old


def tree_hashes(folder: Path) -> dict[str, str]:
    """sha256 of every file under ``folder`` by relative path (temporaries included: there must be none)."""
    return {
        str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(folder.rglob("*"))
        if p.is_file()
    }
