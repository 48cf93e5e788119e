"""The ray casts one sensor frame needs: the output image, the IR margin strip, and for a device registered to
an RGB camera the IR camera's own view with the map back to the output image.

Every command that simulates scenes goes through here (render, the noise study and the unpaired search via
:func:`cast_for_sensor`; compare, fit and diagnose via :func:`sensor_geometry` after their own cast).
"""

from __future__ import annotations

from ddsgen.preset import Intrinsics
from ddsgen.raycast import cast
from ddsgen.sensor.geometry import SensorGeometry
from ddsgen.sensor.ir_margin import cast_margin, cast_widened
from ddsgen.sensor.registration import (
    ir_view,
    is_registered,
    output_projector_x_m,
    registration_index,
)


def cast_for_sensor(scene, intrinsics: Intrinsics, preset, output_shadows: bool = True):
    """Ray-cast ``scene`` for the sensor: ``(hits, geometry)``, the output image's RayHits and the
    :class:`~ddsgen.sensor.geometry.SensorGeometry` (:func:`sensor_geometry`).

    ``output_shadows=False``: a registered device's output view skips its shadow rays (``hits.shadow`` is None;
    the sensor runs on the IR camera's view, which has its own): 25-30 ms of a 640x480 frame. An unregistered
    device's output view is the sensor's, so it always has them."""
    shadows = output_shadows or not is_registered(preset)
    hits = cast(scene, intrinsics, output_projector_x_m(preset), preset.shadow_bias_m, shadows=shadows)
    return hits, sensor_geometry(scene, intrinsics, preset, hits)


def sensor_geometry(scene, intrinsics: Intrinsics, preset, hits):
    """The :class:`~ddsgen.sensor.geometry.SensorGeometry` of ``scene`` given its output image's ``hits``:
    the IR image with the preset's margin strip; for a device registered to an RGB camera
    (:mod:`ddsgen.sensor.registration`) the IR camera's own view and the map back to the output image."""
    if not is_registered(preset):
        margin = cast_margin(scene, intrinsics, preset.ir_margin_right_px, preset.baseline_m, preset.shadow_bias_m)
        return SensorGeometry.from_hits(hits, ir_margin=margin)
    ir_scene, ir_intrinsics = ir_view(scene, intrinsics, preset)
    ir_hits = cast_widened(ir_scene, ir_intrinsics, preset.ir_margin_right_px, preset.baseline_m,
                           preset.shadow_bias_m)  # (H, W + margin): one cast, taken apart without a copy
    index = registration_index(hits, ir_hits, intrinsics, preset)
    return SensorGeometry.from_hits(ir_hits, width=int(ir_intrinsics.width), registration=index,
                                    registration_shift_px=preset.registration_shift_px,
                                    registration_offset_m=preset.registration_ir_offset_m)  # fmt: skip
