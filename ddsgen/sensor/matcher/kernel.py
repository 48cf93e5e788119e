"""The matcher's C kernels (csrc/zncc.c): compiled with the system C compiler on first use,
cached in ddsgen's cache folder, loaded with ctypes; thin wrappers that call them.

:func:`_load_kernel` returns None when there is no compiler (or OpenMP), or when
``DDSGEN_NO_C_KERNEL`` is set: the matcher then runs its torch path.
"""

from __future__ import annotations

import ctypes
import threading

import torch

from ddsgen.ckernel import c_source, load_c_library
from ddsgen.sensor.matcher.reference import RefineGeometry, _Reference

#: Candidates per vector of the integer search (``SL`` in csrc/zncc.c): its reference arrays need this many
#: readable columns beyond the last candidate.
SEARCH_LANES = 16

_KERNEL = None
_KERNEL_TRIED = False
_KERNEL_LOCK = threading.Lock()


def _load_kernel():
    """Compile csrc/zncc.c (:func:`ddsgen.ckernel.load_c_library`: once per source, compiler, flags and
    CPU, cached in ddsgen's cache folder) and load it; memoised per process. Returns None when there is
    no C compiler or OpenMP (``$CC``, default ``cc``), or with ``DDSGEN_NO_C_KERNEL`` set: then the torch
    path does the work."""
    global _KERNEL, _KERNEL_TRIED
    with _KERNEL_LOCK:
        if _KERNEL_TRIED:
            return _KERNEL
        _KERNEL_TRIED = True
        flags = ["-O3", "-march=native", "-fopenmp", "-fPIC", "-shared", "-std=gnu11"]
        lib = load_c_library(c_source(__package__, "csrc", "zncc.c"), "zncc", flags, "matcher", "torch path")
        if lib is not None:
            p, i = ctypes.c_void_p, ctypes.c_int
            lib.ddsgen_zncc_search.argtypes = [p, i, p, i, p, p, p, p, p, i, i, i, i, i, i, p, p, p, p, ctypes.c_float, ctypes.c_float, i]
            f = ctypes.c_float
            q = ctypes.c_int64
            lib.ddsgen_refine.argtypes = [p, i, p, q, q, i, i, i, i, p, i, i, i, i, i, p, p, p, q, q, p, p, f, i, f, f,
                                          p, p, p, p, p, p, i]  # fmt: skip
            lib.ddsgen_observed_stats.argtypes = [p, i, i, i, f, p, p, p, p, p, i]
            lib.ddsgen_window_cross_grad.argtypes = [p, i, p, i, i, i, i, i, p, i, i, i, i, i, p, i, i]
            lib.ddsgen_confirm_by_unique_neighbour.argtypes = [p, i, p, p, q, p, i, i, p, i]
            for fn in (lib.ddsgen_zncc_search, lib.ddsgen_refine, lib.ddsgen_window_cross_grad, lib.ddsgen_observed_stats,
                       lib.ddsgen_confirm_by_unique_neighbour):
                fn.restype = None
        _KERNEL = lib
        return _KERNEL


def integer_search_backend(device="cpu") -> str:
    """Which integer-search implementation :func:`match` uses on ``device``: "c" or "torch"."""
    return "c" if torch.device(device).type == "cpu" and _load_kernel() is not None else "torch"



def _n_threads() -> int:
    return max(1, torch.get_num_threads())



def _integer_search_c(fn, o_pad, ref: _Reference, os_, inv_o, block, r0, n_disp, second_floor: float = 1.0,
                      min_confidence: float = 0.0):  # fmt: skip
    """(best, second, arg, arg2), each (H, W): the best and second-peak ZNCC and their candidate indices
    (disparity k_hi - index; -1 where there is none; arg2 only where second > second_floor at a match
    failing the uniqueness test, -1 elsewhere)."""
    H, W = os_.shape
    o = o_pad.detach().float().contiguous()
    osum, oinv = os_.detach().float().contiguous(), inv_o.detach().float().contiguous()
    best = torch.empty(H, W, dtype=torch.float32)
    second = torch.empty(H, W, dtype=torch.float32)
    arg = torch.empty(H, W, dtype=torch.int32)
    arg2 = torch.empty(H, W, dtype=torch.int32)
    fn.ddsgen_zncc_search(o.data_ptr(), o.shape[1], ref.r0_int.data_ptr(), ref.r0_int.shape[1], osum.data_ptr(), oinv.data_ptr(),
       ref.rs_int.data_ptr(), ref.inv_int.data_ptr(), ref.pen_int.data_ptr(), ref.rs_int.shape[1], H, W, block, r0, n_disp,
       best.data_ptr(), second.data_ptr(), arg.data_ptr(), arg2.data_ptr(), float(second_floor),
       float(min_confidence), max(1, torch.get_num_threads()))  # fmt: skip
    return best, second, arg.long(), arg2



def _call_refine(lib, o, osum, oinv, beta: float, k, ref: _Reference, geom: RefineGeometry, v0: int, v1: int, disp=None,
                 grad=None):
    null = None
    gd, g_band, d_os, d_oi, d_beta = grad if grad is not None else (null,) * 5
    ptr = lambda x: None if x is None else x.data_ptr()  # noqa: E731
    lib.ddsgen_refine(o.data_ptr(), o.shape[1], ref.fwd.data_ptr(), ref.fwd.shape[1], ref.fwd_base, *ref.fwd_strides, ref.n_cand,
                      ref.n_cand_padded, k.data_ptr(), geom.col_shift, v0, v1, k.shape[1], geom.block,
                      ref.stat_sum.data_ptr(), ref.stat_inv.data_ptr(), ref.stat_unk.data_ptr(), ref.stat_sum.shape[1],
                      ref.stat_base,
                      osum.data_ptr(), oinv.data_ptr(), beta, 2**geom.n_sub, geom.d_min - 1e-6, geom.d_max + 1e-6, ptr(disp),
                      ptr(gd), ptr(g_band), ptr(d_os), ptr(d_oi), ptr(d_beta), _n_threads())  # fmt: skip


def confirm_by_unique_neighbour_c(lib, seeds: torch.Tensor, width: int, ys: torch.Tensor, xs: torch.Tensor,
                                  owns: list[torch.Tensor], block: int) -> list[torch.Tensor]:
    """The C twin of :func:`ddsgen.sensor.matcher._confirmed_by_a_unique_neighbour`'s gather: per peak, (N,) bool
    whether a unique neighbour within the window of each candidate (``ys``, ``xs``: (N,) int64) agrees with it.

    Args:
        seeds: flat int32 ((H + 2h) * width,) disparities of the unique matches, padded by h, a sentinel elsewhere.
        width: the padded row length W + 2h.
        owns: the candidates' peak disparities, each (N,) int32.
    """
    n = int(ys.numel())
    own = torch.stack(owns).to(torch.int32).contiguous() if owns else torch.empty(0, n, dtype=torch.int32)
    out = torch.empty(len(owns), n, dtype=torch.uint8)
    if n:
        seeds, ys, xs = seeds.contiguous(), ys.contiguous(), xs.contiguous()
        lib.ddsgen_confirm_by_unique_neighbour(seeds.data_ptr(), int(width), ys.data_ptr(), xs.data_ptr(), n,
                                               own.data_ptr(), len(owns), int(block), out.data_ptr(), _n_threads())
    return list(out.bool())
