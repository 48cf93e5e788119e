"""The device's output window, measured on the real frames before the base fit.

A band of border columns (rows) without depth in every real frame is the device's output window
(:mod:`ddsgen.sensor.output_window`), not a physical effect: no effect of the library adds pixels,
so a preset whose window differs (the stock Kinect's 8 empty left columns against a device that
has depth there, or a registered device's right band) would leave that band in every gap and make
every effect's fall look smaller. The window is measured, like ``fit --unpaired`` does, and the
model uses it from the start; the report says so.
"""

from __future__ import annotations

from ddsgen.fit.lattice import measure_quantum
from ddsgen.realscan.inputs import differing_output_window
from ddsgen.sensor.output_window import OutputWindow


def uncropped(frame) -> bool:
    """Whether a prepared frame is the whole image (a crop's empty border says nothing about the device)."""
    full = frame.full_intrinsics
    return tuple(frame.crop) == (0, 0, full.width, full.height)


def with_measured_window(preset, frames, tolerance_px: int = 2):
    """``(preset, window, note)``: the preset with the output window measured on ``frames``' real valid maps
    when it differs from the preset's by more than ``tolerance_px`` on a side (two or more whole frames
    needed), the measured :class:`OutputWindow` and one sentence for the report; else ``(preset, None, None)``."""
    if not all(uncropped(f) for f in frames):
        return preset, None, None
    measured = differing_output_window(preset, [f.real_depth.numpy() for f in frames], tolerance_px)
    if measured is None:
        return preset, None, None
    note = (f"Output window measured on the {len(frames)} real frames (border bands without depth in every frame): "
            f"{measured.describe()}; the preset declares {OutputWindow.of(preset).describe()}. The model uses the "
            f"measured window from the base fit on (a window is the device's output format, not an effect).")
    return preset.replace(**measured.as_keys()), measured, note


def with_measured_quantum(preset, fit_frames, held_frames):
    """``(preset, note)``: the preset on the disparity quantum the real depth's levels show, measured on the fit
    frames and confirmed on the held-out ones (:func:`ddsgen.fit.lattice.measure_quantum`), with one sentence for
    the report; ``(preset, None)`` when it agrees with the preset's or is not confirmed. Like the window, the quantum
    is the device's output format, read off the data, not an effect searched for."""
    quantum = measure_quantum(fit_frames, held_frames, preset.subpixel_level, preset.baseline_m)
    if not quantum["changed"]:
        return preset, None
    note = (f"Disparity quantum {quantum['reason']}. The model uses it from the base fit on (the device's output "
            f"format, not an effect).")
    return preset.replace(subpixel_level=quantum["level"]), note
