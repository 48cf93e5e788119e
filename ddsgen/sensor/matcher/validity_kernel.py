"""The matcher's validity in C (csrc/validity.c): from the integer search's peaks to the confidence, the valid map
and the kept integer disparity in two passes, where :func:`ddsgen.sensor.matcher.match` does some twenty
whole-image torch passes (its definition, with :func:`ddsgen.sensor.matcher._validity`). The same maps bit for bit
(tests/test_matcher.py); :func:`match_validity_c` returns None without a C compiler (or with
``DDSGEN_NO_C_KERNEL``), and the definition runs.
"""

from __future__ import annotations

import ctypes
import functools

import torch

from ddsgen.ckernel import load_exact_c_library


@functools.cache
def _library():
    p, q, i, f = ctypes.c_void_p, ctypes.c_int64, ctypes.c_int, ctypes.c_float
    return load_exact_c_library(__package__, "validity.c", "matcher validity", "torch path",
                                {"ddsgen_match_validity": [p, p, p, p, q, q, q, q, i, f, f, p, p, p, p, p, p, p]})


def match_validity_c(best: torch.Tensor, second: torch.Tensor, arg: torch.Tensor, arg2: torch.Tensor, k_hi: int,
                     k_lo: int, block: int, min_confidence: float, confirmed_match_zncc: float):  # fmt: skip
    """``(best, second, confidence, valid, k_int, k_second)`` from the C integer search's (H, W) outputs (``best``,
    ``second`` float32, ``arg`` int64, ``arg2`` int32, on the CPU): the peaks' ZNCC clipped to [0, 1], the
    confidence, the valid map, the kept integer disparity (int64) and the second peak's (int32, -1 for none).
    None without the C library."""
    lib = _library()
    if lib is None:
        return None
    height, width = best.shape
    h = block // 2
    best, second = best.contiguous(), second.contiguous()
    arg, arg2 = arg.to(torch.int64).contiguous(), arg2.to(torch.int32).contiguous()
    seeds = torch.empty((height + 2 * h) * (width + 2 * h), dtype=torch.int32)
    outs = (torch.empty_like(best), torch.empty_like(second), torch.empty_like(best),
            torch.empty((height, width), dtype=torch.bool), torch.empty((height, width), dtype=torch.int64),
            torch.empty((height, width), dtype=torch.int32))  # fmt: skip
    lib.ddsgen_match_validity(best.data_ptr(), second.data_ptr(), arg.data_ptr(), arg2.data_ptr(), height, width,
                              int(k_hi), int(k_lo), int(block), float(min_confidence), float(confirmed_match_zncc),
                              seeds.data_ptr(), *(t.data_ptr() for t in outs))  # fmt: skip
    return outs
