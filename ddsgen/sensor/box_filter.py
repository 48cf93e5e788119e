"""Box means and mask erosion on (H, W) torch images, at a cost that does not grow with the window.

torch's pooling costs k^2 per pixel and is slow at stride 1 on the CPU (a 15-px mean took 54 ms at
640 x 480, a 3 x 3 max-pool ~9 ms); a summed-area table costs the same for any k (~4 ms), and OpenCV's
erosion of a uint8 mask takes well under a millisecond. The diagnosis and the fit call these thousands
of times per run.
"""

from __future__ import annotations

import cv2
import numpy as np
import torch
import torch.nn.functional as F


def opencv_can_filter(x: torch.Tensor) -> bool:
    """Whether OpenCV may filter ``x`` instead of torch: a CPU tensor with no gradient to carry."""
    return x.device.type == "cpu" and not (x.requires_grad and torch.is_grad_enabled())


#: OpenCV border of each padding mode.
_BORDERS = {"zeros": cv2.BORDER_CONSTANT, "replicate": cv2.BORDER_REPLICATE}


def box_mean(x: torch.Tensor, k: int, padding: str = "zeros") -> torch.Tensor:
    """k x k mean of (N, C, H, W) ``x``, same size, from a summed-area table (differentiable).

    Args:
        x: (N, C, H, W) image(s).
        k: odd window size (px).
        padding: ``"zeros"`` (outside pixels count as 0) or ``"replicate"`` (the border is repeated).

    Summed in float64 so that differences of large sums stay exact; returned in ``x``'s dtype. Without a
    gradient to carry (CPU), OpenCV's box filter computes the same float64 means several times faster.
    """
    if padding not in _BORDERS:
        raise ValueError(f"padding must be 'zeros' or 'replicate', got {padding!r}")
    if opencv_can_filter(x):
        # OpenCV sums float32 images in float64 too: its float32 means equal the float64 ones rounded.
        exact = x.detach() if x.dtype in (torch.float32, torch.float64) else x.detach().double()
        planes = exact.reshape(-1, *x.shape[-2:]).numpy()
        means = [cv2.boxFilter(plane, -1, (k, k), normalize=True, borderType=_BORDERS[padding]) for plane in planes]
        return torch.from_numpy(np.stack(means)).reshape(x.shape).to(x.dtype)
    r = k // 2
    if padding == "replicate":
        padded = F.pad(x.double(), (r, r, r, r), mode="replicate")
        padded = F.pad(padded, (1, 0, 1, 0))  # the table's zero row and column
    else:
        padded = F.pad(x.double(), (r + 1, r, r + 1, r))
    table = padded.cumsum(-1).cumsum(-2)
    box = table[..., k:, k:] - table[..., :-k, k:] - table[..., k:, :-k] + table[..., :-k, :-k]
    return (box / (k * k)).to(x.dtype)


def erode(mask: torch.Tensor, k: int = 3) -> torch.Tensor:
    """(H, W) bool: pixels whose whole k x k neighbourhood (inside the image) is in ``mask``.

    Outside the image counts as in the mask (a border pixel is kept if its in-image neighbours are).
    OpenCV on CPU tensors; the equivalent max-pool on other devices.
    """
    if mask.device.type == "cpu":
        eroded = cv2.erode(mask.numpy().astype(np.uint8), np.ones((k, k), np.uint8), borderType=cv2.BORDER_CONSTANT,
                           borderValue=1)  # fmt: skip
        return torch.from_numpy(eroded.astype(bool))
    outside = (~mask).float()[None, None]
    return F.max_pool2d(outside, k, stride=1, padding=k // 2)[0, 0] < 0.5
