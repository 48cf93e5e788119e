"""The prepared reference: normalised, padded phases and their window statistics, in the
layouts the C kernels and the torch path read. Constant per sensor, so cached per phases tensor."""

from __future__ import annotations

import threading
import weakref
from dataclasses import dataclass

import torch

from ddsgen.sensor.matcher.windows import VARIANCE_FLOOR, _EXCLUDED_INT, _box_sum, _pad_rows_reflect, _shift_cols


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



@dataclass(frozen=True)
class RefineGeometry:
    """What the sub-pixel refinement reads, the same for its C and torch paths.

    block: window size w (px, odd); col_shift: extended reference column of the window of
    pixel u at integer disparity 0 (pixel u, disparity K starts at u + col_shift - K);
    n_sub: sub-pixel level (S = 2^n_sub candidates per px); d_min, d_max: disparity range
    (px; candidates outside it are excluded); rows: rows per band (bounds memory; results
    do not depend on it).
    """

    block: int
    col_shift: int
    n_sub: int
    d_min: float
    d_max: float
    rows: int


def _interleave_reversed(rows: int, width: int, S: int, left: int, right: int, dtype, fill=0) -> tuple:
    """An (rows, left + width S + right) buffer filled with ``fill`` and its (rows, width, S)
    view of the middle in reversed column order: ``view[:, c, s]`` is element
    ``left + (width - 1 - c) S + s``; write ``x.flip(-1)`` into ``view[:, :, s]``."""
    buf = torch.full((rows, left + width * S + right), fill, dtype=dtype)
    return buf, buf[:, left : left + width * S].view(rows, width, S)



_REF_CACHE: dict = {}  # key -> (weakref to the phases, _Reference), least recently used first
_REF_LOCK = threading.Lock()
# A few cameras at once: refining several views of a scene (or fitting frames cropped to different
# windows) switches the sensor's camera every call; one entry would rebuild the reference each time
# (~60 ms at 320x240). Render and a one-camera fit use one entry.
_REF_CACHE_SIZE = 4


def _prepare_reference(phases: torch.Tensor, pad: int, block: int, n_sub: int, extra: int,
                       refine_level: int | None = None) -> _Reference:
    """The prepared reference of ``phases`` (S = 2^n_sub phases), cached per phases tensor.

    ``refine_level`` (<= n_sub, default n_sub): the refinement's candidates are 2^-refine_level px
    apart, read from every 2^(n_sub - refine_level)-th phase (phase 2^(n_sub - r) s' of the fine set
    is phase s' of the coarse one: R(j - pad - s' / 2^r))."""
    refine_level = n_sub if refine_level is None else int(refine_level)
    if not 0 <= refine_level <= n_sub:
        raise ValueError(f"refine_level must be in 0..n_sub = {n_sub}, got {refine_level}")
    key = None
    if not phases.requires_grad:
        key = (phases.data_ptr(), phases._version, tuple(phases.shape), phases.dtype, str(phases.device),
               pad, block, n_sub, extra, refine_level)  # fmt: skip
        with _REF_LOCK:
            hit = _REF_CACHE.pop(key, None)
            if hit is not None and hit[0]() is phases:
                _REF_CACHE[key] = hit  # most recently used last
                return hit[1]
            _evict(_REF_CACHE_SIZE - 1)  # free before building: memory stays flat
    ref = _build_reference(phases[:: 2 ** (n_sub - refine_level)], pad, block, refine_level, extra)
    if key is not None:
        with _REF_LOCK:
            _evict(_REF_CACHE_SIZE - 1)
            _REF_CACHE[key] = (weakref.ref(phases), ref)
    return ref


def _evict(keep: int) -> None:
    """Drop entries whose phases are gone, then the least recently used down to ``keep`` (lock held)."""
    for key in [k for k, (phases, _) in _REF_CACHE.items() if phases() is None]:
        del _REF_CACHE[key]
    while len(_REF_CACHE) > keep:
        del _REF_CACHE[next(iter(_REF_CACHE))]


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
