"""The inputs of every real-scan command (compare, fit, diagnose): a preset with the scans' camera, and the
real frames prepared for simulation. Below the commands, so that no command module imports another.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from ddsgen.errors import InputError
from ddsgen.io.scanfolder import read_scan_folder
from ddsgen.preset import load_preset
from ddsgen.realscan.plane_depth import plane_depth_for
from ddsgen.realscan.simulate import prepare_frames
from ddsgen.sensor.depth_sensor import DepthSensor
from ddsgen.sensor.output_window import OutputWindow, measure_device_window


def adopt_camera(preset, scan_frames):
    """The preset with the scans' camera when they differ (image size, focal length, principal point).

    The simulation must see the real images' pixels, and the sensor sizes its disparity search
    from the preset's focal length. Frames must share one image size.
    """
    sizes = {(f.intrinsics.width, f.intrinsics.height) for f in scan_frames}
    if len(sizes) > 1:
        raise InputError(f"{scan_frames[0].source_depth_path}: frames have different image sizes {sorted(sizes)}; "
                         f"compare/fit them separately")  # fmt: skip
    c = scan_frames[0].intrinsics
    p = preset
    same = ((c.width, c.height) == (p.width_px, p.height_px) and abs(c.fx - p.focal_px) <= 0.01 * p.focal_px
            and abs(c.fy - p.focal_y_px) <= 0.01 * p.focal_y_px)  # fmt: skip
    if same:
        return preset, False
    try:
        # The registration's principal-point shift is an angle: in this camera's pixels it scales with fx.
        return preset.replace(width_px=c.width, height_px=c.height, focal_px=c.fx, focal_y_px=c.fy, cx_px=c.cx, cy_px=c.cy,
                              registration_shift_px=p.registration_shift_px * c.fx / p.focal_px), True  # fmt: skip
    except InputError as error:
        raise InputError(f"{scan_frames[0].source_depth_path}: the scans' camera does not fit the preset: {error}") from None


def load_inputs(preset_path, real_dir, *, support_plane=True, crop=False, plausible_px=2.0, seed=0, progress=True,
                echo: Callable[[str], None] | None = None, window_hint: bool = True):
    """(original preset, preset with the scans' camera, scan frames, prepared FrameData list).

    The support plane of each frame is fitted to the real depth with the preset's disparity effects undone
    (:mod:`ddsgen.realscan.plane_depth`), so a preset that models its device's disparity errors is compared on
    the table where that device saw it.

    ``echo`` (e.g. ``click.echo`` to stderr) is told when the scans' camera replaces the preset's, and (if
    ``window_hint``) when the real frames' output window differs from the preset's.
    """
    preset = load_preset(preset_path)
    scans = read_scan_folder(real_dir)
    if not scans:
        raise InputError(f"{real_dir}: no frames")
    camera_preset, adopted = adopt_camera(preset, scans)
    if adopted and progress and echo is not None:
        c = scans[0].intrinsics
        echo(f"using the scans' camera ({c.width}x{c.height} px, fx {c.fx:.2f} px) instead of the preset's")
    # The support plane where the preset's own disparity errors put it (ddsgen.realscan.plane_depth).
    plane_depth = plane_depth_for(DepthSensor(camera_preset)) if support_plane else None
    frames = prepare_frames(camera_preset, scans, support_plane=support_plane, crop=crop, plausible_px=plausible_px,
                            seed=seed, progress=progress, plane_depth=plane_depth)  # fmt: skip
    hint = output_window_hint(camera_preset, scans) if window_hint else None
    if hint and progress and echo is not None:
        echo(hint)
    return preset, camera_preset, scans, frames


def differing_output_window(preset, depth_maps, tolerance_px: int = 2):
    """The output window measured on real frames (border bands empty in every frame,
    :func:`~ddsgen.sensor.output_window.measure_device_window`: for a registered preset in its IR frame) when it
    differs from the preset's by more than ``tolerance_px`` on a side, else None. Needs two maps of one size
    (one frame's empty border may be the scene's).

    Args:
        preset: the preset at the frames' image size.
        depth_maps: (H, W) depth of the real frames (m, 0 = invalid), uncropped.
    """
    maps = [np.asarray(d) for d in depth_maps]
    if len(maps) < 2 or len({m.shape for m in maps}) != 1:
        return None
    measured = measure_device_window(maps, preset)
    return measured if measured.largest_difference(OutputWindow.of(preset)) > tolerance_px else None


def output_window_hint(preset, scans, tolerance_px: int = 2) -> str | None:
    """One line for the user when the real frames' output window differs from the preset's
    (:func:`differing_output_window`), else None."""
    measured = differing_output_window(preset, [scan.depth for scan in scans], tolerance_px)
    if measured is None:
        return None
    declared = OutputWindow.of(preset).as_keys()
    keys = ", ".join(f"{key}: {px}" for key, px in measured.as_keys().items() if abs(px - declared[key]) > tolerance_px)
    return (f"the real frames have no depth in other border bands than the preset declares ({keys} measured, "
            f"in px of these frames): set them in the preset, or run fit --unpaired or diagnose, which measure them")
