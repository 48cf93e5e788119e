"""The IR camera image in C (ddsgen/csrc/ir_image.c) where no gradient is taken: ``render`` and every other
forward-only use of :func:`ddsgen.sensor.ir.render_ir`.

Two passes over the pixels around torch's ``grid_sample`` replace some thirty whole-image torch passes (about
10 ms of a 640 x 480 frame). Each pass does the torch definition's float32 operations in its order, but with
correctly rounded square roots, which torch's CPU float32 ``sqrt`` is not (about 0.6 % of its results are 1 ulp
off): the signal agrees within a few ulp, and 3 IR counts of 16 default renders differ by one
(tests/test_ir_kernel.py checks both, and bit-for-bit equality with correct square roots on both sides).
:func:`render_ir_c` returns None where the definition must run instead: no C compiler (or ``DDSGEN_NO_C_KERNEL``),
a gradient wanted, another device or dtype, no noise, or a fall-off exponent that is not a whole
number from 0 to 8.
"""

from __future__ import annotations

import ctypes
import functools

import torch
import torch.nn.functional as F

from ddsgen.ckernel import load_exact_c_library


@functools.cache
def _library():
    p, q, f, i = ctypes.c_void_p, ctypes.c_int64, ctypes.c_float, ctypes.c_int
    return load_exact_c_library("ddsgen", "ir_image.c", "IR image", "torch path", {
        "ddsgen_ir_grid": [p, q, f, f, f, f, f, f, f, f, f, f, f, p],
        "ddsgen_ir_image": [p, p, p, p, p, p, p, q, q, q] + [f] * 9 + [i, i, f, i, p, p],
    })  # fmt: skip


def _whole_exponent(exponent: float) -> int | None:
    """``exponent`` as an int when the C pass computes it as the definition does (0 = off, 1..8 by squaring)."""
    value = float(exponent)
    if value.is_integer() and 0 <= value <= 8:
        return int(value)
    return None


def float32_value(value) -> float:
    """A scalar (0-d tensor or Python number) as the float32 a torch float32 operation computes with: Python numbers
    rounded once, float32 tensors as they are."""
    return float(torch.as_tensor(value, dtype=torch.float32))


def render_ir_c(points: torch.Tensor, normals: torch.Tensor, albedo: torch.Tensor, lit: torch.Tensor, field,
                fx, fy, cx, cy, baseline, emitted_intensity, ambient, speckle_scale, read_noise_mean, read_noise_std,
                noise, ir_bits: int, quantise: bool, projector_falloff_exponent: float, vignetting_exponent: float,
                electrons_per_count: float, pattern_unit: float):  # fmt: skip
    """``(ir, signal)`` as :func:`ddsgen.sensor.ir.render_ir` returns them (same arguments), or None where its
    definition must run (module docstring)."""
    tensors = (points, normals, albedo, lit, noise.speckle_unit, noise.read_unit) if noise is not None else ()
    scalars = (fx, fy, cx, cy, baseline, emitted_intensity, ambient, speckle_scale, read_noise_mean, read_noise_std)
    falloff, vignetting = _whole_exponent(projector_falloff_exponent), _whole_exponent(vignetting_exponent)
    if (noise is None or falloff is None or vignetting is None
            or any(t.device.type != "cpu" or t.dtype != torch.float32 for t in tensors)
            or (torch.is_grad_enabled() and any(torch.is_tensor(v) and v.requires_grad for v in tensors + scalars))
            or field.raster.dtype != torch.float32):  # fmt: skip
        return None
    lib = _library()
    if lib is None:
        return None
    height, width = albedo.shape
    speckle, read = noise.speckle_unit[:, :width], noise.read_unit[:, :width]
    if speckle.stride() != read.stride() or speckle.stride(1) != 1 or read.shape[0] != height:
        return None
    points, normals = points.contiguous(), normals.contiguous()
    albedo, lit = albedo.contiguous(), lit.contiguous()
    hs, ws = field.raster.shape
    grid = torch.empty((1, 1, height * width, 2), dtype=torch.float32)
    lib.ddsgen_ir_grid(points.data_ptr(), height * width, *(float32_value(v) for v in (fx, fy, cx, cy, baseline)),
                       *(float32_value(v) for v in (field.origin_u, field.origin_v, field.sx, field.sy, ws, hs)),
                       grid.data_ptr())  # fmt: skip
    pattern = F.grid_sample(field.raster[None, None], grid, mode="bilinear", padding_mode="zeros",
                            align_corners=False).reshape(height, width)  # fmt: skip
    ir, signal = torch.empty((height, width)), torch.empty((height, width))
    lib.ddsgen_ir_image(points.data_ptr(), normals.data_ptr(), albedo.data_ptr(), lit.data_ptr(), pattern.data_ptr(),
                        speckle.data_ptr(), read.data_ptr(), speckle.stride(0), height, width,
                        *(float32_value(v) for v in (pattern_unit, baseline, emitted_intensity, ambient, speckle_scale,
                                               read_noise_mean, read_noise_std, read_noise_std**2, electrons_per_count)),
                        falloff, vignetting, float32_value(2.0**ir_bits - 1.0), int(bool(quantise)),
                        ir.data_ptr(), signal.data_ptr())  # fmt: skip
    return ir, signal
