"""The differentiable block matcher: ZNCC, integer search, sub-pixel soft-argmax, row bands.

The observed IR image I_o(u, v) is compared with the reference R(u - d, v) for d in
[d_min, d_max] (docs/model.md, "Block matcher"). Two stages:

1. **Integer search** (no gradient: an argmax is piecewise constant). Zero-mean normalised
   cross-correlation (ZNCC) over block x block windows for every integer disparity, keeping
   per pixel the best score, the best score of any other peak (>= 2 px away) and its
   argmax K. On the CPU this runs in a small C kernel (compiled once with the system C
   compiler, cached in ddsgen's cache folder; OpenMP over rows, vectorised over disparities;
   streaming, so it never holds a cost volume). Without a compiler, or on CUDA, a torch
   implementation over row bands does the same.
2. **Sub-pixel refinement** (differentiable). Candidates d_t = K + t / S, t = -T..T with
   S = 2^min(n_sub, REFINE_LEVEL) (1/4 px by default: the soft-argmax is continuous in the shift, so the
   device's 1/8-px output needs no 1/8-px candidates, see REFINE_LEVEL) and T = S + S // 2 (K +- 1.5 px),
   scored by the same ZNCC against the sub-pixel shifted
   reference phases (exact windows, gathered per pixel, not approximated), then
   d = sum_t softmax(beta * zncc)_t * d_t. The forward value is quantised to 2^-n_sub px with a
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
``confidence >= min_confidence`` (and > 0). With ``confirmed_match_zncc`` < 1 a match that fails
this uniqueness test is still valid when its best ZNCC exceeds ``confirmed_match_zncc`` and a
unique match within its window has its integer disparity (+-1 px): a window across a depth edge
sees two surfaces (two peaks of about half the ZNCC each) and its best peak is one of them, which
a neighbour on that surface confirms; repeated texture and noise agree with a unique neighbour only
by chance. Where the best peak is not confirmed (another alignment of the dot pattern can outscore
both surfaces' part-window peaks), the second peak is checked the same way (its ZNCC exceeds
``confirmed_match_zncc`` and a unique neighbour within the window has its disparity); the pixel
then takes the second peak, and the sub-pixel refinement centres on it. A confirmed match's
confidence is min_confidence + (its peak's ZNCC - confirmed_match_zncc), so
``confidence >= min_confidence`` stays the validity test. Uniqueness and confirmation use the
integer search only, so they are decided before the refinement.

Gradients: the disparity is differentiable w.r.t. ``observed``, ``beta`` and (if they
require grad) ``reference_phases``; variance floors keep them finite on flat windows.
Everything works in float64 too (for ``torch.autograd.gradcheck``), with ``quantize=False``
to check the soft-argmax itself.

Shapes: observed (H, W); reference_phases (S, H, W + pad); outputs (H, W).

The package, one idea per module: this file checks inputs, sets defaults and picks a path
(:func:`match`); ``windows`` (box sums, mirrored borders, the observed window statistics),
``reference`` (the prepared, cached reference layouts), ``kernel`` (compiling, loading and
calling ``csrc/zncc.c``), ``autograd`` (the C path's autograd Functions, which only call the
kernels), ``torch_path`` (the pure-torch twin with the same arguments), ``stereo`` (reference
phases of an ordinary stereo pair).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import torch

from ddsgen.sensor.matcher.autograd import _ObservedStatsC, _RefineC
from ddsgen.sensor.matcher.kernel import (SEARCH_LANES, _integer_search_c, _load_kernel, confirm_by_unique_neighbour_c,
                                          integer_search_backend)
from ddsgen.sensor.matcher.reference import RefineGeometry, _prepare_reference
from ddsgen.sensor.matcher.stereo import stereo_reference_phases
from ddsgen.sensor.matcher.torch_path import _integer_search_torch, _refine_torch, _want_compile
from ddsgen.sensor.matcher.validity_kernel import match_validity_c
from ddsgen.sensor.matcher.windows import VARIANCE_FLOOR, _observed_stats

__all__ = ["MatchResult", "match", "stereo_reference_phases", "integer_search_backend", "VARIANCE_FLOOR", "REFINE_LEVEL"]

#: Default spacing 2^-REFINE_LEVEL px of the refinement's candidates (when n_sub is larger). The
#: soft-argmax is a weighted mean, continuous in the true shift: with beta = 15 its weights are a peak
#: of ~0.2 px sigma, which 1/4-px samples resolve without locking to the grid (measured in
#: tests/test_matcher.py), so a finer output quantum (the device's 1/8 px) needs no finer candidates.
REFINE_LEVEL = 2


@dataclass
class MatchResult:
    """Output of :func:`match`, all (H, W).

    disparity: float px; differentiable; forward value quantised to 2^-n_sub px.
    confidence: in [0, 1] (best ZNCC minus the best other peak), no gradient.
    valid: bool, ``confidence >= min_confidence`` and inside the matchable area (see the module
        docstring for confirmed matches).
    best_zncc, second_zncc: the best integer-disparity ZNCC and the best other peak's, clipped to
        [0, 1], no gradient (for diagnosis: confidence is derived from them).
    peak_px: int64, the integer disparity the sub-pixel refinement centred on: the best peak's, or the
        second peak's where only that one was confirmed (see the module docstring).
    second_peak_px: int32, the integer disparity of the second peak where the rule may use it: its ZNCC
        exceeds ``confirmed_match_zncc`` and the match fails the uniqueness test (-1 elsewhere, where
        the search skips it).
    """

    disparity: torch.Tensor
    confidence: torch.Tensor
    valid: torch.Tensor
    best_zncc: torch.Tensor | None = None
    second_zncc: torch.Tensor | None = None
    peak_px: torch.Tensor | None = None
    second_peak_px: torch.Tensor | None = None

    def columns(self, width: int) -> "MatchResult":
        """The first ``width`` columns (an IR image wider than the depth image: ddsgen.sensor.ir_margin)."""
        return MatchResult(**{f.name: None if getattr(self, f.name) is None else getattr(self, f.name)[:, :width]
                              for f in fields(self)})  # fmt: skip


def _confirmed_by_a_unique_neighbour(k_int: torch.Tensor, unique: torch.Tensor, candidates: torch.Tensor,
                                     block: int, peaks: tuple[torch.Tensor, ...] | None = None,
                                     chunk: int = 32768, backend: str | None = None) -> list[torch.Tensor]:  # fmt: skip
    """[(H, W) bool per peak]: candidate pixels whose peak's integer disparity a unique match within
    their block x block window has (within 1 px).

    A window across a depth edge sees two surfaces and has a peak at each, so a unique neighbour on
    the surface of a peak has that peak's disparity. A wrong match (repeated texture, noise) agrees
    with a unique neighbour only by chance, and where no neighbour is unique nothing is confirmed.

    Args:
        k_int: (H, W) integer disparity of the best peak (px): the unique neighbours' disparities.
        unique: (H, W) bool, the matches that pass the uniqueness test.
        candidates: (H, W) bool, the pixels to check (the others come back False).
        peaks: the candidates' peak disparities to check, each (H, W) (default: ``(k_int,)``, the best
            peak); the neighbours' disparities are always their best peaks'.
        chunk: candidates gathered at once (bounds memory to chunk x block^2 elements).
        backend: "c" (the C kernel: it stops at the first agreeing neighbour, ~10x faster) or "torch";
            default: :func:`~ddsgen.sensor.matcher.kernel.integer_search_backend` of the tensors' device.
    """
    peaks = (k_int,) if peaks is None else peaks
    h = block // 2
    width = k_int.shape[1] + 2 * h
    # Disparities of the unique matches, far from any disparity elsewhere, padded by h: (H + 2h) x width, flat.
    seeds = torch.where(unique, k_int.to(torch.int32), torch.full_like(k_int, -(2**20), dtype=torch.int32))
    seeds = torch.nn.functional.pad(seeds[None], (h, h, h, h), value=-(2**20))[0].reshape(-1)
    ys, xs = torch.nonzero(candidates, as_tuple=True)
    owns = [peak[ys, xs].to(torch.int32) for peak in peaks]
    outs = [torch.zeros_like(candidates) for _ in peaks]
    if (backend or integer_search_backend(k_int.device)) == "c":
        for out, agreed in zip(outs, confirm_by_unique_neighbour_c(_load_kernel(), seeds, width, ys, xs, owns, block)):
            out[ys, xs] = agreed
        return outs
    dy, dx = torch.meshgrid(torch.arange(block, device=k_int.device), torch.arange(block, device=k_int.device),
                            indexing="ij")  # fmt: skip
    window = (dy * width + dx).reshape(1, -1)  # offsets of a window's pixels from its top-left corner
    corner = ys * width + xs
    for start in range(0, ys.numel(), chunk):
        part = slice(start, start + chunk)
        at = (corner[part, None] + window).reshape(-1)  # index_select: ~3x faster than seeds[2-D index]
        neighbours = seeds.index_select(0, at).reshape(-1, window.shape[1])  # (chunk, block^2)
        for own, out in zip(owns, outs):
            out[ys[part], xs[part]] = ((neighbours - own[part, None]).abs() <= 1).any(dim=1)
    return outs


def _validity(best: torch.Tensor, second: torch.Tensor, found: torch.Tensor, k_int: torch.Tensor, k_second: torch.Tensor,
              block: int, min_confidence: float, confirmed_match_zncc: float):  # fmt: skip
    """(confidence, valid, k_int): the uniqueness test, then confirmed matches (module docstring).

    best, second: (H, W) ZNCC of the best and second peaks, clipped to [0, 1]; found: (H, W) bool, a
    candidate existed; k_int, k_second: (H, W) their integer disparities (-1: no second peak).
    Returns k_int with the second peak's disparity where only that one was confirmed.
    """
    W = best.shape[1]
    h = block // 2
    matchable = found.clone()
    if h > 0:
        matchable[:, :h] = False
        matchable[:, W - h :] = False
    confidence = torch.where(matchable, (best - second).clamp(0, 1), torch.zeros_like(best))
    if confirmed_match_zncc < 1.0:
        unique = matchable & (confidence >= min_confidence) & (confidence > 0)
        # The best peak, or else the second, when a unique neighbour within the window confirms it. A
        # window across a depth edge has a peak per surface and its best may be neither (another
        # alignment of the dot pattern); the surface's peak is then the second.
        candidates = matchable & ~unique & (best > confirmed_match_zncc)
        k_second = k_second.to(best.device)
        by_best, by_second = _confirmed_by_a_unique_neighbour(k_int.to(best.device), unique, candidates, block,
                                                              (k_int.to(best.device), k_second))  # fmt: skip
        by_second &= ~by_best & (k_second >= 0) & (second > confirmed_match_zncc)
        k_int = torch.where(by_second.to(k_int.device), k_second.to(k_int.dtype), k_int)
        # The margin by which a confirmed match passes: min_confidence + (its peak's ZNCC - confirmed_match_zncc).
        peak = torch.where(by_second, second, best)
        confirmed_margin = (min_confidence + peak - confirmed_match_zncc).clamp(0, 1)
        confidence = torch.where(by_best | by_second, torch.maximum(confidence, confirmed_margin), confidence)
    valid = (confidence >= min_confidence) & (confidence > 0)
    return confidence, valid, k_int


def _validity_of_peaks(best: torch.Tensor, second: torch.Tensor, arg: torch.Tensor, arg2: torch.Tensor, k_hi: int,
                       k_lo: int, block: int, min_confidence: float, confirmed_match_zncc: float):  # fmt: skip
    """``(best, second, confidence, valid, k_int, k_second)`` from the integer search's (H, W) peaks (ZNCC ``best``,
    ``second``; candidate indices ``arg``, ``arg2``, -1 for none, disparity k_hi - index): the ZNCCs clipped to
    [0, 1], then :func:`_validity`; ``k_int`` is k_lo where nothing was found, ``k_second`` int32 (-1 for none).
    The definition that :func:`ddsgen.sensor.matcher.validity_kernel.match_validity_c` computes in C."""
    found = arg >= 0
    k_int = torch.where(found, k_hi - arg, torch.full_like(arg, k_lo))
    k_second = torch.where(arg2 >= 0, k_hi - arg2, torch.full_like(arg2, -1)).to(torch.int32)
    best, second = best.clamp(0, 1), second.clamp(0, 1)
    confidence, valid, k_int = _validity(best, second, found.to(best.device), k_int, k_second, block, min_confidence,
                                         confirmed_match_zncc)  # fmt: skip
    return best, second, confidence, valid, k_int, k_second


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
    refine_level: int | None = None,
    confirmed_match_zncc: float = 1.0,
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
        refine_level: the refinement's candidates are 2^-refine_level px apart (default
            min(n_sub, REFINE_LEVEL), at most n_sub); the output is still quantised to 2^-n_sub px.
        confirmed_match_zncc: a match that is not unique (confidence < min_confidence) is still
            valid when its best ZNCC exceeds this and a unique match within its block x block
            window has its integer disparity (+-1 px): a window across a depth edge. Failing that,
            the same test on its second peak (ZNCC and disparity), which it then takes. 1 = off.

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
    n_disp = k_hi - k_lo + 1

    extra = h + SEARCH_LANES + max(0, -k_lo)  # readable columns right of the image (see the C kernels)
    refine_level = min(int(n_sub), REFINE_LEVEL) if refine_level is None else int(refine_level)
    ref = _prepare_reference(reference_phases, pad, block, int(n_sub), extra, refine_level)

    # The C kernels on the CPU when they compiled (or when asked for); the torch twin otherwise.
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
            best, second, arg, arg2 = _integer_search_c(kernel, o_pad, ref, osum, oinv, block, r0, n_disp,
                                                        confirmed_match_zncc, min_confidence)  # fmt: skip
        else:
            best, second, arg, arg2 = _integer_search_torch(o_pad, ref, osum, oinv, block, r0, n_disp, band_rows,
                                                            confirmed_match_zncc, min_confidence)  # fmt: skip
        # Validity is decided on the integer peaks, so before the refinement (which centres on the peak it keeps).
        peaks = None
        if kernel is not None and dev.type == "cpu":  # the same maps in C
            peaks = match_validity_c(best, second, arg, arg2, k_hi, k_lo, block, min_confidence, confirmed_match_zncc)
        if peaks is None:
            peaks = _validity_of_peaks(best.to(dev), second.to(dev), arg, arg2, k_hi, k_lo, block, min_confidence,
                                      confirmed_match_zncc)  # fmt: skip
        best, second, confidence, valid, k_int, k_second = peaks
        del arg, arg2, peaks
        confidence = confidence.to(dtype)

    # Stage 2: sub-pixel refinement.
    grad = torch.is_grad_enabled() and (observed.requires_grad or beta.requires_grad or reference_phases.requires_grad)
    rows = max(1, min(int(band_rows), H))
    col_shift = pad + ref.offset - h
    use_c_refine = (kernel is not None and dev.type == "cpu" and dtype == torch.float32
                    and ref.fwd is not None and ref.n_cand_padded <= 64 and block <= 64)  # fmt: skip
    geom = RefineGeometry(block=block, col_shift=col_shift, n_sub=refine_level, d_min=float(d_min), d_max=float(d_max),
                          rows=rows)  # fmt: skip
    if use_c_refine:
        # Fused C kernel: no cost volume, no torch.compile; the backward recomputes bands of
        # `rows` rows in C, so memory is bounded by the band. Results do not depend on `rows`.
        disparity = _RefineC.apply(o_pad, osum, oinv, beta, k_int, ref, geom)
    else:
        disparity = _refine_torch(o_pad, osum, oinv, beta, k_int, ref, geom,
                                  compile_mode=_want_compile(dev, compile), use_checkpoint=grad)  # fmt: skip

    if quantize:
        quantised = torch.round(disparity.detach() * S) / S
        disparity = disparity + (quantised - disparity).detach()

    return MatchResult(disparity=disparity, confidence=confidence, valid=valid, best_zncc=best, second_zncc=second,
                       peak_px=k_int.to(dev), second_peak_px=k_second.to(dev))  # fmt: skip
