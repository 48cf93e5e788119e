"""The C path's autograd Functions: each calls its C kernel in the forward pass and
its hand-written (or recomputed) gradient in the backward pass; nothing else."""

from __future__ import annotations

import torch

from ddsgen.sensor.matcher.kernel import _call_refine, _load_kernel, _n_threads
from ddsgen.sensor.matcher.windows import VARIANCE_FLOOR, _observed_stats


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



class _RefineC(torch.autograd.Function):
    """Sub-pixel refinement by the fused C kernel ``ddsgen_refine``: window cross-correlations,
    ZNCC and soft-argmax per pixel, without a cost volume. Differentiable w.r.t. the padded
    observed image ``o`` (through the cross-correlations), its window statistics ``osum``,
    ``oinv`` and ``beta``; the backward recomputes each band of ``rows`` rows in C.

    o: (H + b - 1, W + b - 1) float32 normalised padded observed image; osum, oinv: (H, W);
    beta: 0-dim; k: (H, W) integer disparities; ref: the prepared reference (its C layouts
    ``fwd``, ``bwd``, ``stat_sum``, ``stat_inv``, ``stat_unk``); geom: a RefineGeometry.
    Returns (H, W). Its torch twin, same arguments: torch_path._refine_torch."""

    @staticmethod
    def forward(ctx, o, osum, oinv, beta, k, ref, geom):
        lib = _load_kernel()
        k = k.to(torch.int32).contiguous()
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
        rows = geom.rows
        g_band = torch.empty(min(rows, H), W, ref.n_cand_padded, dtype=torch.float32)
        bwd = ref.bwd
        for v0 in range(0, H, rows):  # the (rows, W, C) gradient buffer bounds the memory
            v1 = min(H, v0 + rows)
            _call_refine(lib, o_c, os_c, oi_c, float(beta.detach()), k, ref, geom, v0, v1, grad=(gd, g_band, d_os, d_oi, d_beta))  # fmt: skip
            lib.ddsgen_window_cross_grad(g_band.data_ptr(), g_band.shape[2], bwd.data_ptr(), bwd.shape[2], ref.bwd_left,
                                         bwd.shape[1], ref.S, C, k.data_ptr(), geom.col_shift, v0, v1, W,
                                         geom.block, d_o.data_ptr(), d_o.shape[1], _n_threads())  # fmt: skip
        d_beta_total = d_beta.double().sum().to(beta.dtype) if ctx.needs_input_grad[3] else None
        return d_o, d_os, d_oi, d_beta_total, None, None, None
