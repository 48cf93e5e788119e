"""The differentiable block matcher: ZNCC, integer search, sub-pixel soft-argmax, row bands.

The observed IR image I_o(u, v) is compared with the reference R(u - d, v) for d in
[d_min, d_max] (DESIGN.md §2, "projector geometry"). Two stages:

1. **Integer search** (no gradient: an argmax is piecewise constant). Zero-mean normalised
   cross-correlation (ZNCC) over block x block windows for every integer disparity, keeping
   per pixel the best score, the best score of any other peak (>= 2 px away) and its
   argmax K. On the CPU this runs in a small C kernel (compiled once with the system C
   compiler, cached in the project cache; OpenMP over rows, vectorised over disparities;
   streaming, so it never holds a cost volume). Without a compiler, or on CUDA, a torch
   implementation over row bands does the same.
2. **Sub-pixel refinement** (differentiable). Candidates d_t = K + t / S, t = -T..T with
   S = 2^n_sub and T = S + S // 2 (K +- 1.5 px), scored by the same ZNCC against the sub-pixel shifted
   reference phases (exact windows, gathered per pixel, not approximated), then
   d = sum_t softmax(beta * zncc)_t * d_t. The forward value is quantised to 1/S px with a
   straight-through gradient. Candidates outside [d_min, d_max] or touching unknown
   reference columns (NaN in ``reference_phases``) are excluded. The window reaches 1 px
   beyond the true peak on both sides (which lies within K +- 1/2): with K +- 1/2 only, the
   truncated softmax pulled estimates towards K, and d(disparity)/d(image shift) was 0.85
   instead of 1, so gradients w.r.t. baseline disagreed with finite differences by 5x.

   On the CPU (float32, reference not requiring grad) one fused C kernel does the window
   cross-correlations, the ZNCC and the soft-argmax per pixel, writing only the disparity:
   no cost volume and no torch.compile (so a render worker's first frame pays no compile
   time). Its hand-written backward recomputes bands of ``band_rows`` rows in C. Elsewhere
   (float64, CUDA, differentiable reference, no C compiler) the same is written in torch,
   compiled with torch.compile where available (eager fallback).

Rows are independent (epipolar lines are rows): the refinement runs on horizontal bands of
``band_rows`` rows, each reading ``block - 1`` extra rows (the overlap), and each band is
recomputed in the backward pass (activation checkpointing in torch, recomputation in C),
so memory is bounded by the band, not the image. Every output pixel is computed from its
own window in a fixed order, so a band-split run is bit-identical to a single-band run
(forward and, on the C path, gradients), whatever the thread count. Top and bottom image rows use
mirrored rows (the same mirror in both images, so it is consistent); the ``block // 2``
columns at the left and right borders are reported invalid.

Confidence = clip(best, 0, 1) - clip(second peak, 0, 1) in [0, 1]: 0 for flat windows
(ZNCC 0), for ambiguous (repeated) texture and where no candidate exists; ``valid`` is
``confidence >= min_confidence`` (and > 0).

Gradients: the disparity is differentiable w.r.t. ``observed``, ``beta`` and (if they
require grad) ``reference_phases``; variance floors keep them finite on flat windows.
Everything works in float64 too (for ``torch.autograd.gradcheck``), with ``quantize=False``
to check the soft-argmax itself.

Shapes: observed (H, W); reference_phases (S, H, W + pad); outputs (H, W).
"""

from __future__ import annotations

import ctypes
import hashlib
import logging
import math
import os
import platform
import subprocess
import tempfile
import threading
import weakref
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch.utils.checkpoint import checkpoint

log = logging.getLogger(__name__)

#: Variance floor of a window, per pixel, in units of the image's global variance: keeps
#: ZNCC (and its gradient) finite on flat windows, where ZNCC -> 0.
VARIANCE_FLOOR = 1e-4
#: Score given to excluded refinement candidates (ZNCC itself is >= -1).
_EXCLUDED_SCORE = -3.0
#: Penalty added to integer-search scores of candidates whose window touches unknown reference.
_EXCLUDED_INT = -1e30

__all__ = ["MatchResult", "match", "stereo_reference_phases", "integer_search_backend", "VARIANCE_FLOOR"]


@dataclass
class MatchResult:
    """Output of :func:`match`, all (H, W).

    disparity: float px; differentiable; forward value quantised to 2^-n_sub px.
    confidence: in [0, 1] (best ZNCC minus the best other peak), no gradient.
    valid: bool, ``confidence >= min_confidence`` and inside the matchable area.
    """

    disparity: torch.Tensor
    confidence: torch.Tensor
    valid: torch.Tensor


# --------------------------------------------------------------------------------------
# Reference phases for an ordinary rectified stereo pair
# --------------------------------------------------------------------------------------
def _cubic_weights(t: torch.Tensor, a: float = -0.5) -> list[torch.Tensor]:
    """Keys cubic convolution weights for the 4 taps at offsets -1, 0, 1, 2 (t in [0, 1))."""

    def w(x):
        x = x.abs()
        return torch.where(
            x <= 1, (a + 2) * x**3 - (a + 3) * x**2 + 1,
            torch.where(x < 2, a * x**3 - 5 * a * x**2 + 8 * a * x - 4 * a, torch.zeros_like(x)),
        )  # fmt: skip

    return [w(t + 1), w(t), w(1 - t), w(2 - t)]


def stereo_reference_phases(right: torch.Tensor, n_sub: int, pad: int) -> torch.Tensor:
    """Sub-pixel shifted copies of the right image of a rectified pair, for :func:`match`.

    Args:
        right: (H, W) right image (any real dtype; float32/float64 kept).
        n_sub: sub-pixel level; S = 2^n_sub phases.
        pad: columns added on the left; must be >= ceil(d_max) + block for :func:`match`.

    Returns:
        (S, H, W + pad): column j of phase s holds R(j - pad - s/S) by Keys cubic
        interpolation along the row. Positions outside the right image are NaN
        ("unknown"): :func:`match` never matches against them, so pixels whose match
        would fall outside the right image come out invalid, not as fake matches.
    """
    if right.ndim != 2:
        raise ValueError(f"right image must be (H, W), got {tuple(right.shape)}")
    right = right if right.is_floating_point() else right.float()
    height, width = right.shape
    phases = 2 ** int(n_sub)
    cols = torch.arange(width + pad, device=right.device, dtype=right.dtype) - pad
    out = []
    for s in range(phases):
        x = cols - s / phases
        x0 = torch.floor(x)
        frac = x - x0
        weights = _cubic_weights(frac)
        acc = torch.zeros(height, width + pad, device=right.device, dtype=right.dtype)
        for tap, weight in zip((-1, 0, 1, 2), weights):
            idx = (x0.long() + tap).clamp(0, width - 1)
            acc = acc + right[:, idx] * weight
        inside = (x >= 0) & (x <= width - 1)
        out.append(torch.where(inside, acc, torch.full_like(acc, float("nan"))))
    return torch.stack(out).contiguous()


# --------------------------------------------------------------------------------------
# Helpers
# --------------------------------------------------------------------------------------
def _box_sum(x: torch.Tensor, block: int) -> torch.Tensor:
    """Sums over block x block windows of the last two dims (window-start indexing):
    (..., H, W) -> (..., H - block + 1, W - block + 1). Cumulative sums in float64."""
    acc = x.double()
    acc = F.pad(acc.cumsum(-1), (1, 0))
    acc = acc[..., block:] - acc[..., :-block]
    acc = F.pad(acc.cumsum(-2), (0, 0, 1, 0))
    acc = acc[..., block:, :] - acc[..., :-block, :]
    return acc.to(x.dtype)


def _pad_rows_reflect(x: torch.Tensor, h: int) -> torch.Tensor:
    """Mirror ``h`` rows at the top and bottom of (..., H, W) (no edge repeat)."""
    if h == 0:
        return x
    top = x[..., 1 : h + 1, :].flip(-2)
    bottom = x[..., -h - 1 : -1, :].flip(-2)
    return torch.cat([top, x, bottom], dim=-2)


def _pad_cols_reflect(x: torch.Tensor, h: int) -> torch.Tensor:
    if h == 0:
        return x
    left = x[..., :, 1 : h + 1].flip(-1)
    right = x[..., :, -h - 1 : -1].flip(-1)
    return torch.cat([left, x, right], dim=-1)


def _shift_cols(x: torch.Tensor, shift: int, fill=float("nan")) -> torch.Tensor:
    """y[..., j] = x[..., j - shift], ``fill`` where j - shift is outside."""
    if shift == 0:
        return x
    nan = torch.full_like(x[..., : abs(shift)], fill)
    if shift > 0:
        return torch.cat([nan, x[..., :-shift]], dim=-1)
    return torch.cat([x[..., -shift:], nan], dim=-1)


def _observed_stats(x: torch.Tensor, block: int):
    """Padded normalised observed image and its window statistics (torch).
    x: (H, W) -> o_pad (H + 2h, W + 2h) mirrored, osum (H, W) window sums, oinv (H, W)
    1 / window std (with the variance floor)."""
    h = block // 2
    n = block * block
    o_pad = _pad_cols_reflect(_pad_rows_reflect(x, h), h)
    osum = _box_sum(o_pad, block)
    osum2 = _box_sum(o_pad * o_pad, block)
    oinv = torch.rsqrt((osum2 - osum * osum / n).clamp_min(0) + VARIANCE_FLOOR * n)
    return o_pad, osum, oinv


class _ObservedStatsC(torch.autograd.Function):
    """:func:`_observed_stats` by one C kernel (float32 CPU). The backward recomputes the
    torch version and differentiates it (the values agree to float round-off)."""

    @staticmethod
    def forward(ctx, x, block):
        lib = _load_kernel()
        xc = x.detach().contiguous()
        H, W = xc.shape
        o_pad = torch.empty(H + block - 1, W + block - 1, dtype=torch.float32)
        osum, oinv = torch.empty(H, W, dtype=torch.float32), torch.empty(H, W, dtype=torch.float32)
        scratch = torch.empty(2, H + block - 1, W, dtype=torch.float64)
        lib.ddsgen_observed_stats(xc.data_ptr(), H, W, block, VARIANCE_FLOOR * block * block, o_pad.data_ptr(),
                                  osum.data_ptr(), oinv.data_ptr(), scratch[0].data_ptr(), scratch[1].data_ptr(),
                                  _n_threads())  # fmt: skip
        ctx.save_for_backward(xc)
        ctx.block = block
        return o_pad, osum, oinv

    @staticmethod
    def backward(ctx, d_pad, d_sum, d_inv):
        (xc,) = ctx.saved_tensors
        with torch.enable_grad():
            x = xc.detach().requires_grad_(True)
            outs = _observed_stats(x, ctx.block)
            pairs = [(o, g) for o, g in zip(outs, (d_pad, d_sum, d_inv)) if g is not None]
            (d_x,) = torch.autograd.grad([o for o, _ in pairs], [x], [g for _, g in pairs], allow_unused=True)
        return d_x, None


# --------------------------------------------------------------------------------------
# Prepared reference (normalised, padded, box statistics): constant per sensor, cached
# --------------------------------------------------------------------------------------
@dataclass
class _Reference:
    """The prepared reference, constant per sensor (cached per phases tensor).

    The refinement's candidate t = -T..T (d = K + t / S) reads phase t mod S shifted by
    floor(t / S) columns. No per-candidate copy is kept: on the C path (float32 CPU, reference
    not requiring grad) the kernels index the S phases directly, in two layouts of the same
    values (each the size of the phases, or 8 / S times it for S < 8):

    * ``fwd`` (H + 2h, FL + Wr S + FR): the phases interleaved along each row in reversed
      column order, element ``FL + (Wr - 1 - c) S + s`` = phase s, column c. Candidate t at
      column c is element ``fwd_base - c S + (t + T)``: the C candidates of a column are
      contiguous (the forward kernel vectorises over them). Zero outside the phases. For
      S < 8, where these vectors would straddle 32-byte boundaries, ``fwd`` holds instead the
      first 8 candidates of every column (8 floats per column, reversed order): vector q of
      column c is vector 0 of column c - 8q / S (``fwd_strides``).
    * ``bwd`` (S, H + 2h, BL + Wr + BR): the phases with zero columns on both sides; candidate
      t at column c is ``bwd[t mod S, :, BL + c - floor(t / S)]`` (the backward kernel
      vectorises over window columns).

    Window statistics are per phase too, shifted by index: ``stat_sum``, ``stat_inv`` (float32)
    and ``stat_unk`` (uint8, 1 outside) are (H, SL + Ws S + SR) in the interleaved reversed
    layout. The torch refinement's per-candidate arrays ((H + 2h, Wr, C) candidates and
    (H, Ws, C) statistics) are built only when that path runs (:meth:`torch_candidates`).
    """

    r0_int: torch.Tensor  # (H + 2h, Wr) float32, phase 0, normalised, unknown -> 0 (integer stage)
    rs_int: torch.Tensor  # (H, Ws) window sums of r0_int
    inv_int: torch.Tensor  # (H, Ws) 1 / window std of r0_int (0 where unknown)
    pen_int: torch.Tensor  # (H, Ws) 0, or _EXCLUDED_INT where the window touches unknown reference
    filled: torch.Tensor  # (S, H + 2h, Wr) normalised phases, unknown -> 0 (a view of ``bwd`` on the C path)
    phase_stats: tuple | None  # (sum, 1/std, unknown) per phase, (S, H, Ws); None on the C path
    S: int
    T: int
    block: int
    offset: int  # extended column index = reference column j + offset
    n_cand: int
    fwd: torch.Tensor | None = None
    fwd_base: int = 0
    fwd_strides: tuple = (0, 8)  # (column, vector) strides in floats, see the C kernel
    bwd: torch.Tensor | None = None
    bwd_left: int = 0
    stat_sum: torch.Tensor | None = None
    stat_inv: torch.Tensor | None = None
    stat_unk: torch.Tensor | None = None
    stat_base: int = 0
    _torch: tuple | None = None

    @property
    def n_cand_padded(self) -> int:
        return -(-self.n_cand // 8) * 8

    def _stats(self):
        """Per-phase window statistics (S, H, Ws): stored, or read back from the C layout."""
        if self.phase_stats is not None:
            return self.phase_stats
        S, T = self.S, self.T
        ws = self.filled.shape[-1] - self.block + 1
        lo = self.stat_base + T - (ws - 1) * S  # element of column ws - 1, phase 0

        def back(x):
            return x[:, lo : lo + ws * S].view(x.shape[0], ws, S).flip(1).permute(2, 0, 1)

        return back(self.stat_sum), back(self.stat_inv), back(self.stat_unk).bool()

    def torch_candidates(self):
        """(cand (H + 2h, Wr, C), cand_sum, cand_inv, cand_unknown (H, Ws, C)) for the torch
        refinement; built on first use (cached with the reference unless it needs grad)."""
        if self._torch is not None:
            return self._torch
        S, T = self.S, self.T
        psum, pinv, punk = self._stats()

        def shifted(x, fill, dim):
            return torch.stack([_shift_cols(x[t % S], t // S, fill) for t in range(-T, T + 1)], dim=dim)

        cand = shifted(self.filled, 0.0, -1).contiguous()  # (H + 2h, Wr, C)
        csum, cinv, cunk = (shifted(x, f, -1).contiguous() for x, f in ((psum, 0.0), (pinv, 0.0), (punk, True)))
        out = (cand, csum, cinv, cunk)
        if not self.filled.requires_grad:
            self._torch = out
        return out


def _interleave_reversed(rows: int, width: int, S: int, left: int, right: int, dtype, fill=0) -> tuple:
    """An (rows, left + width S + right) buffer filled with ``fill`` and its (rows, width, S)
    view of the middle in reversed column order: ``view[:, c, s]`` is element
    ``left + (width - 1 - c) S + s``; write ``x.flip(-1)`` into ``view[:, :, s]``."""
    buf = torch.full((rows, left + width * S + right), fill, dtype=dtype)
    return buf, buf[:, left : left + width * S].view(rows, width, S)


_REF_CACHE: dict = {}
_REF_LOCK = threading.Lock()


def _prepare_reference(phases: torch.Tensor, pad: int, block: int, n_sub: int, extra: int) -> _Reference:
    key = None
    if not phases.requires_grad:
        key = (phases.data_ptr(), phases._version, tuple(phases.shape), phases.dtype, str(phases.device),
               pad, block, n_sub, extra)  # fmt: skip
        with _REF_LOCK:
            hit = _REF_CACHE.get(key)
        if hit is not None and hit[0]() is phases:
            return hit[1]
    with _REF_LOCK:
        if key is not None:
            _REF_CACHE.clear()  # one sensor at a time is the common case: free the old one first
    ref = _build_reference(phases, pad, block, n_sub, extra)
    if key is not None:
        with _REF_LOCK:
            _REF_CACHE.clear()  # one sensor at a time is the common case; keep memory flat
            _REF_CACHE[key] = (weakref.ref(phases), ref)
    return ref


def _build_reference(phases: torch.Tensor, pad: int, block: int, n_sub: int, extra: int) -> _Reference:
    h = block // 2
    n = block * block
    S = 2**n_sub
    T = S + S // 2  # candidates K +- 1.5 px: the soft-argmax window is not truncated near the peak
    finite = phases[torch.isfinite(phases)]
    if finite.numel() < 2:
        raise ValueError("reference_phases has no finite values")
    mean, std = finite.mean(), finite.std().clamp_min(1e-12)  # differentiable if phases need it
    del finite
    floor = VARIANCE_FLOOR * n

    def ext_phase(x):
        """Normalised phase(s) (..., H, W + pad) -> (..., H + 2h, Wr): 1 unknown column on
        the left, ``extra`` on the right, mirrored rows."""
        norm = (x - mean) / std
        left = torch.full_like(norm[..., :1], float("nan"))
        right = torch.full_like(norm[..., :1], float("nan")).expand(*norm.shape[:-1], extra)
        return _pad_rows_reflect(torch.cat([left, norm, right], dim=-1), h)

    def stats(ext):
        unknown = torch.isnan(ext)
        filled = torch.where(unknown, torch.zeros_like(ext), ext)
        psum = _box_sum(filled, block)
        psum2 = _box_sum(filled * filled, block)
        pinv = torch.rsqrt((psum2 - psum * psum / n).clamp_min(0) + floor)
        punk = _box_sum(unknown.to(filled.dtype), block) > 0.5
        return filled, psum, pinv, punk

    with torch.no_grad():
        r0 = ext_phase(phases[0].detach()).float()
        r0_unknown = torch.isnan(r0)
        r0 = torch.where(r0_unknown, torch.zeros_like(r0), r0).contiguous()
        rs = _box_sum(r0, block)
        rs2 = _box_sum(r0 * r0, block)
        inv = torch.rsqrt((rs2 - rs * rs / n).clamp_min(0) + floor)
        r0_bad = _box_sum(r0_unknown.float(), block) > 0.5  # window touches unknown reference
        zero = torch.zeros_like(rs)
        rs = torch.where(r0_bad, zero, rs)
        inv = torch.where(r0_bad, zero, inv)
        penalty = torch.where(r0_bad, torch.full_like(rs, _EXCLUDED_INT), zero)
    common = dict(r0_int=r0, rs_int=rs.contiguous(), inv_int=inv.contiguous(), pen_int=penalty.contiguous(), S=S, T=T,
                  block=block, offset=1, n_cand=2 * T + 1)  # fmt: skip

    if not (phases.device.type == "cpu" and phases.dtype == torch.float32 and not phases.requires_grad):
        # torch refinement only: per-phase arrays (differentiable if the phases need it).
        filled, psum, pinv, punk = stats(ext_phase(phases))
        return _Reference(filled=filled, phase_stats=(psum, pinv, punk), **common)

    # C kernels: the two layouts of the phases and the interleaved statistics, built one phase
    # at a time (no transient of more than a phase or two).
    hp, wr = r0.shape
    H, ws = rs.shape
    cp = -(-(2 * T + 1) // 8) * 8
    # >= T zero elements before the first candidate read, >= cp - T after the last; first
    # candidates (lead - T + c S) and rows 32-byte aligned where S allows (S >= 8: all columns).
    lead = T + 8
    tail = {w: cp + 8 + (-(lead + w * S + cp + 8)) % 8 for w in (wr, ws)}
    fwd, fwd_v = _interleave_reversed(hp, wr, S, lead, tail[wr], torch.float32)
    ssum, ssum_v = _interleave_reversed(H, ws, S, lead, tail[ws], torch.float32)
    sinv, sinv_v = _interleave_reversed(H, ws, S, lead, tail[ws], torch.float32)
    sunk, sunk_v = _interleave_reversed(H, ws, S, lead, tail[ws], torch.uint8, fill=1)
    b_left, b_right = 8, 16  # shifts floor(t / S) in [-2, 1]; the kernel reads 8-column vectors
    bwd = torch.zeros(S, hp, b_left + wr + b_right, dtype=torch.float32)
    with torch.no_grad():
        for s in range(S):
            filled, psum, pinv, punk = stats(ext_phase(phases[s]))
            bwd[s, :, b_left : b_left + wr] = filled
            fwd_v[:, :, s] = filled.flip(-1)
            ssum_v[:, :, s] = psum.flip(-1)
            sinv_v[:, :, s] = pinv.flip(-1)
            sunk_v[:, :, s] = punk.flip(-1)
    fwd_base, fwd_strides = lead + (wr - 1) * S - T, (S, 8)
    if S < 8:  # the first 8 candidates of each column (8 / S copies of the phases): aligned vectors
        step = 8 // S
        fwd = fwd[:, lead - T :].unfold(1, 8, S)[:, : wr + (cp // 8 - 1) * step].contiguous().view(hp, -1)
        fwd_base, fwd_strides = (wr - 1) * 8, (8, 8 * step)
    return _Reference(
        filled=bwd[:, :, b_left : b_left + wr], phase_stats=None, fwd=fwd, fwd_base=fwd_base, fwd_strides=fwd_strides,
        bwd=bwd,
        bwd_left=b_left, stat_sum=ssum, stat_inv=sinv, stat_unk=sunk, stat_base=lead + (ws - 1) * S - T, **common,
    )  # fmt: skip


# --------------------------------------------------------------------------------------
# Stage 1: integer search (C kernel, torch fallback)
# --------------------------------------------------------------------------------------
_C_SOURCE = r"""/* Integer-disparity ZNCC search for ddsgen's block matcher (no gradient needed here).
 *
 * For every output pixel (v, u) and candidate c = 0..D-1 (integer disparity k = k_hi - c):
 *   cross(v, u, c) = sum_{i<b, j<b} O[v+i][u+j] * R[v+i][u+j + r0 + c]
 *   score          = (cross - OS[v][u] * RS[v][u+r0+c] / n) * invO[v][u] * invR[v][u+r0+c] + PEN[v][u+r0+c]
 * O is the row/column padded observed image, R the row padded reference (phase 0, unknown
 * values zeroed), PEN is 0 where the reference window is known and -1e30 where it is not.
 * Window sums are running sums (vertical ones restarted every ROW_BLOCK rows, so the result
 * is independent of the thread count). Outputs per pixel: best score, the best score at least 2 candidates away from the
 * best (the "second peak"), and the best candidate index (-1 if every candidate is
 * excluded). Arrays R, RS, invR, PEN must have 7 readable columns beyond candidate D - 1.
 */
#include <stddef.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>
#include <math.h>

typedef float v8 __attribute__((vector_size(32)));
typedef float v8u __attribute__((vector_size(32), aligned(4)));
#define LOADU(p) (*(const v8u *)(p))
#define NEG_BIG (-1e30f)
#define ROW_BLOCK 32

static inline float hmax8(v8 m) {
    float r = m[0];
    for (int k = 1; k < 8; k++) r = m[k] > r ? m[k] : r;
    return r;
}

typedef int32_t vi8 __attribute__((vector_size(32)));
typedef uint8_t vu8 __attribute__((vector_size(8)));

static inline v8 vsel8(vi8 mask, v8 a, v8 b) { /* mask ? a : b, lane-wise */
    return (v8)((mask & (vi8)a) | (~mask & (vi8)b));
}

static inline v8 vmax8(v8 a, v8 b) { return vsel8(a > b, a, b); }

void ddsgen_zncc_search(const float *restrict O, int Wo,
                        const float *restrict R, int Wr,
                        const float *restrict OS, const float *restrict invO,
                        const float *restrict RS, const float *restrict invR,
                        const float *restrict PEN, int Ws,
                        int H, int W, int b, int r0, int D,
                        float *restrict best_out, float *restrict second_out,
                        int32_t *restrict arg_out, int n_threads)
{
    const float inv_n = 1.0f / (float)(b * b);
    const int Wv = W + b - 1;
    const int nb = (D + 7) / 8;
    const int Dp = nb * 8;
#pragma omp parallel num_threads(n_threads)
    {
        v8 *V = (v8 *)aligned_alloc(32, sizeof(v8) * (size_t)Wv * nb);
        v8 *S = (v8 *)aligned_alloc(32, sizeof(v8) * (size_t)nb);
        v8 *SC = (v8 *)aligned_alloc(32, sizeof(v8) * (size_t)nb);
        v8 *TAIL = (v8 *)aligned_alloc(32, sizeof(v8) * (size_t)nb);
        float *tail = (float *)TAIL;
        for (int c = 0; c < Dp; c++) tail[c] = c < D ? 0.0f : NEG_BIG;
        /* Rows are processed in fixed blocks of ROW_BLOCK: the vertical window sums are
           computed in full at a block's first row and then updated incrementally, so the
           result depends on neither the thread count nor the caller's band split. */
#pragma omp for schedule(dynamic, 1)
        for (int blk = 0; blk < (H + ROW_BLOCK - 1) / ROW_BLOCK; blk++)
        for (int v = blk * ROW_BLOCK; v < H && v < (blk + 1) * ROW_BLOCK; v++) {
            if (v == blk * ROW_BLOCK) {
                for (int x = 0; x < Wv; x++) {
                    v8 *Vx = V + (size_t)x * nb;
                    for (int q = 0; q < nb; q++) Vx[q] = (v8){0, 0, 0, 0, 0, 0, 0, 0};
                    for (int i = 0; i < b; i++) {
                        const float oi = O[(size_t)(v + i) * Wo + x];
                        const float *ri = R + (size_t)(v + i) * Wr + r0 + x;
                        for (int q = 0; q < nb; q++) Vx[q] += oi * LOADU(ri + 8 * q);
                    }
                }
            } else {
                const float *onew = O + (size_t)(v + b - 1) * Wo, *oold = O + (size_t)(v - 1) * Wo;
                const float *rnew = R + (size_t)(v + b - 1) * Wr + r0, *rold = R + (size_t)(v - 1) * Wr + r0;
                for (int x = 0; x < Wv; x++) {
                    v8 *Vx = V + (size_t)x * nb;
                    const float on = onew[x], oo = oold[x];
                    for (int q = 0; q < nb; q++)
                        Vx[q] += on * LOADU(rnew + x + 8 * q) - oo * LOADU(rold + x + 8 * q);
                }
            }
            /* horizontal running window sums */
            for (int q = 0; q < nb; q++) {
                v8 acc = V[q];
                for (int j = 1; j < b; j++) acc += V[(size_t)j * nb + q];
                S[q] = acc;
            }
            for (int u = 0; u < W; u++) {
                const float os = OS[(size_t)v * W + u] * inv_n;
                const float io = invO[(size_t)v * W + u];
                const size_t base = (size_t)v * Ws + u + r0;
                v8 m = {NEG_BIG, NEG_BIG, NEG_BIG, NEG_BIG, NEG_BIG, NEG_BIG, NEG_BIG, NEG_BIG};
                vi8 mi = {0, 0, 0, 0, 0, 0, 0, 0};
                vi8 ci = {0, 1, 2, 3, 4, 5, 6, 7};
                for (int q = 0; q < nb; q++) {
                    v8 sc = (S[q] - os * LOADU(RS + base + 8 * q)) * (io * LOADU(invR + base + 8 * q))
                            + LOADU(PEN + base + 8 * q) + TAIL[q];
                    SC[q] = sc;
                    vi8 gt = sc > m;
                    m = vsel8(gt, sc, m);
                    mi = (gt & ci) | (~gt & mi);
                    ci += 8;
                }
                /* lowest index among the lanes holding the maximum */
                float best = m[0];
                int arg = mi[0];
                for (int k = 1; k < 8; k++) {
                    if (m[k] > best || (m[k] == best && mi[k] < arg)) { best = m[k]; arg = mi[k]; }
                }
                if (!(best > 0.5f * NEG_BIG)) arg = -1;
                float second = -2.0f;
                if (arg >= 0) {
                    float *scw = (float *)SC;  /* exclude the best peak itself (+-1 candidate) */
                    for (int c = arg - 1; c <= arg + 1; c++) {
                        if (c >= 0 && c < Dp) scw[c] = NEG_BIG;
                    }
                    v8 m2 = {NEG_BIG, NEG_BIG, NEG_BIG, NEG_BIG, NEG_BIG, NEG_BIG, NEG_BIG, NEG_BIG};
                    for (int q = 0; q < nb; q++) m2 = vmax8(m2, SC[q]);
                    float s2 = hmax8(m2);
                    if (s2 > second) second = s2;
                }
                best_out[(size_t)v * W + u] = arg >= 0 ? best : -2.0f;
                second_out[(size_t)v * W + u] = second;
                arg_out[(size_t)v * W + u] = arg;
                if (u + 1 < W) {
                    const v8 *add = V + (size_t)(u + b) * nb;
                    const v8 *sub = V + (size_t)u * nb;
                    for (int q = 0; q < nb; q++) S[q] += add[q] - sub[q];
                }
            }
        }
        free(V);
        free(S);
        free(SC);
        free(TAIL);
    }
}


/* Vector exp for x <= 0 (Cephes expf: range reduction by ln 2, degree-6 polynomial, exponent
 * bits; relative error ~1e-7). Inputs below -87 give 2^-126 (callers only use x >= -87 as
 * weights next to exp(0) = 1, where that is far below float resolution). */
static inline v8 vexp8(v8 x) {
    const v8 lo = {-87.0f, -87.0f, -87.0f, -87.0f, -87.0f, -87.0f, -87.0f, -87.0f};
    x = vmax8(x, lo);
    v8 t = x * 1.44269504088896341f + 0.5f;
    vi8 n = __builtin_convertvector(t, vi8);  /* truncation; floor for negative t below */
    v8 nf = __builtin_convertvector(n, v8);
    vi8 gt = nf > t;
    n += gt;  /* gt is -1 where nf > t */
    nf = __builtin_convertvector(n, v8);
    v8 r = x - nf * 0.693359375f - nf * -2.12194440e-4f;
    v8 y = 1.9875691500e-4f * r + 1.3981999507e-3f;
    y = y * r + 8.3334519073e-3f;
    y = y * r + 4.1665795894e-2f;
    y = y * r + 1.6666665459e-1f;
    y = y * r + 5.0000001201e-1f;
    y = y * (r * r) + r + 1.0f;
    vi8 scale = (n + 127) << 23;
    return y * (v8)scale;
}

/* Observed-image window statistics. X is the (H, W) normalised observed image; writes the
 * mirrored (no edge repeat) padded image Opad (H + b - 1, W + b - 1), and per output pixel the
 * window sums OSUM = sum Opad, OINV = 1 / sqrt(max(sum Opad^2 - OSUM^2 / n, 0) + floor) over
 * b x b windows (sums in double: running along each padded row, then direct over the b rows,
 * so every value is computed in a fixed order, whatever the thread count). RS, RS2 are
 * scratch of (H + b - 1) x W doubles. */
static inline int mirror(int i, int n) { return i < 0 ? -i : (i >= n ? 2 * n - 2 - i : i); }

void ddsgen_observed_stats(const float *restrict X, int H, int W, int b, float floor_, float *restrict Opad,
                           float *restrict OSUM, float *restrict OINV, double *restrict RS,
                           double *restrict RS2, int n_threads)
{
    const int h = b / 2, Hp = H + b - 1, Wp = W + b - 1;
    const float nf = (float)(b * b);
#pragma omp parallel num_threads(n_threads)
    {
#pragma omp for schedule(static)
        for (int y = 0; y < Hp; y++) {
            const float *restrict x = X + (size_t)mirror(y - h, H) * W;
            float *restrict o = Opad + (size_t)y * Wp;
            for (int c = 0; c < Wp; c++) o[c] = x[mirror(c - h, W)];
            double s = 0.0, s2 = 0.0;
            for (int j = 0; j < b; j++) {
                s += (double)o[j];
                s2 += (double)(o[j] * o[j]);
            }
            double *restrict rs = RS + (size_t)y * W, *restrict rs2 = RS2 + (size_t)y * W;
            rs[0] = s;
            rs2[0] = s2;
            for (int u = 1; u < W; u++) {
                const float a = o[u + b - 1], d = o[u - 1];
                s += (double)a - (double)d;
                s2 += (double)(a * a) - (double)(d * d);
                rs[u] = s;
                rs2[u] = s2;
            }
        }
#pragma omp for schedule(static)
        for (int v = 0; v < H; v++) {
            for (int u = 0; u < W; u++) {
                double s = 0.0, s2 = 0.0;
                for (int i = 0; i < b; i++) {
                    s += RS[(size_t)(v + i) * W + u];
                    s2 += RS2[(size_t)(v + i) * W + u];
                }
                const float os = (float)s, os2 = (float)s2;
                float var = os2 - os * os / nf;
                var = var > 0.0f ? var : 0.0f;
                OSUM[(size_t)v * W + u] = os;
                OINV[(size_t)v * W + u] = 1.0f / sqrtf(var + floor_);
            }
        }
    }
}

/* acc[q] = sum_{i<b, j<b} O[v+i][u+j] * FX[v+i][xoff - j CS + q VS .. + 7], q < nq (FX: the
 * candidates of window column j start at xoff - j CS, vector q of them VS floats further;
 * row stride WX). NR window rows are accumulated side by side into separate
 * sums (independent dependency chains: an FMA's latency, not its throughput, would otherwise
 * bound the loop). */
static inline __attribute__((always_inline)) void window_cross(
    const float *restrict O, int Wo, const float *restrict FX, size_t WX, ptrdiff_t xoff, int CS, int VS, int v,
    int u, int b, v8 *restrict out, const int nq, const int NR)
{
    v8 acc[4][8];
    for (int r = 0; r < NR; r++)
        for (int q = 0; q < nq; q++) acc[r][q] = (v8){0, 0, 0, 0, 0, 0, 0, 0};
    int i = 0;
    for (; i + NR <= b; i += NR) {
        const float *restrict o[4];
        const float *f[4];
        for (int r = 0; r < NR; r++) {
            o[r] = O + (size_t)(v + i + r) * Wo + u;
            f[r] = FX + (size_t)(v + i + r) * WX + xoff;
        }
        for (int j = 0; j < b; j++)
            for (int r = 0; r < NR; r++) {
                const float oj = o[r][j];
                const float *fj = f[r] - (ptrdiff_t)j * CS;
                for (int q = 0; q < nq; q++) acc[r][q] += oj * LOADU(fj + (ptrdiff_t)q * VS);
            }
    }
    for (; i < b; i++) {
        const float *restrict o = O + (size_t)(v + i) * Wo + u;
        const float *f = FX + (size_t)(v + i) * WX + xoff;
        for (int j = 0; j < b; j++) {
            const float oj = o[j];
            const float *fj = f - (ptrdiff_t)j * CS;
            for (int q = 0; q < nq; q++) acc[0][q] += oj * LOADU(fj + (ptrdiff_t)q * VS);
        }
    }
    for (int q = 0; q < nq; q++) {
        v8 s = acc[0][q];
        for (int r = 1; r < NR; r++) s += acc[r][q];
        out[q] = s;
    }
}

static inline float hsum8(v8 x) {
    float r = 0.0f;
    for (int k = 0; k < 8; k++) r += x[k];
    return r;
}

typedef struct {
    const float *O; int Wo; const float *FX; size_t WX; ptrdiff_t XB; int XCS; int XVS; int S; int C; int CP;
    const int32_t *K; int col_shift; int v0; int W; int b;
    const float *CSUM; const float *CINV; const uint8_t *CUNK; size_t WS; ptrdiff_t SB;
    const float *OSUM; const float *OINV; float beta; float d_lo; float d_hi;
    float *disp; const float *GD; float *G; float *dOSUM; float *dOINV; float *dBETA;
    v8 OFF[8]; vi8 PADL[8];  /* candidate offsets (t - T) / S; -1 in lanes t >= C */
} refine_args;

/* One row v of ddsgen_refine, with constant nq = CP / 8 (accumulators in registers). */
static inline __attribute__((always_inline)) void refine_row(const refine_args *A, int v, const int nq, const int NR)
{
    const v8 m3 = {-3.0f, -3.0f, -3.0f, -3.0f, -3.0f, -3.0f, -3.0f, -3.0f};
    const v8 zero = {0, 0, 0, 0, 0, 0, 0, 0};
    const v8 vlow = {-3.4e38f, -3.4e38f, -3.4e38f, -3.4e38f, -3.4e38f, -3.4e38f, -3.4e38f, -3.4e38f};
    const float nf = (float)(A->b * A->b), beta = A->beta;
    for (int u = 0; u < A->W; u++) {
        const size_t p = (size_t)v * A->W + u;
        const int k = A->K[p];
        const int c0 = u + A->col_shift - k;
        v8 cr[8], z[8], e[8];
        vi8 ex[8];
        window_cross(A->O, A->Wo, A->FX, A->WX, A->XB - (ptrdiff_t)c0 * A->XCS, A->XCS, A->XVS, v, u, A->b, cr, nq, NR);
        const float a = A->OSUM[p] / nf, io = A->OINV[p];
        const size_t s = (size_t)v * A->WS + (size_t)(A->SB - (ptrdiff_t)c0 * A->S);
        const float *cs = A->CSUM + s, *ci = A->CINV + s;  /* read 8 nq floats: arrays have slack */
        const uint8_t *cu = A->CUNK + s;
        const float kf = (float)k;
        v8 mv = vlow;
        for (int q = 0; q < nq; q++) {
            const v8 dt = kf + A->OFF[q];
            vi8 x = (dt < A->d_lo) | (dt > A->d_hi) | A->PADL[q];
            vu8 unk;
            memcpy(&unk, cu + 8 * q, 8);
            x |= __builtin_convertvector(unk, vi8) != 0;
            const v8 zz = vsel8(x, m3, ((cr[q] - a * LOADU(cs + 8 * q)) * io) * LOADU(ci + 8 * q));
            z[q] = zz;
            ex[q] = x;
            e[q] = vsel8(A->PADL[q], vlow, beta * zz);
            mv = vmax8(mv, e[q]);
        }
        const float m = hmax8(mv);
        v8 se_v = zero, so_v = zero;
        for (int q = 0; q < nq; q++) {
            e[q] = vsel8(A->PADL[q], zero, vexp8(e[q] - m));
            se_v += e[q];
            so_v += e[q] * A->OFF[q];
        }
        const float se = hsum8(se_v), delta = hsum8(so_v) / se;
        if (!A->GD) {
            A->disp[p] = kf + delta;
            continue;
        }
        const float g = A->GD[p];
        v8 *gp = (v8 *)(A->G + ((size_t)(v - A->v0) * A->W + u) * A->CP);
        v8 db = zero, dos = zero, doi = zero;
        for (int q = 0; q < nq; q++) {
            const v8 dl = g * (e[q] / se) * (A->OFF[q] - delta);
            db += dl * z[q];
            const v8 dz = vsel8(ex[q], zero, dl * beta);
            const v8 c_i = LOADU(ci + 8 * q), c_s = LOADU(cs + 8 * q);
            const v8 gt = vsel8(ex[q], zero, dz * io * c_i);  /* (garbage lanes: excluded) */
            gp[q] = gt;
            dos -= vsel8(ex[q], zero, gt * c_s / nf);
            doi += vsel8(ex[q], zero, dz * (cr[q] - a * c_s) * c_i);
        }
        A->dOSUM[p] = hsum8(dos);
        A->dOINV[p] = hsum8(doi);
        A->dBETA[p] = hsum8(db);
    }
}

/* Sub-pixel refinement, fused (no cost volume is written). For each pixel (v, u) of rows
 * [v0, v1) with integer disparity k = K[v][u] and candidates t = 0..C-1 (d_t = k + (t - T)/S,
 * T = (C - 1) / 2), window start column c0 = u + col_shift - k:
 *   cross_t = sum_{i<b, j<b} O[v+i][u+j] * F[v+i][c0 + j][t],
 *             F[y][c][8q + l] = FX[y][XB - c XCS + q XVS + l]
 *   z_t     = ((cross_t - OSUM/n * CSUM_t) * OINV) * CINV_t, or -3 if excluded (CUNK, or d_t
 *             outside [d_lo, d_hi])
 *   d       = k + sum_t e_t (t - T)/S / sum_t e_t,  e_t = exp(beta z_t - max beta z)
 * Candidate t of column c is phase (t - T) mod S, shifted by floor((t - T) / S) columns; FX
 * holds the S phases interleaved in reversed column order (XCS = S, XVS = 8: the C candidates
 * of a column are contiguous), or for S < 8 the first 8 candidates of every column (XCS = 8,
 * XVS = 64 / S: vector q of column c is vector 0 of column c - 8q / S), so that vectors are
 * 32-byte aligned; no per-candidate copy exists. CP (a multiple of 8, at most 64) values are
 * read per column. CSUM, CINV, CUNK (row stride WS) are the phases' window
 * statistics in the same layout: candidate t of window start column c is [v][SB - c S + t].
 * All arrays have zero (CUNK: 1) elements around the phases for the reads that fall outside. Forward (GD == NULL): writes disp[v][u]. Backward (GD given): recomputes
 * the same and writes, for dL/dd = GD[v][u], the gradients w.r.t. cross_t into
 * G[(v - v0)][u][t] (band-local, CP per pixel, 0 in padding lanes), w.r.t. OSUM, OINV into
 * dOSUM, dOINV and the pixel's contribution to dL/dbeta into dBETA (all H x W). Every pixel is
 * computed on its own, in a fixed order: results depend neither on the thread count nor on the
 * band split. */
void ddsgen_refine(const float *restrict O, int Wo, const float *restrict FX, int64_t WX, int64_t XB, int XCS, int XVS,
                   int C, int CP,
                   const int32_t *restrict K, int col_shift, int v0, int v1, int W, int b,
                   const float *restrict CSUM, const float *restrict CINV, const uint8_t *restrict CUNK, int64_t WS,
                   int64_t SB,
                   const float *restrict OSUM, const float *restrict OINV, float beta, int S,
                   float d_lo, float d_hi, float *restrict disp,
                   const float *restrict GD, float *restrict G, float *restrict dOSUM,
                   float *restrict dOINV, float *restrict dBETA, int n_threads)
{
    refine_args A = {O, Wo, FX, (size_t)WX, (ptrdiff_t)XB, XCS, XVS, S, C, CP, K, col_shift, v0, W, b, CSUM, CINV, CUNK,
                     (size_t)WS, (ptrdiff_t)SB, OSUM, OINV, beta, d_lo, d_hi, disp, GD, G, dOSUM, dOINV, dBETA};
    const int T = (C - 1) / 2;
    for (int t = 0; t < 64; t++) {
        A.OFF[t / 8][t % 8] = (float)(t - T) / (float)S;
        A.PADL[t / 8][t % 8] = t < C ? 0 : -1;
    }
    const int nq = CP / 8;
#pragma omp parallel for schedule(dynamic, 4) num_threads(n_threads)
    for (int v = v0; v < v1; v++) {
        switch (nq) {  /* constant trip counts: the accumulators stay in registers */
        case 1: if (b % 3 == 0) refine_row(&A, v, 1, 3); else refine_row(&A, v, 1, 4); break;
        case 2: if (b % 3 == 0) refine_row(&A, v, 2, 3); else refine_row(&A, v, 2, 4); break;
        case 3: refine_row(&A, v, 3, 2); break;
        case 4: refine_row(&A, v, 4, 2); break;
        case 5: refine_row(&A, v, 5, 1); break;
        case 6: refine_row(&A, v, 6, 1); break;
        case 7: refine_row(&A, v, 7, 1); break;
        default: refine_row(&A, v, 8, 1); break;
        }
    }
}

/* acc[q] = sum_t g[t] * ft[toff[t] + 8q .. 8q + 7], q < nbq; NR candidates side by side
 * into separate sums (independent dependency chains). */
static inline __attribute__((always_inline)) void cross_grad(
    const float *restrict g, const float *restrict ft, const ptrdiff_t *restrict toff, int C, v8 *restrict out,
    const int nbq, const int NR)
{
    v8 acc[4][8];
    for (int r = 0; r < NR; r++)
        for (int q = 0; q < nbq; q++) acc[r][q] = (v8){0, 0, 0, 0, 0, 0, 0, 0};
    int t = 0;
    for (; t + NR <= C; t += NR)
        for (int r = 0; r < NR; r++) {
            const float gt = g[t + r];
            const float *restrict f = ft + toff[t + r];
            for (int q = 0; q < nbq; q++) acc[r][q] += gt * LOADU(f + 8 * q);
        }
    for (; t < C; t++) {
        const float gt = g[t];
        const float *restrict f = ft + toff[t];
        for (int q = 0; q < nbq; q++) acc[0][q] += gt * LOADU(f + 8 * q);
    }
    for (int q = 0; q < nbq; q++) {
        v8 s = acc[0][q];
        for (int r = 1; r < NR; r++) s += acc[r][q];
        out[q] = s;
    }
}

/* Backward of the window cross-correlation w.r.t. O, for the band of rows [v0, v1): adds
 *   dO[y][u+j] += sum_t G[v - v0][u][t] * FT[t][y][c0 + j]   (G: CG floats per pixel)   for v = y - i in [v0, v1), all u, j
 * (c0 = u + col_shift - K[v][u]), where FT[t][y][c] = P[s][y][PL + c - q] for candidate t - T
 * = q S + s (0 <= s < S): P holds the S phases (S x Hp x WP) with PL zero columns on the left,
 * and is readable 7 columns beyond the last window column of every shift. Each row y is owned by one thread (no races,
 * deterministic). Bands are called in order and each dO element receives its terms in order
 * of (v, u) whatever the band split, so the result is bit-identical for any split. */
void ddsgen_window_cross_grad(const float *restrict G, int CG, const float *restrict P, int WP, int PL, int Hp,
                              int S, int C, const int32_t *restrict K, int col_shift, int v0, int v1, int W,
                              int b, float *restrict dO, int Wo, int n_threads)
{
    const int nbq = (b + 7) / 8;
    const int T = (C - 1) / 2;
    ptrdiff_t toff[64];  /* element offset of candidate t from P[0][y][c0] */
    for (int t = 0; t < C && t < 64; t++) {
        const int tt = t - T;
        const int q = tt >= 0 ? tt / S : -((-tt + S - 1) / S);
        const int s = tt - q * S;
        toff[t] = (ptrdiff_t)s * Hp * WP + PL - q;
    }
#pragma omp parallel num_threads(n_threads)
    {
        v8 acc[8];
#pragma omp for schedule(dynamic, 4)
        for (int y = v0; y < v1 + b - 1; y++) {
            float *restrict drow = dO + (size_t)y * Wo;
            for (int i = b - 1; i >= 0; i--) {  /* v ascending, as across bands: every dO */
                const int v = y - i;                /* element sums its terms in the same order */
                if (v < v0 || v >= v1) continue;
                for (int u = 0; u < W; u++) {
                    const float *restrict g = G + ((size_t)(v - v0) * W + u) * CG;
                    const int c0 = u + col_shift - K[(size_t)v * W + u];
                    const float *restrict ft = P + (size_t)y * WP + c0;
                    switch (nbq) {  /* constant trip counts: the accumulators stay in registers */
                    case 1: cross_grad(g, ft, toff, C, acc, 1, 4); break;
                    case 2: cross_grad(g, ft, toff, C, acc, 2, 4); break;
                    case 3: cross_grad(g, ft, toff, C, acc, 3, 2); break;
                    case 4: cross_grad(g, ft, toff, C, acc, 4, 2); break;
                    case 5: cross_grad(g, ft, toff, C, acc, 5, 1); break;
                    case 6: cross_grad(g, ft, toff, C, acc, 6, 1); break;
                    case 7: cross_grad(g, ft, toff, C, acc, 7, 1); break;
                    default: cross_grad(g, ft, toff, C, acc, 8, 1); break;
                    }
                    const float *restrict sv = (const float *)acc;
                    float *restrict d = drow + u;
                    for (int j = 0; j < b; j++) d[j] += sv[j];  /* scalar: store-forwarding friendly */
                }
            }
        }
    }
}
"""

_KERNEL = None
_KERNEL_TRIED = False
_KERNEL_LOCK = threading.Lock()


def _cpu_tag() -> str:
    try:
        with open("/proc/cpuinfo", encoding="utf-8", errors="replace") as handle:
            for line in handle:
                if line.startswith("flags"):
                    return line
    except OSError:
        pass
    return platform.processor() or platform.machine()


def _load_kernel():
    """Compile (once, cached in the project cache) and load the C integer-search kernel.
    Returns None when no C compiler/OpenMP is available (then torch does the work)."""
    global _KERNEL, _KERNEL_TRIED
    with _KERNEL_LOCK:
        if _KERNEL_TRIED:
            return _KERNEL
        _KERNEL_TRIED = True
        if os.environ.get("DDSGEN_NO_C_KERNEL"):
            return None
        from ddsgen.cache import cache_dir

        compiler = os.environ.get("CC", "cc")
        flags = ["-O3", "-march=native", "-fopenmp", "-fPIC", "-shared", "-std=gnu11"]
        digest = hashlib.sha256("\n".join([_C_SOURCE, compiler, *flags, _cpu_tag()]).encode()).hexdigest()[:16]
        folder = cache_dir() / "kernels"
        lib_path = folder / f"zncc_{digest}.so"
        try:
            if not lib_path.exists():
                folder.mkdir(parents=True, exist_ok=True)
                with tempfile.TemporaryDirectory(dir=folder) as tmp:
                    src = Path(tmp) / "zncc.c"
                    src.write_text(_C_SOURCE)
                    out = Path(tmp) / "zncc.so"
                    subprocess.run([compiler, *flags, str(src), "-o", str(out), "-lm"],
                                   check=True, capture_output=True, timeout=120)  # fmt: skip
                    os.replace(out, lib_path)  # atomic: concurrent workers never see half a file
            lib = ctypes.CDLL(str(lib_path))
            p, i = ctypes.c_void_p, ctypes.c_int
            lib.ddsgen_zncc_search.argtypes = [p, i, p, i, p, p, p, p, p, i, i, i, i, i, i, p, p, p, i]
            f = ctypes.c_float
            q = ctypes.c_int64
            lib.ddsgen_refine.argtypes = [p, i, p, q, q, i, i, i, i, p, i, i, i, i, i, p, p, p, q, q, p, p, f, i, f, f,
                                          p, p, p, p, p, p, i]  # fmt: skip
            lib.ddsgen_observed_stats.argtypes = [p, i, i, i, f, p, p, p, p, p, i]
            lib.ddsgen_window_cross_grad.argtypes = [p, i, p, i, i, i, i, i, p, i, i, i, i, i, p, i, i]
            for fn in (lib.ddsgen_zncc_search, lib.ddsgen_refine, lib.ddsgen_window_cross_grad, lib.ddsgen_observed_stats):
                fn.restype = None
            _KERNEL = lib
        except (OSError, subprocess.SubprocessError) as error:
            log.warning("ddsgen matcher: C kernel unavailable (%s); using the torch integer search", error)
            _KERNEL = None
        return _KERNEL


def integer_search_backend(device="cpu") -> str:
    """Which integer-search implementation :func:`match` uses on ``device``: "c" or "torch"."""
    return "c" if torch.device(device).type == "cpu" and _load_kernel() is not None else "torch"


def _integer_search_c(fn, o_pad, ref: _Reference, os_, inv_o, block, r0, n_disp):
    H, W = os_.shape
    o = o_pad.detach().float().contiguous()
    osum, oinv = os_.detach().float().contiguous(), inv_o.detach().float().contiguous()
    best = torch.empty(H, W, dtype=torch.float32)
    second = torch.empty(H, W, dtype=torch.float32)
    arg = torch.empty(H, W, dtype=torch.int32)
    fn.ddsgen_zncc_search(o.data_ptr(), o.shape[1], ref.r0_int.data_ptr(), ref.r0_int.shape[1], osum.data_ptr(), oinv.data_ptr(),
       ref.rs_int.data_ptr(), ref.inv_int.data_ptr(), ref.pen_int.data_ptr(), ref.rs_int.shape[1], H, W, block, r0, n_disp,
       best.data_ptr(), second.data_ptr(), arg.data_ptr(), max(1, torch.get_num_threads()))  # fmt: skip
    return best, second, arg.long()


def _integer_search_torch(o_pad, ref: _Reference, os_, inv_o, block, r0, n_disp, band_rows):
    """Same as the C kernel, as row bands of a (row, column, disparity) volume."""
    H, W = os_.shape
    n = block * block
    o = o_pad.detach().to(ref.r0_int.dtype)
    best_all, second_all, arg_all = [], [], []
    rows = max(1, min(band_rows, H))
    near = torch.tensor([-1, 0, 1], device=o.device)
    for start in range(0, H, rows):
        stop = min(H, start + rows)
        hb = stop - start
        ob = o[start : stop + block - 1]
        rb = ref.r0_int[start : stop + block - 1]
        ru = rb.unfold(1, n_disp, 1)  # (hb + b - 1, Wr - D + 1, D): zero-copy candidates
        vert = None  # vertical sums at every padded column
        for i in range(block):
            term = ob[i : i + hb, :, None] * ru[i : i + hb, r0 : r0 + W + block - 1, :]
            vert = term if vert is None else vert + term
        cross = vert[:, 0:W]
        for j in range(1, block):
            cross = cross + vert[:, j : j + W]
        rs = ref.rs_int[start:stop].unfold(1, n_disp, 1)[:, r0 : r0 + W]
        ri = ref.inv_int[start:stop].unfold(1, n_disp, 1)[:, r0 : r0 + W]
        pen = ref.pen_int[start:stop].unfold(1, n_disp, 1)[:, r0 : r0 + W]
        score = (cross - (os_[start:stop, :, None] / n) * rs) * inv_o[start:stop, :, None] * ri + pen
        best, arg = score.max(dim=-1)
        peak = (arg[..., None] + near).clamp(0, n_disp - 1)  # the best peak itself (+-1 candidate)
        second = score.scatter_(-1, peak, -2.0).amax(dim=-1).clamp_min(-2.0)
        none = best < 0.5 * _EXCLUDED_INT
        best_all.append(torch.where(none, torch.full_like(best, -2.0), best))
        second_all.append(torch.where(none, torch.full_like(second, -2.0), second))
        arg_all.append(torch.where(none, torch.full_like(arg, -1), arg))
    return torch.cat(best_all).float(), torch.cat(second_all).float(), torch.cat(arg_all)


# --------------------------------------------------------------------------------------
# Stage 2: sub-pixel refinement of one band (differentiable)
# --------------------------------------------------------------------------------------
def _n_threads() -> int:
    return max(1, torch.get_num_threads())


class _RefineC(torch.autograd.Function):
    """Sub-pixel refinement by the fused C kernel ``ddsgen_refine``: window cross-correlations,
    ZNCC and soft-argmax per pixel, without a cost volume. Differentiable w.r.t. the padded
    observed image ``o`` (through the cross-correlations), its window statistics ``osum``,
    ``oinv`` and ``beta``; the backward recomputes each band of ``rows`` rows in C.

    o: (H + b - 1, W + b - 1) float32 normalised padded observed image; osum, oinv: (H, W);
    beta: 0-dim; k: (H, W) int32 integer disparities; ref: the prepared reference (its C
    layouts ``fwd``, ``bwd``, ``stat_sum``, ``stat_inv``, ``stat_unk``). Returns (H, W)."""

    @staticmethod
    def forward(ctx, o, osum, oinv, beta, k, ref, geom):
        lib = _load_kernel()
        o_c, os_c, oi_c = (x.detach().float().contiguous() for x in (o, osum, oinv))
        H, W = k.shape
        disp = torch.empty(H, W, dtype=torch.float32)
        _call_refine(lib, o_c, os_c, oi_c, float(beta.detach()), k, ref, geom, 0, H, disp=disp)
        ctx.save_for_backward(o_c, os_c, oi_c, beta, k)
        ctx.ref, ctx.geom = ref, geom
        return disp

    @staticmethod
    def backward(ctx, grad_disp):
        o_c, os_c, oi_c, beta, k = ctx.saved_tensors
        ref, geom = ctx.ref, ctx.geom
        lib = _load_kernel()
        H, W = k.shape
        C = ref.n_cand
        gd = grad_disp.float().contiguous()
        d_o = torch.zeros_like(o_c)
        d_os, d_oi, d_beta = (torch.empty(H, W, dtype=torch.float32) for _ in range(3))
        rows = geom["rows"]
        g_band = torch.empty(min(rows, H), W, ref.n_cand_padded, dtype=torch.float32)
        bwd = ref.bwd
        for v0 in range(0, H, rows):  # the (rows, W, C) gradient buffer bounds the memory
            v1 = min(H, v0 + rows)
            _call_refine(lib, o_c, os_c, oi_c, float(beta.detach()), k, ref, geom, v0, v1, grad=(gd, g_band, d_os, d_oi, d_beta))  # fmt: skip
            lib.ddsgen_window_cross_grad(g_band.data_ptr(), g_band.shape[2], bwd.data_ptr(), bwd.shape[2], ref.bwd_left,
                                         bwd.shape[1], ref.S, C, k.data_ptr(), geom["col_shift"], v0, v1, W,
                                         geom["block"], d_o.data_ptr(), d_o.shape[1], _n_threads())  # fmt: skip
        d_beta_total = d_beta.double().sum().to(beta.dtype) if ctx.needs_input_grad[3] else None
        return d_o, d_os, d_oi, d_beta_total, None, None, None


def _call_refine(lib, o, osum, oinv, beta: float, k, ref: _Reference, geom: dict, v0: int, v1: int, disp=None, grad=None):
    null = None
    gd, g_band, d_os, d_oi, d_beta = grad if grad is not None else (null,) * 5
    ptr = lambda x: None if x is None else x.data_ptr()  # noqa: E731
    lib.ddsgen_refine(o.data_ptr(), o.shape[1], ref.fwd.data_ptr(), ref.fwd.shape[1], ref.fwd_base, *ref.fwd_strides, ref.n_cand,
                      ref.n_cand_padded, k.data_ptr(), geom["col_shift"], v0, v1, k.shape[1], geom["block"],
                      ref.stat_sum.data_ptr(), ref.stat_inv.data_ptr(), ref.stat_unk.data_ptr(), ref.stat_sum.shape[1],
                      ref.stat_base,
                      osum.data_ptr(), oinv.data_ptr(), beta, geom["S"], geom["d_lo"], geom["d_hi"], ptr(disp),
                      ptr(gd), ptr(g_band), ptr(d_os), ptr(d_oi), ptr(d_beta), _n_threads())  # fmt: skip


def _refine_band(o_band, cand_band, csum_band, cinv_band, cunk_band, osum_band, oinv_band, k_band, beta,
                 block: int, col_shift: int, n_sub: int, d_min: float, d_max: float, soft=None):  # fmt: skip
    """Soft-argmax disparity of one band (torch; the C path uses :class:`_RefineC`).

    o_band: (hb + b - 1, W + b - 1) normalised, padded observed rows of the band.
    cand_band: (hb + b - 1, Wr, C) candidate references of the same rows.
    csum_band, cinv_band, cunk_band: (hb, Ws, C) window statistics of the candidates.
    osum_band, oinv_band: (hb, W) window statistics of the observed image.
    k_band: (hb, W) int64 integer disparity K.
    soft: the soft-argmax (default :func:`_soft_argmax`).
    Returns (hb, W) disparity (not quantised).
    """
    hb, W = k_band.shape
    n_c = csum_band.shape[-1]
    n = block * block
    # Window start column (in extended reference columns) of each pixel's candidates.
    col0 = torch.arange(W, device=k_band.device)[None, :] + col_shift - k_band  # (hb, W)
    row_idx = torch.arange(hb, device=k_band.device)[:, None]
    cross = None
    for i in range(block):  # window rows; each term is an exact per-pixel window product
        seg = cand_band[i : i + hb].unfold(1, block, 1)[row_idx, col0]  # (hb, W, C, b)
        obs = o_band[i : i + hb].unfold(1, block, 1)  # (hb, W, b)
        term = (seg * obs[:, :, None, :]).sum(-1)
        cross = term if cross is None else cross + term
    index = col0[..., None].expand(hb, W, n_c)
    csum = torch.gather(csum_band, 1, index)  # (hb, W, C)
    cinv = torch.gather(cinv_band, 1, index)
    cunk = torch.gather(cunk_band, 1, index)
    return (soft or _soft_argmax)(cross, csum, cinv, cunk, osum_band, oinv_band, k_band, beta,
                                  n=n, n_sub=n_sub, d_min=d_min, d_max=d_max)  # fmt: skip


def _soft_argmax(cross, csum, cinv, cunk, osum, oinv, k, beta, n: int, n_sub: int, d_min: float, d_max: float):
    """ZNCC of each pixel's C candidates (window sums given), then the soft-argmax disparity.
    cross, csum, cinv, cunk: (hb, W, C); osum, oinv: (hb, W); k: (hb, W) int64."""
    n_c = cross.shape[-1]
    T = (n_c - 1) // 2
    S = 2**n_sub
    zncc = (cross - (osum / n)[..., None] * csum) * oinv[..., None] * cinv
    offsets = torch.arange(-T, T + 1, device=k.device, dtype=cross.dtype) / S
    cand_d = k[..., None].to(cross.dtype) + offsets
    excluded = cunk | (cand_d < d_min - 1e-6) | (cand_d > d_max + 1e-6)
    zncc = torch.where(excluded, torch.full_like(zncc, _EXCLUDED_SCORE), zncc)
    logits = beta * zncc
    logits = logits - logits.amax(dim=-1, keepdim=True).detach()  # softmax, written out (faster
    expo = logits.exp()  # than aten's for a last dimension of 3..33 candidates)
    return k.to(cross.dtype) + (expo * offsets).sum(-1) / expo.sum(-1)


_COMPILED = {}
_COMPILE_FAILED = False


def _compiled(fn, compile_mode: bool):
    """``fn`` compiled with torch.compile (cached per function), or ``fn`` itself."""
    if not compile_mode or _COMPILE_FAILED:
        return fn
    if fn not in _COMPILED:
        from ddsgen.cache import configure_torch_compile_cache

        configure_torch_compile_cache()
        _COMPILED[fn] = torch.compile(fn, dynamic=False)
    return _COMPILED[fn]


def _want_compile(device: torch.device, compile: bool | None) -> bool:
    if compile is not None:
        return compile
    if os.environ.get("DDSGEN_NO_COMPILE"):
        return False
    return device.type in ("cpu", "cuda")


# --------------------------------------------------------------------------------------
# The matcher
# --------------------------------------------------------------------------------------
def match(
    observed: torch.Tensor,
    reference_phases: torch.Tensor,
    pad: int,
    d_min: float,
    d_max: float,
    block: int,
    beta,
    n_sub: int,
    band_rows: int = 64,
    min_confidence: float = 0.05,
    *,
    quantize: bool = True,
    compile: bool | None = None,
    backend: str = "auto",
    device=None,
) -> MatchResult:
    """Block-match ``observed`` against the reference: I_o(u, v) ~ R(u - d, v).

    Args:
        observed: (H, W) observed image (IR counts or any intensity; float32 or float64).
        reference_phases: (S, H, W + pad), S = 2^n_sub; column j of phase s holds
            R(j - pad - s/S). NaN marks unknown reference (never matched).
        pad: reference columns left of the image; >= ceil(d_max) + block // 2 + 1.
        d_min, d_max: disparity search range (px), d_max - d_min >= 0.
        block: odd window size w (ZNCC over w x w).
        beta: soft-argmax temperature (float or 0-dim tensor, differentiable).
        n_sub: sub-pixel level (steps of 2^-n_sub px).
        band_rows: rows per band (bounds memory; the result does not depend on it).
        min_confidence: confidence below which a pixel is invalid.
        quantize: quantise the forward value to 2^-n_sub px (straight-through gradient).
        compile: use torch.compile for the torch refinement (default: yes, with eager
            fallback; environment DDSGEN_NO_COMPILE=1 disables it). The C refinement (CPU,
            float32) never compiles.
        backend: integer search "auto" (C kernel on CPU when available), "c" or "torch".
        device: run on this device (inputs are moved); default: ``observed.device``.

    Returns:
        :class:`MatchResult` with (H, W) disparity, confidence, valid.
    """
    if device is not None:
        observed = observed.to(device)
        reference_phases = reference_phases.to(device)
    dev = observed.device
    if observed.ndim != 2:
        raise ValueError(f"observed must be (H, W), got {tuple(observed.shape)}")
    H, W = observed.shape
    S = 2 ** int(n_sub)
    if reference_phases.ndim != 3 or tuple(reference_phases.shape) != (S, H, W + pad):
        raise ValueError(f"reference_phases must be (2^n_sub, H, W + pad) = {(S, H, W + pad)}, "
                         f"got {tuple(reference_phases.shape)}")  # fmt: skip
    block = int(block)
    if block < 1 or block % 2 == 0:
        raise ValueError(f"block must be odd and >= 1, got {block}")
    h = block // 2
    if H <= h or W <= 2 * h:
        raise ValueError(f"image {W}x{H} is too small for block {block}")
    k_lo, k_hi = math.ceil(d_min - 1e-9), math.floor(d_max + 1e-9)
    if k_hi < k_lo:
        raise ValueError(f"empty disparity range [{d_min}, {d_max}]")
    if pad < k_hi + h + 1:
        raise ValueError(f"pad {pad} too small for d_max {d_max} and block {block} (need >= {k_hi + h + 1})")
    dtype = observed.dtype if observed.dtype in (torch.float32, torch.float64) else torch.float32
    observed = observed.to(dtype)
    reference_phases = reference_phases.to(dtype)
    beta = beta if torch.is_tensor(beta) else torch.tensor(float(beta))
    beta = beta.to(device=dev, dtype=dtype)
    n = block * block
    n_disp = k_hi - k_lo + 1

    extra = h + 8 + max(0, -k_lo)  # readable columns right of the image (see the C kernel)
    ref = _prepare_reference(reference_phases, pad, block, int(n_sub), extra)

    # Observed: normalised to zero mean, unit variance (ZNCC is invariant; this makes the
    # variance floor relative and float32 sums well conditioned), mirrored at the borders.
    use_c = backend == "c" or (backend == "auto" and dev.type == "cpu")
    kernel = _load_kernel() if use_c else None
    if backend == "c" and kernel is None:
        raise RuntimeError("C integer-search kernel unavailable")

    # Observed: normalised to zero mean, unit variance (ZNCC is invariant; this makes the
    # variance floor relative and float32 sums well conditioned), mirrored at the borders;
    # window sums and 1 / window std: (H + 2h, W + 2h), (H, W), (H, W).
    x = (observed - observed.mean()) / observed.std().clamp_min(1e-12)
    if kernel is not None and dev.type == "cpu" and dtype == torch.float32:
        o_pad, osum, oinv = _ObservedStatsC.apply(x, block)
    else:
        o_pad, osum, oinv = _observed_stats(x, block)

    # Stage 1: integer search. Window start column for candidate c (k = k_hi - c) at pixel u.
    r0 = pad + ref.offset - h - k_hi
    with torch.no_grad():
        if kernel is not None and dev.type == "cpu":
            best, second, arg = _integer_search_c(kernel, o_pad, ref, osum, oinv, block, r0, n_disp)
        else:
            best, second, arg = _integer_search_torch(o_pad, ref, osum, oinv, block, r0, n_disp, band_rows)
        found = arg >= 0
        k_int = torch.where(found, k_hi - arg, torch.full_like(arg, k_lo))

    # Stage 2: sub-pixel refinement.
    grad = torch.is_grad_enabled() and (observed.requires_grad or beta.requires_grad or reference_phases.requires_grad)
    rows = max(1, min(int(band_rows), H))
    col_shift = pad + ref.offset - h
    use_c_refine = (kernel is not None and dev.type == "cpu" and dtype == torch.float32
                    and ref.fwd is not None and ref.n_cand_padded <= 64 and block <= 64)  # fmt: skip
    if use_c_refine:
        # Fused C kernel: no cost volume, no torch.compile; the backward recomputes bands of
        # `rows` rows in C, so memory is bounded by the band. Results do not depend on `rows`.
        geom = dict(block=block, col_shift=col_shift, S=S, d_lo=float(d_min) - 1e-6, d_hi=float(d_max) + 1e-6,
                    rows=rows)  # fmt: skip
        disparity = _RefineC.apply(o_pad, osum, oinv, beta, k_int.to(torch.int32).contiguous(), ref, geom)
    else:
        # torch: bands of equal height (uniform shapes for the compiled kernel), each
        # recomputed in the backward pass (checkpointing).
        fn = _compiled(_refine_band, _want_compile(dev, compile))
        cand, cand_sum, cand_inv, cand_unknown = ref.torch_candidates()
        pieces = []
        done = 0
        while done < H:
            start = min(done, H - rows)  # the last band is shifted up to keep its height
            stop = start + rows
            args = (o_pad[start : stop + 2 * h], cand[start : stop + 2 * h], cand_sum[start:stop],
                    cand_inv[start:stop], cand_unknown[start:stop], osum[start:stop], oinv[start:stop],
                    k_int[start:stop], beta)  # fmt: skip
            kwargs = dict(block=block, col_shift=col_shift, n_sub=int(n_sub), d_min=float(d_min), d_max=float(d_max))
            band = _run_refine(fn, args, kwargs, grad)
            pieces.append(band[done - start :])
            done = stop
        disparity = torch.cat(pieces, dim=0)

    if quantize:
        quantised = torch.round(disparity.detach() * S) / S
        disparity = disparity + (quantised - disparity).detach()

    with torch.no_grad():
        confidence = (best.clamp(0, 1) - second.clamp(0, 1)).clamp(0, 1).to(dev)
        confidence = torch.where(found, confidence, torch.zeros_like(confidence))
        if h > 0:
            confidence[:, :h] = 0
            confidence[:, W - h :] = 0
        confidence = confidence.to(dtype)
        valid = (confidence >= min_confidence) & (confidence > 0)
    return MatchResult(disparity=disparity, confidence=confidence, valid=valid)


def _run_refine(fn, args, kwargs, use_checkpoint: bool):
    """Run one band; with ``use_checkpoint`` its graph is rebuilt in the backward pass."""
    global _COMPILE_FAILED

    def call(f, kw):
        if use_checkpoint:
            return checkpoint(lambda *a: f(*a, **kw), *args, use_reentrant=False)
        return f(*args, **kw)

    try:
        return call(fn, kwargs)
    except Exception as error:  # noqa: BLE001 - a compile failure of any kind: eager from now on
        if _COMPILE_FAILED or not _COMPILED:
            raise
        _COMPILE_FAILED = True
        log.warning("ddsgen matcher: torch.compile failed (%s); using eager mode", type(error).__name__)
        return call(_refine_band, kwargs)
