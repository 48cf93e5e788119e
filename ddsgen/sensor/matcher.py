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

Rows are independent (epipolar lines are rows): the refinement runs on horizontal bands of
``band_rows`` rows, each reading ``block - 1`` extra rows (the overlap), and each band is
recomputed in the backward pass (activation checkpointing), so memory is bounded by the
band, not the image. Every output pixel is computed from its own window in a fixed order,
so a band-split run is bit-identical to a single-band run. Top and bottom image rows use
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
#: Above this many (pixel, candidate) pairs the C path also recomputes bands in the backward.
_CHECKPOINT_ELEMENTS = 4_000_000
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


def _shift_cols(x: torch.Tensor, shift: int) -> torch.Tensor:
    """y[..., j] = x[..., j - shift], NaN where j - shift is outside."""
    if shift == 0:
        return x
    nan = torch.full_like(x[..., : abs(shift)], float("nan"))
    if shift > 0:
        return torch.cat([nan, x[..., :-shift]], dim=-1)
    return torch.cat([x[..., -shift:], nan], dim=-1)


# --------------------------------------------------------------------------------------
# Prepared reference (normalised, padded, box statistics): constant per sensor, cached
# --------------------------------------------------------------------------------------
@dataclass
class _Reference:
    r0_int: torch.Tensor  # (H + 2h, Wr) float32, phase 0, normalised, unknown -> 0 (integer stage)
    rs_int: torch.Tensor  # (H, Ws) window sums of r0_int
    inv_int: torch.Tensor  # (H, Ws) 1 / window std of r0_int (0 where unknown)
    pen_int: torch.Tensor  # (H, Ws) 0, or _EXCLUDED_INT where the window touches unknown reference
    cand: torch.Tensor  # (H + 2h, Wr, C) candidate references, normalised, NaN -> 0
    cand_sum: torch.Tensor  # (H, Ws, C) window sums
    cand_inv: torch.Tensor  # (H, Ws, C) 1 / window std
    cand_unknown: torch.Tensor  # (H, Ws, C) bool: window touches unknown reference
    cand_padded: torch.Tensor | None  # (H + 2h, Wr, CP) float32, C padded to a multiple of 8 (C kernel)
    cand_t: torch.Tensor | None  # (C, H + 2h, Wr) float32 (C kernel backward)
    offset: int  # extended column index = reference column j + offset
    n_cand: int


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
    norm = (phases - finite.mean()) / finite.std().clamp_min(1e-12)  # differentiable if phases need it
    # Extended columns: 1 unknown column on the left, `extra` on the right.
    left = torch.full_like(norm[..., :1], float("nan"))
    right = torch.full_like(norm[..., :1], float("nan")).expand(*norm.shape[:-1], extra)
    ext = torch.cat([left, norm, right], dim=-1)
    ext = _pad_rows_reflect(ext, h)  # (S, H + 2h, Wr)
    floor = VARIANCE_FLOOR * n
    with torch.no_grad():
        r0 = ext[0].float()
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
    # Candidate t reads phase t mod S shifted by floor(t / S) columns.
    cands = [_shift_cols(ext[t % S], t // S) for t in range(-T, T + 1)]
    cand = torch.stack(cands, dim=-1)  # (H + 2h, Wr, C)
    unknown = torch.isnan(cand)
    cand = torch.where(unknown, torch.zeros_like(cand), cand)
    cand_chw = cand.permute(2, 0, 1)
    csum = _box_sum(cand_chw, block)
    csum2 = _box_sum(cand_chw * cand_chw, block)
    cinv = torch.rsqrt((csum2 - csum * csum / n).clamp_min(0) + floor)
    cunk = _box_sum(unknown.permute(2, 0, 1).to(cand.dtype), block) > 0.5
    padded = transposed = None
    if cand.device.type == "cpu" and not cand.requires_grad:
        with torch.no_grad():
            c32 = cand.float()
            padded = F.pad(c32, (0, (-c32.shape[-1]) % 8)).contiguous()
            transposed = c32.permute(2, 0, 1).contiguous()
    return _Reference(
        r0_int=r0, rs_int=rs.contiguous(), inv_int=inv.contiguous(), pen_int=penalty.contiguous(), cand=cand.contiguous(),
        cand_sum=csum.permute(1, 2, 0).contiguous(), cand_inv=cinv.permute(1, 2, 0).contiguous(),
        cand_unknown=cunk.permute(1, 2, 0).contiguous(), offset=1, n_cand=2 * T + 1,
        cand_padded=padded, cand_t=transposed,
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
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

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


/* Refinement: exact window cross-correlation of each pixel with its C candidate references,
 * and the candidates' window statistics gathered at the same place.
 *   out[v][u][t] = sum_{i<b, j<b} O[v+i][u+j] * F[v+i][col0[v][u] + j][t]
 * F is (H+2h) x Wr x CP (candidates padded with zeros to CP, a multiple of 8); STAT1/STAT2
 * are (H) x Ws x C, gathered into out1/out2 at [v][col0[v][u]]. */
void ddsgen_window_cross(const float *restrict O, int Wo, const float *restrict Fc, int Wr, int C, int CP,
                         const int32_t *restrict col0, int H, int W, int b,
                         const float *restrict STAT1, const float *restrict STAT2, int Ws,
                         float *restrict out, float *restrict out1, float *restrict out2, int n_threads)
{
    const int nq = CP / 8;
#pragma omp parallel num_threads(n_threads)
    {
        v8 acc[8];
#pragma omp for schedule(dynamic, 4)
        for (int v = 0; v < H; v++) {
            for (int u = 0; u < W; u++) {
                const int c0 = col0[(size_t)v * W + u];
                for (int q = 0; q < nq; q++) acc[q] = (v8){0, 0, 0, 0, 0, 0, 0, 0};
                for (int i = 0; i < b; i++) {
                    const float *restrict o = O + (size_t)(v + i) * Wo + u;
                    const v8 *f = (const v8 *)(Fc + ((size_t)(v + i) * Wr + c0) * CP);
                    for (int j = 0; j < b; j++) {
                        const float oj = o[j];
                        for (int q = 0; q < nq; q++) acc[q] += oj * f[j * nq + q];
                    }
                }
                const size_t p = ((size_t)v * W + u) * C;
                const float *accf = (const float *)acc;
                for (int t = 0; t < C; t++) out[p + t] = accf[t];
                const size_t s = ((size_t)v * Ws + c0) * C;
                for (int t = 0; t < C; t++) {
                    out1[p + t] = STAT1[s + t];
                    out2[p + t] = STAT2[s + t];
                }
            }
        }
    }
}

/* Backward of ddsgen_window_cross w.r.t. O. Each output row y is owned by one thread (no
 * races, deterministic order):
 *   dO[y][u+j] += sum_t G[v][u][t] * FT[t][y][col0[v][u] + j]   for v = y - i, all u, j
 * FT is the candidate references transposed to C x (H+2h) x Wr, readable 7 columns beyond
 * the last window column. */
void ddsgen_window_cross_grad(const float *restrict G, const float *restrict FT, int Wr, int C,
                              const int32_t *restrict col0, int H, int W, int b,
                              float *restrict dO, int Wo, int n_threads)
{
    const int Hp = H + b - 1;
    const int nbq = (b + 7) / 8;
#pragma omp parallel num_threads(n_threads)
    {
        v8 acc[8];
#pragma omp for schedule(dynamic, 4)
        for (int y = 0; y < Hp; y++) {
            float *restrict drow = dO + (size_t)y * Wo;
            for (int x = 0; x < Wo; x++) drow[x] = 0.0f;
            for (int i = 0; i < b; i++) {
                const int v = y - i;
                if (v < 0 || v >= H) continue;
                for (int u = 0; u < W; u++) {
                    const float *restrict g = G + ((size_t)v * W + u) * C;
                    const int c0 = col0[(size_t)v * W + u];
                    for (int q = 0; q < nbq; q++) acc[q] = (v8){0, 0, 0, 0, 0, 0, 0, 0};
                    for (int t = 0; t < C; t++) {
                        const float gt = g[t];
                        const float *restrict f = FT + ((size_t)t * Hp + y) * Wr + c0;
                        for (int q = 0; q < nbq; q++) acc[q] += gt * LOADU(f + 8 * q);
                    }
                    const float *restrict s = (const float *)acc;
                    float *restrict d = drow + u;
                    for (int j = 0; j < b; j++) d[j] += s[j];  /* scalar: store-forwarding friendly */
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
            lib.ddsgen_window_cross.argtypes = [p, i, p, i, i, i, p, i, i, i, p, p, i, p, p, p, i]
            lib.ddsgen_window_cross_grad.argtypes = [p, p, i, i, p, i, i, i, p, i, i]
            for fn in (lib.ddsgen_zncc_search, lib.ddsgen_window_cross, lib.ddsgen_window_cross_grad):
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


class _WindowCrossC(torch.autograd.Function):
    """C kernel: cross[v, u, t] = sum_{i, j} o[v + i, u + j] * cand[v + i, col0[v, u] + j, t],
    plus the candidates' window sum and 1/std gathered at col0 (constants).

    o: (hb + b - 1, W + b - 1) float32; cand_p: (hb + b - 1, Wr, CP) float32 candidates padded
    to a multiple of 8; cand_t: (C, hb + b - 1, Wr) transposed candidates (for the backward);
    csum, cinv: (hb, Ws, C); col0: (hb, W) int. Differentiable w.r.t. ``o`` only."""

    @staticmethod
    def forward(ctx, o, cand_p, cand_t, csum, cinv, col0, block):
        lib = _load_kernel()
        hb, W = col0.shape
        C = cand_t.shape[0]
        o_c = o.detach().contiguous()
        col0_c = col0.to(torch.int32).contiguous()
        out = torch.empty(3, hb, W, C, dtype=torch.float32)
        lib.ddsgen_window_cross(o_c.data_ptr(), o_c.shape[1], cand_p.data_ptr(), cand_p.shape[1], C,
                                cand_p.shape[2], col0_c.data_ptr(), hb, W, block, csum.data_ptr(),
                                cinv.data_ptr(), csum.shape[1], out[0].data_ptr(), out[1].data_ptr(),
                                out[2].data_ptr(), _n_threads())  # fmt: skip
        ctx.save_for_backward(cand_t, col0_c)
        ctx.block, ctx.o_shape = block, tuple(o_c.shape)
        ctx.mark_non_differentiable(out[1], out[2])
        return out[0], out[1], out[2]

    @staticmethod
    def backward(ctx, grad_cross, _g1, _g2):
        cand_t, col0_c = ctx.saved_tensors
        lib = _load_kernel()
        hb, W = col0_c.shape
        g = grad_cross.float().contiguous()
        d_o = torch.empty(ctx.o_shape, dtype=torch.float32)
        lib.ddsgen_window_cross_grad(g.data_ptr(), cand_t.data_ptr(), cand_t.shape[2], cand_t.shape[0],
                                     col0_c.data_ptr(), hb, W, ctx.block, d_o.data_ptr(), ctx.o_shape[1],
                                     _n_threads())  # fmt: skip
        return d_o, None, None, None, None, None, None


def _refine_band(o_band, cand_band, csum_band, cinv_band, cunk_band, osum_band, oinv_band, k_band, beta,
                 block: int, col_shift: int, n_sub: int, d_min: float, d_max: float, use_c: bool = False,
                 soft=None):  # fmt: skip
    """Soft-argmax disparity of one band.

    o_band: (hb + b - 1, W + b - 1) normalised, padded observed rows of the band.
    cand_band: (hb + b - 1, Wr, C) candidate references of the same rows.
    csum_band, cinv_band, cunk_band: (hb, Ws, C) window statistics of the candidates.
    osum_band, oinv_band: (hb, W) window statistics of the observed image.
    k_band: (hb, W) int64 integer disparity K.
    use_c: window cross-correlations by the C kernel (float32 CPU, constant reference).
    soft: the (possibly compiled) :func:`_soft_argmax`.
    Returns (hb, W) disparity (not quantised).
    """
    hb, W = k_band.shape
    n_c = csum_band.shape[-1]
    n = block * block
    S = 2**n_sub
    T = (n_c - 1) // 2
    # Window start column (in extended reference columns) of each pixel's candidates.
    col0 = torch.arange(W, device=k_band.device)[None, :] + col_shift - k_band  # (hb, W)
    row_idx = torch.arange(hb, device=k_band.device)[:, None]
    if use_c:
        cand_p, cand_t = cand_band
        cross, csum, cinv = _WindowCrossC.apply(o_band, cand_p, cand_t, csum_band, cinv_band, col0, block)
        cunk = torch.gather(cunk_band, 1, col0[..., None].expand(hb, W, n_c))
    else:
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
        compile: use torch.compile for the refinement (default: yes, with eager fallback;
            environment DDSGEN_NO_COMPILE=1 disables it).
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
    o_mean = observed.mean()
    o_std = observed.std().clamp_min(1e-12)
    o_pad = _pad_cols_reflect(_pad_rows_reflect((observed - o_mean) / o_std, h), h)  # (H + 2h, W + 2h)
    osum = _box_sum(o_pad, block)  # (H, W)
    osum2 = _box_sum(o_pad * o_pad, block)
    oinv = torch.rsqrt((osum2 - osum * osum / n).clamp_min(0) + VARIANCE_FLOOR * n)

    # Stage 1: integer search. Window start column for candidate c (k = k_hi - c) at pixel u.
    r0 = pad + ref.offset - h - k_hi
    use_c = backend == "c" or (backend == "auto" and dev.type == "cpu")
    kernel = _load_kernel() if use_c else None
    if backend == "c" and kernel is None:
        raise RuntimeError("C integer-search kernel unavailable")
    with torch.no_grad():
        if kernel is not None and dev.type == "cpu":
            best, second, arg = _integer_search_c(kernel, o_pad, ref, osum, oinv, block, r0, n_disp)
        else:
            best, second, arg = _integer_search_torch(o_pad, ref, osum, oinv, block, r0, n_disp, band_rows)
        found = arg >= 0
        k_int = torch.where(found, k_hi - arg, torch.full_like(arg, k_lo))

    # Stage 2: refinement in bands of equal height (uniform shapes for the compiled kernel).
    grad = torch.is_grad_enabled() and (observed.requires_grad or beta.requires_grad or reference_phases.requires_grad)
    use_c_refine = (kernel is not None and dev.type == "cpu" and dtype == torch.float32
                    and ref.cand_padded is not None)  # fmt: skip
    compile_mode = _want_compile(dev, compile)
    fn = _refine_band if use_c_refine else _compiled(_refine_band, compile_mode)
    rows = max(1, min(int(band_rows), H))
    # The C path holds no cost volume; its autograd graph is ~12 floats per pixel and candidate.
    # Split it into bands recomputed in the backward pass (checkpointing) only when that graph
    # would be large; otherwise one call (fewer, larger ops: much faster on a busy machine).
    checkpoint_bands = H * W * ref.n_cand > _CHECKPOINT_ELEMENTS
    if use_c_refine and not checkpoint_bands:
        rows = H
    col_shift = pad + ref.offset - h
    pieces = []
    done = 0
    while done < H:
        start = min(done, H - rows)  # the last band is shifted up to keep its height
        stop = start + rows
        cand_band = ref.cand[start : stop + 2 * h]
        if use_c_refine:
            cand_band = (ref.cand_padded[start : stop + 2 * h], ref.cand_t[:, start : stop + 2 * h].contiguous())
        args = (o_pad[start : stop + 2 * h], cand_band, ref.cand_sum[start:stop],
                ref.cand_inv[start:stop], ref.cand_unknown[start:stop], osum[start:stop], oinv[start:stop],
                k_int[start:stop], beta)  # fmt: skip
        kwargs = dict(block=block, col_shift=col_shift, n_sub=int(n_sub), d_min=float(d_min), d_max=float(d_max))
        if use_c_refine:
            kwargs.update(use_c=True, soft=_compiled(_soft_argmax, compile_mode))
        band = _run_refine(fn, args, kwargs, grad and (checkpoint_bands or not use_c_refine))
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
        eager = dict(kwargs)
        if "soft" in eager:
            eager["soft"] = _soft_argmax
        return call(_refine_band, eager)
