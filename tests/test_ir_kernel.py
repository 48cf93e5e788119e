"""The IR image's C pass (ddsgen/csrc/ir_image.c) against render_ir's torch definition."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from ddsgen.sensor import ir_kernel
from ddsgen.sensor.depth_sensor import DepthSensor
from ddsgen.sensor.ir import IRNoise, render_ir
from tests.sensor_scenes import plane_geometry, small_kinect

# (projector fall-off, vignetting, electrons per count, quantise): the device's, none, odd whole powers without
# shot noise, the highest power the C pass takes.
CASES = [(4, 4, 31.0, True), (0, 0, 0.0, True), (3, 1, 0.0, False), (8, 2, 5.0, True)]


def _inputs(falloff, vignetting, electrons, seed=0):
    """A slanted plane at 1.4 m with random albedo, normals tilted by up to ~30 degrees, a few unlit pixels and
    noise drawn for a wider image (the IR margin): ``render_ir``'s arguments for a 160 x 120 kinect_v1."""
    preset = small_kinect(ir_margin_right_px=0)
    sensor = DepthSensor(preset).eval()
    geometry = plane_geometry(preset.intrinsics, 1.4, tilt_deg=35.0)
    rng = np.random.default_rng(seed)
    shape = geometry.albedo.shape
    normals = geometry.normals + torch.from_numpy(rng.normal(0.0, 0.3, geometry.normals.shape).astype(np.float32))
    normals = normals / normals.norm(dim=-1, keepdim=True)
    albedo = torch.from_numpy(rng.uniform(0.02, 1.0, shape).astype(np.float32))
    lit = torch.from_numpy((rng.random(shape) > 0.1).astype(np.float32))
    noise = IRNoise.draw(shape[0], shape[1] + 7, 4.54, rng, speckle_grain_px=1.0)
    intr = sensor.intr
    with torch.no_grad():  # plain tensors: the sensor's parameters want no gradient here
        return (geometry.points, normals, albedo, lit, sensor.pattern_field(), intr.fx * sensor.focal_scale,
                intr.fy * sensor.focal_scale, intr.cx - preset.registration_shift_px, intr.cy, sensor.baseline,
                sensor.emitted_intensity, sensor.ambient, sensor.speckle_scale, sensor.read_noise_mean,
                sensor.read_noise_std, noise, preset.ir_bits)  # fmt: skip


def _render(args, falloff, vignetting, electrons, quantise):
    with torch.no_grad():
        return render_ir(*args, quantise=quantise, projector_falloff_exponent=falloff, vignetting_exponent=vignetting,
                         electrons_per_count=electrons)  # fmt: skip


def _exact_sqrt(x):
    """float32 square roots rounded correctly (torch's CPU float32 sqrt is not: ~0.6 % of them are 1 ulp off)."""
    return torch.from_numpy(np.sqrt(x.detach().numpy()))


@pytest.mark.parametrize("falloff, vignetting, electrons, quantise", CASES)
def test_the_c_ir_image_is_the_torch_definition_operation_by_operation(monkeypatch, falloff, vignetting, electrons,
                                                                       quantise):  # fmt: skip
    """With correctly rounded square roots on both sides the C pass gives the definition's signal and counts bit
    for bit; with torch's own square roots the signal is within 20 ulp and at most 0.1 % of the counts move by one."""
    if ir_kernel._library() is None:
        pytest.skip("no C compiler: the torch definition is the only path")
    args = _inputs(falloff, vignetting, electrons)
    ir_c, signal_c = _render(args, falloff, vignetting, electrons, quantise)
    monkeypatch.setattr(ir_kernel, "_library", lambda: None)
    ir_t, signal_t = _render(args, falloff, vignetting, electrons, quantise)
    assert signal_c.abs().max() > 1.0 and (signal_c == 0).any()  # lit and unlit pixels, a real signal
    torch.testing.assert_close(signal_c, signal_t, rtol=2.5e-6, atol=0.0)  # 1 ulp in a distance, 8th powers
    if quantise:
        moved = ir_c != ir_t
        assert float(moved.float().mean()) <= 1e-3 and float((ir_c - ir_t).abs().max()) <= 1.0
    else:
        torch.testing.assert_close(ir_c, ir_t, rtol=1e-6, atol=1e-4)
    monkeypatch.setattr(torch.Tensor, "sqrt", _exact_sqrt)
    monkeypatch.setattr(torch, "sqrt", _exact_sqrt)
    ir_exact, signal_exact = _render(args, falloff, vignetting, electrons, quantise)
    assert torch.equal(signal_c, signal_exact) and torch.equal(ir_c, ir_exact)


def test_the_c_ir_image_leaves_gradients_and_fractional_powers_to_the_definition():
    """Where the definition must run, the C pass declines: a parameter that wants a gradient, a
    fall-off exponent that is not a whole number from 0 to 8, no noise."""
    if ir_kernel._library() is None:
        pytest.skip("no C compiler: the torch definition is the only path")
    args = list(_inputs(4, 4, 31.0))
    base = dict(ir_bits=args[16], quantise=True, projector_falloff_exponent=4.0, vignetting_exponent=4.0,
                electrons_per_count=31.0, pattern_unit=1.0)  # fmt: skip
    positional = args[:16]
    with torch.no_grad():
        assert ir_kernel.render_ir_c(*positional, **base) is not None
        assert ir_kernel.render_ir_c(*positional, **{**base, "projector_falloff_exponent": 2.5}) is None
        assert ir_kernel.render_ir_c(*positional, **{**base, "vignetting_exponent": 9.0}) is None
        assert ir_kernel.render_ir_c(*positional[:15], None, **base) is None
    wanting = args[10].clone().requires_grad_(True)
    assert ir_kernel.render_ir_c(*positional[:10], wanting, *positional[11:], **base) is None
    ir, _ = render_ir(*positional[:10], wanting, *positional[11:], ir_bits=args[16])
    ir.sum().backward()
    assert wanting.grad is not None and float(wanting.grad) > 0  # more emitted light, more counts
