"""The IR camera's margin: the columns it sees beyond the depth image's right edge.

A matching window is ``block`` px wide, so a depth pixel needs IR pixels ``block // 2`` to each side. When
the simulated IR image is exactly the depth image's grid, the last ``block // 2`` columns have no whole
window and come out invalid. The real device does not show that band: its depth image is offset from
its IR image by about half a window (ROS kinect_calibration, "IR camera to depth offset", which
Smisek et al. 2011 also note), so the depth image's right edge is matched with IR pixels beyond it, while its left edge lacks
them (the ``output_left_border_px`` band: LineMOD cat columns 0-6 empty, the last 10 columns 88-91 %
valid, like the rest of the frame).

Preset key ``ir_margin_right_px`` (m): the caller ray-casts an (H, m) strip beyond the right edge
(:func:`cast_margin`; image and strip at once: :func:`cast_for_sensor`) and hands it to
:meth:`SensorGeometry.from_hits`; the sensor renders and matches the (H, W + m) IR image and returns the
(H, W) depth image. The strip is cast on its own, so the
depth image's own hits (clean depth, masks, labels) are exactly those of a plain cast.
"""

from __future__ import annotations

import dataclasses

from ddsgen.preset import Intrinsics


def margin_intrinsics(intrinsics: Intrinsics, margin_px: int) -> Intrinsics:
    """Intrinsics of the (H, ``margin_px``) strip right of ``intrinsics``' image: its column 0 is column W."""
    return dataclasses.replace(intrinsics, width=int(margin_px), cx=intrinsics.cx - intrinsics.width)


def cast_margin(scene, intrinsics: Intrinsics, margin_px: int, baseline_m: float, shadow_bias_m: float):
    """Ray-cast the IR margin strip right of the image (a :class:`~ddsgen.raycast.RayHits` of shape
    (H, ``margin_px``)), or None when ``margin_px`` is 0."""
    if margin_px <= 0:
        return None
    from ddsgen.raycast import cast

    return cast(scene, margin_intrinsics(intrinsics, margin_px), baseline_m, shadow_bias_m)


def cast_for_sensor(scene, intrinsics: Intrinsics, preset):
    """Ray-cast ``scene`` for the sensor: ``(hits, geometry)``, the output image's RayHits and the
    :class:`~ddsgen.sensor.depth_sensor.SensorGeometry` (:func:`sensor_geometry`)."""
    from ddsgen.raycast import cast
    from ddsgen.sensor.registration import output_projector_x_m

    hits = cast(scene, intrinsics, output_projector_x_m(preset), preset.shadow_bias_m)
    return hits, sensor_geometry(scene, intrinsics, preset, hits)


def sensor_geometry(scene, intrinsics: Intrinsics, preset, hits):
    """The :class:`~ddsgen.sensor.depth_sensor.SensorGeometry` of ``scene`` given its output image's ``hits``:
    the IR image with the preset's margin strip; for a device registered to an RGB camera
    (:mod:`ddsgen.sensor.registration`) the IR camera's own view and the map back to the output image."""
    from ddsgen.raycast import cast
    from ddsgen.sensor.depth_sensor import SensorGeometry
    from ddsgen.sensor.registration import ir_view, is_registered, registration_index

    if not is_registered(preset):
        margin = cast_margin(scene, intrinsics, preset.ir_margin_right_px, preset.baseline_m, preset.shadow_bias_m)
        return SensorGeometry.from_hits(hits, ir_margin=margin)
    ir_scene, ir_intrinsics = ir_view(scene, intrinsics, preset)
    ir_hits = cast(ir_scene, ir_intrinsics, preset.baseline_m, preset.shadow_bias_m)
    margin = cast_margin(ir_scene, ir_intrinsics, preset.ir_margin_right_px, preset.baseline_m, preset.shadow_bias_m)
    index = registration_index(hits, ir_hits, intrinsics, preset)
    return SensorGeometry.from_hits(ir_hits, ir_margin=margin, registration=index,
                                    registration_shift_px=preset.registration_shift_px,
                                    registration_offset_m=preset.registration_ir_offset_m)  # fmt: skip
