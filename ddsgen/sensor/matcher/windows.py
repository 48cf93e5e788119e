"""Window statistics shared by both matcher paths: box sums over block x block windows,
mirrored borders, column shifts, and the observed image's normalised window statistics.

Shapes follow the matcher: images (H, W), padded images (H + 2h, W + 2h) with h = block // 2,
window sums indexed by the window's first row/column.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

#: Variance floor of a window, per pixel, in units of the image's global variance: keeps
#: ZNCC (and its gradient) finite on flat windows, where ZNCC -> 0.
VARIANCE_FLOOR = 1e-4
#: Score given to excluded refinement candidates (ZNCC itself is >= -1).
_EXCLUDED_SCORE = -3.0
#: Penalty added to integer-search scores of candidates whose window touches unknown reference.
_EXCLUDED_INT = -1e30


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
