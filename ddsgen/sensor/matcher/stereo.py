"""Reference phases for an ordinary rectified stereo pair (``ddsgen stereo``): sub-pixel
shifted copies of the right image by Keys cubic interpolation, NaN outside it."""

from __future__ import annotations

import torch


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
