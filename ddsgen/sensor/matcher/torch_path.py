"""The matcher's pure-torch path: the integer search over row bands of a cost volume and
the banded, checkpointed sub-pixel refinement (optionally torch.compile'd). Used on CUDA,
in float64, when the reference needs gradients, and when no C compiler is present; the
C path must agree with it (tests/test_matcher.py)."""

from __future__ import annotations

import logging
import os

import torch
from torch.utils.checkpoint import checkpoint

from ddsgen.cache import configure_torch_compile_cache
from ddsgen.sensor.matcher.reference import RefineGeometry, _Reference
from ddsgen.sensor.matcher.windows import _EXCLUDED_INT, _EXCLUDED_SCORE

log = logging.getLogger(__name__)


def _integer_search_torch(o_pad, ref: _Reference, os_, inv_o, block, r0, n_disp, band_rows, second_floor: float = 1.0,
                          min_confidence: float = 0.0):  # fmt: skip
    """Same as the C kernel, as row bands of a (row, column, disparity) volume: (best, second, arg, arg2)."""
    H, W = os_.shape
    n = block * block
    o = o_pad.detach().to(ref.r0_int.dtype)
    best_all, second_all, arg_all, arg2_all = [], [], [], []
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
        second, arg2 = score.scatter_(-1, peak, -2.0).max(dim=-1)  # first index among ties, as in C
        none = best < 0.5 * _EXCLUDED_INT
        no_second = none | ~(second > -2.0)
        conf = (best.float().clamp(0, 1) - second.float().clamp(0, 1)).clamp(0, 1)
        no_arg2 = none | ~(second > second_floor) | ((conf >= min_confidence) & (conf > 0))
        best_all.append(torch.where(none, torch.full_like(best, -2.0), best))
        second_all.append(torch.where(no_second, torch.full_like(second, -2.0), second))
        arg_all.append(torch.where(none, torch.full_like(arg, -1), arg))
        arg2_all.append(torch.where(no_arg2, torch.full_like(arg2, -1), arg2).to(torch.int32))
    return torch.cat(best_all).float(), torch.cat(second_all).float(), torch.cat(arg_all), torch.cat(arg2_all)



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
        configure_torch_compile_cache()
        _COMPILED[fn] = torch.compile(fn, dynamic=False)
    return _COMPILED[fn]



def _want_compile(device: torch.device, compile: bool | None) -> bool:
    if compile is not None:
        return compile
    if os.environ.get("DDSGEN_NO_COMPILE"):
        return False
    return device.type in ("cpu", "cuda")


def _refine_torch(o_pad, osum, oinv, beta, k_int, ref: _Reference, geom: RefineGeometry, *, compile_mode: bool = False,
                  use_checkpoint: bool = False) -> torch.Tensor:
    """The torch twin of the C refinement, same arguments as
    :class:`~ddsgen.sensor.matcher.autograd._RefineC`: bands of ``geom.rows`` rows of equal
    height (uniform shapes for the compiled kernel), torch.compile'd with ``compile_mode``, each
    recomputed in the backward pass with ``use_checkpoint``. Returns (H, W)."""
    H, rows = k_int.shape[0], geom.rows
    h = geom.block // 2
    fn = _compiled(_refine_band, compile_mode)
    cand, cand_sum, cand_inv, cand_unknown = ref.torch_candidates()
    pieces = []
    done = 0
    while done < H:
        start = min(done, H - rows)  # the last band is shifted up to keep its height
        stop = start + rows
        args = (o_pad[start : stop + 2 * h], cand[start : stop + 2 * h], cand_sum[start:stop],
                cand_inv[start:stop], cand_unknown[start:stop], osum[start:stop], oinv[start:stop],
                k_int[start:stop], beta)  # fmt: skip
        kwargs = dict(block=geom.block, col_shift=geom.col_shift, n_sub=geom.n_sub, d_min=geom.d_min, d_max=geom.d_max)
        band = _run_refine(fn, args, kwargs, use_checkpoint)
        pieces.append(band[done - start :])
        done = stop
    return torch.cat(pieces, dim=0)


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
