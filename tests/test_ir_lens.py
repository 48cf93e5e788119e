"""The IR lens and the reference the device recorded through it (ddsgen/sensor/ir_lens.py): the lens's maps invert
each other, a pinhole lens changes nothing, and on planes the lens loses depth where the physics says -- in the
corners, on surfaces away from the reference plane, not along the image's central cross -- while the depth it keeps
is right."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from ddsgen.depth_statistics import normalised_radius
from ddsgen.preset import load_preset
from ddsgen.sensor.depth_sensor import DepthSensor
from ddsgen.sensor.ir_lens import IRLens, distorted_px, undistorted_px
from gradient_check import autograd_and_difference
from sensor_scenes import plane_geometry

F, CX, CY = 572.41, 319.5, 239.5


def test_the_lens_maps_invert_each_other_and_a_barrel_lens_looks_further_out_in_the_corners():
    v, u = torch.meshgrid(torch.arange(0, 480, 7.0, dtype=torch.float64), torch.arange(0, 640, 7.0,
                          dtype=torch.float64), indexing="ij")  # fmt: skip
    for k1 in (-0.2, 0.05, 0.17, 0.3):
        su, sv = undistorted_px(u, v, k1, F, F, CX, CY)
        back_u, back_v = distorted_px(su, sv, k1, F, F, CX, CY)
        assert float((back_u - u).abs().max()) < 1e-6 and float((back_v - v).abs().max()) < 1e-6, k1
    su, sv = undistorted_px(torch.tensor([0.0]), torch.tensor([0.0]), 0.17, F, F, CX, CY)
    assert float(su) < 0 and float(sv) < 0  # barrel: the corner pixel sees beyond the pinhole's corner
    su, sv = undistorted_px(torch.tensor([CX]), torch.tensor([CY]), 0.17, F, F, CX, CY)
    assert (float(su), float(sv)) == (CX, CY)  # and the principal point along the axis


def _unregistered(ir_lens_k1=0.0, **changes):
    """kinect_v1 writing depth on its IR camera's grid; a pinhole lens unless ``ir_lens_k1`` is given."""
    return load_preset("kinect_v1").replace(registration_ir_offset_m=0.0, registration_shift_px=0.0,
                                            ir_margin_right_px=0, ir_lens_k1=ir_lens_k1, **changes)  # fmt: skip


def test_a_pinhole_lens_records_the_reference_at_infinity_shifted_by_the_planes_disparity():
    """With k1 = 0 the plane at z_ref, seen through the lens and shifted by f b / z_ref, is the reference at infinity
    the matcher reads without a lens: the reference distance then changes nothing."""
    preset = _unregistered()
    sensor = DepthSensor(preset)
    at_infinity = sensor.reference_phases()
    for distance in (0.8, 2.5):
        recorded = IRLens(0.0, distance).reference_phases(sensor.pattern_field(), 640, 480, sensor.pad, 3, F, F, CX,
                                                          CY, preset.baseline_m)  # fmt: skip
        assert float((recorded - at_infinity).abs().max()) < 1e-3 * float(at_infinity.abs().max()), distance


def _plane(preset, z):
    with torch.no_grad():
        out = DepthSensor(preset).eval()(plane_geometry(preset.intrinsics, z), seed=1)
    return out.depth.numpy(), out.valid.numpy()


@pytest.mark.parametrize("z", [1.0, 2.5])
def test_the_lens_loses_the_corners_of_a_plane_away_from_the_reference_plane_and_keeps_its_central_cross(z):
    preset = _unregistered(ir_lens_k1=0.17, reference_distance_m=1.0)
    pinhole = _unregistered()
    depth, valid = _plane(preset, z)
    _, valid_pinhole = _plane(pinhole, z)
    r = normalised_radius(480, 640)
    v, u = np.mgrid[0:480, 0:640]
    corners = (r > 0.85) & (u > 20)  # the device's blind left band is not the lens's
    cross = (r > 0.7) & ((np.abs(v - CY) < 20) | (np.abs(u - CX) < 20)) & (u > 20)  # x y ~ 0: no row shift
    centre = r < 0.5
    assert valid[centre].mean() > 0.99
    assert valid[cross].mean() > 0.97
    if z == 1.0:  # the reference plane itself: its dots sit where the reference has them, corners included
        assert valid[corners].mean() > 0.95
    else:  # 2.5 m: the corners' dots are about 2 k1 x y f b (1/z - 1/z_ref) = 2 px off their rows
        assert valid[corners].mean() < 0.3 < valid_pinhole[corners].mean()
    # The calibration undoes the lens: where the dots stay on their rows (the whole reference plane; the cross, whose
    # outer part the lens bends by 3-5 %, at any distance) depth is unbiased, within the 1/8-px quantum's saw-tooth.
    quantum = z * z / (F * preset.baseline_m) / 8
    for part in (centre, cross) + ((corners,) if z == 1.0 else ()):
        error = (depth[part & valid] - z) / quantum
        assert abs(error.mean()) < 0.2 and np.median(np.abs(error)) < 0.75


@pytest.mark.parametrize("name, output", [("log_baseline", "disparity"), ("log_focal_scale", "raw_depth")])
def test_depth_through_the_lens_has_the_gradient_of_its_finite_differences(name, output):
    """As tests/test_sensor.py's check, through the lens: the IR image on the distorted grid, the match against the
    recorded reference and the calibration's conversion back (a tilted plane about the reference distance, where the
    dots stay near their rows; quantise=False, fixed noise, a fixed mask of valid pixels). The step is 1e-3: the
    lens's off-row dots make more matches change peak within larger steps (focal scale, measured: autograd 1.039;
    differences 1.033, 1.22, -1.77 over 1e-3, 3e-3, 1e-2). The baseline on the disparity, as
    tests/test_device_model.py checks it: depth hardly moves with b (the dots move with it)."""
    from sensor_scenes import small_kinect

    sensor = DepthSensor(small_kinect(128, 96, electrons_per_count=0.0, read_noise_std_counts=10.4,
                                      ir_lens_k1=0.17, reference_distance_m=0.9))  # fmt: skip
    geometry = plane_geometry(sensor.intr, 0.9, tilt_deg=20.0)
    noise = sensor.draw_noise(3)
    with torch.no_grad():
        mask = sensor(geometry, noise=noise, quantise=False).valid

    def loss():
        return getattr(sensor(geometry, noise=noise, quantise=False), output)[mask].double().mean()

    autograd, difference = autograd_and_difference(loss, getattr(sensor, name), eps=1e-3)
    assert autograd == pytest.approx(difference, rel=0.03, abs=1e-8)
