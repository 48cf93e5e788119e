"""The IR camera's margin: the columns it sees beyond the depth image's right edge.

A matching window is ``block`` px wide, so a depth pixel needs IR pixels ``block // 2`` to each side. When
the simulated IR image is exactly the depth image's grid, the last ``block // 2`` columns have no whole
window and come out invalid. The real device does not show that band: its depth image is offset from
its IR image by about half a window (ROS kinect_calibration, "IR camera to depth offset", which
Smisek et al. 2011 also note), so the depth image's right edge is matched with IR pixels beyond it, while its left edge lacks
them (the ``output_left_border_px`` band: LineMOD cat columns 0-6 empty, the last 10 columns 88-91 %
valid, like the rest of the frame).

Preset key ``ir_margin_right_px`` (m): the caller ray-casts an (H, m) strip beyond the right edge
(:func:`cast_margin`; a registered device's IR view is cast widened by the strip,
:func:`cast_widened`; both through :func:`ddsgen.sensor.sensor_cast.cast_for_sensor`) and hands it to
:meth:`SensorGeometry.from_hits`; the sensor renders and matches the (H, W + m) IR image and returns the
(H, W) depth image. Where the cast image is the depth image, the strip is cast on its own, so the
depth image's own hits (clean depth, masks, labels, and the coverage behind the visible fractions) are exactly
those of a plain cast.
"""

from __future__ import annotations

import dataclasses

from ddsgen.preset import Intrinsics
from ddsgen.raycast import cast


def margin_intrinsics(intrinsics: Intrinsics, margin_px: int) -> Intrinsics:
    """Intrinsics of the (H, ``margin_px``) strip right of ``intrinsics``' image: its column 0 is column W."""
    return dataclasses.replace(intrinsics, width=int(margin_px), cx=intrinsics.cx - intrinsics.width)


def cast_margin(scene, intrinsics: Intrinsics, margin_px: int, baseline_m: float, shadow_bias_m: float):
    """Ray-cast the IR margin strip right of the image (a :class:`~ddsgen.raycast.RayHits` of shape
    (H, ``margin_px``)), or None when ``margin_px`` is 0."""
    if margin_px <= 0:
        return None
    return cast(scene, margin_intrinsics(intrinsics, margin_px), baseline_m, shadow_bias_m)


def cast_widened(scene, intrinsics: Intrinsics, margin_px: int, baseline_m: float, shadow_bias_m: float):
    """One cast of the image widened by the margin strip: a :class:`~ddsgen.raycast.RayHits` of shape
    (H, W + ``margin_px``), whose columns W.. are the strip. Every ray is cast on its own, so its first W columns
    and the strip equal separate casts pixel for pixel, for one cast's fixed cost (~10 ms of a 640 x 480 frame);
    its ``coverage`` counts the widened image. For a view whose coverage nobody reads (a registered device's IR
    camera): :meth:`ddsgen.sensor.geometry.SensorGeometry.from_hits` with ``width=W`` takes it apart without a
    copy. With ``margin_px`` 0: the plain cast."""
    return cast(scene, dataclasses.replace(intrinsics, width=int(intrinsics.width) + max(int(margin_px), 0)),
                baseline_m, shadow_bias_m)  # fmt: skip
