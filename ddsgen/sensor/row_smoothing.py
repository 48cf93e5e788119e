"""The device's smoothing of its disparity along the rows (``row_smoothing_weight``).

Real PrimeSense depth is grained along the rows: on flat surfaces the noise of a pixel and of its right neighbour
correlate 0.53-0.67 (median 0.62, nine IC-BIN frames; the LineMOD cat and the TUM frame 0.62 and 0.63), of a pixel
and of its lower neighbour 0.34-0.56 (median 0.43; :mod:`ddsgen.surface_roughness`). A square matching window
alone gives about the same correlation both ways (0.42 and 0.44, medians of 16 renders): the device combines
neighbouring columns' matches along the row (how is not published: an average of adjacent windows' disparities and a
window wider than tall act alike). Modelled as a 3-tap average [w, 1 - 2w, w] of each valid disparity with its
left and right neighbours on the same surface (within :data:`SAME_SURFACE_PX` of it; a missing or other-surface
neighbour counts as the pixel itself, so depth edges are not blurred), on the matcher's sub-pixel estimates, then
the device's 2^-n px quantum (rounding first and again after moves a pixel only when w times its neighbours'
offset reaches half a step: a step function of w). ``ddsgen fit --unpaired`` measures w on the grain
(:mod:`ddsgen.fit.unpaired.features`): IC-BIN 0.163, the LineMOD cat 0.158, TUM 0.169 (kinect_v1: 0.16), which gives
0.59 / 0.37 on the renders (a row filter lowers the column correlation a little, which it cannot raise). Linear, so
differentiable; the quantum keeps its straight-through gradient.
"""

from __future__ import annotations

import ctypes
import functools

import torch

from ddsgen.ckernel import load_exact_c_library
from ddsgen.sensor.ir import straight_through_round
from ddsgen.sensor.ir_kernel import float32_value

#: Neighbours whose disparity differs by more than this (px) are another surface and are not averaged in.
SAME_SURFACE_PX = 1.0


def smooth_along_rows(disparity: torch.Tensor, valid: torch.Tensor, weight: float,
                      quantum_px: float | None) -> torch.Tensor:  # fmt: skip
    """Average each valid disparity with its row neighbours on the same surface, then quantise.

    Args:
        disparity: (H, W) the matcher's sub-pixel disparity (px), not yet on the device's quantum.
        valid: (H, W) bool, the matcher's valid pixels (the others are only quantised, and never averaged in).
        weight: w of the weights [w, 1 - 2w, w] (0 <= w <= 0.5); 0 returns ``disparity`` itself.
        quantum_px: the output quantum 2^-n px (straight-through rounding, every pixel); None keeps it unrounded.

    Returns:
        (H, W) disparity (px).
    """
    if weight <= 0:
        return disparity
    fast = _smooth_along_rows_c(disparity, valid, weight, quantum_px)
    if fast is not None:  # the same disparities in C where no gradient is taken
        return fast
    same = valid[:, 1:] & valid[:, :-1] & ((disparity[:, 1:] - disparity[:, :-1]).abs() <= SAME_SURFACE_PX)
    # Each pixel's left and right neighbours, or the pixel itself where that neighbour is not on its surface.
    left = disparity.clone()
    left[:, 1:] = torch.where(same, disparity[:, :-1], disparity[:, 1:])
    right = disparity.clone()
    right[:, :-1] = torch.where(same, disparity[:, 1:], disparity[:, :-1])
    smoothed = torch.where(valid, (1.0 - 2.0 * weight) * disparity + weight * (left + right), disparity)
    if quantum_px is not None:
        smoothed = straight_through_round(smoothed / quantum_px) * quantum_px
    return smoothed


@functools.cache
def _library():
    p, q, f = ctypes.c_void_p, ctypes.c_int64, ctypes.c_float
    return load_exact_c_library("ddsgen", "row_smoothing.c", "row smoothing", "torch path",
                                {"ddsgen_smooth_along_rows": [p, p, q, q, f, f, f, f, p]})


def _smooth_along_rows_c(disparity: torch.Tensor, valid: torch.Tensor, weight, quantum_px) -> torch.Tensor | None:
    """:func:`smooth_along_rows` in ddsgen/csrc/row_smoothing.c, or None where the torch definition runs: a gradient
    wanted, another device or dtype, no C compiler (or ``DDSGEN_NO_C_KERNEL``)."""
    wants_grad = torch.is_grad_enabled() and (disparity.requires_grad or getattr(weight, "requires_grad", False))
    if wants_grad or disparity.device.type != "cpu" or disparity.dtype != torch.float32 or disparity.dim() != 2:
        return None
    lib = _library()
    if lib is None:
        return None
    height, width = disparity.shape
    source = disparity.contiguous()
    mask = valid.to(device="cpu", dtype=torch.bool).contiguous()  # one byte per pixel, 0 or 1
    out = torch.empty_like(source)
    lib.ddsgen_smooth_along_rows(source.data_ptr(), mask.data_ptr(), height, width, float32_value(1.0 - 2.0 * weight),
                                 float32_value(weight), float32_value(SAME_SURFACE_PX),
                                 0.0 if quantum_px is None else float32_value(quantum_px), out.data_ptr())  # fmt: skip
    return out
