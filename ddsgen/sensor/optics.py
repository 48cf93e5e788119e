"""The IR lens's defocus: dots out of the focal plane are blurred, more so the nearer they are.

A lens of aperture diameter A focused at z_f images a point at depth z as a disc of diameter
c = f_px * A * |1/z - 1/z_f| pixels (thin lens, f_px the focal length in pixels). A fixed-focus
Kinect V1 is sharp around its working range and blurs close objects: the dots lose contrast and
the matcher's sub-pixel disparity gets noisier near the camera. The disc is approximated by a
Gaussian of the same standard deviation, c / 4.

The blur varies per pixel; it is applied by blending a few copies of the image blurred with
fixed sigmas (linear in sigma between neighbouring levels), so it costs a handful of separable
convolutions per frame and stays differentiable in the image.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

# Sigmas (px) of the pre-blurred copies; per-pixel sigmas beyond the last are clamped to it.
BLUR_LEVELS_PX = (0.0, 0.35, 0.7, 1.05, 1.4)


def defocus_sigma_px(depth_m: torch.Tensor, focal_px: float, aperture_m: float, focus_m: float) -> torch.Tensor:
    """(H, W) Gaussian sigma (px) of the defocus blur at each pixel's depth (0 where depth is 0)."""
    inverse = torch.where(depth_m > 0, 1.0 / depth_m.clamp_min(1e-6), torch.full_like(depth_m, 1.0 / focus_m))
    return 0.25 * focal_px * aperture_m * (inverse - 1.0 / focus_m).abs()


def _gaussian_blur(image: torch.Tensor, sigma: float) -> torch.Tensor:
    if sigma <= 0:
        return image
    radius = int(math.ceil(3.0 * sigma))
    x = torch.arange(-radius, radius + 1, dtype=image.dtype, device=image.device)
    kernel = torch.exp(-0.5 * (x / sigma) ** 2)
    kernel = kernel / kernel.sum()
    out = F.pad(image[None, None], (radius, radius, radius, radius), mode="replicate")
    out = F.conv2d(out, kernel.view(1, 1, 1, -1))
    out = F.conv2d(out, kernel.view(1, 1, -1, 1))
    return out[0, 0]


def defocus_blur(image: torch.Tensor, sigma_px: torch.Tensor) -> torch.Tensor:
    """Blur ``image`` (H, W) by a per-pixel Gaussian sigma ``sigma_px`` (H, W, px; no gradient needed).

    Blends the two pre-blurred copies whose sigmas bracket each pixel's (see BLUR_LEVELS_PX).
    """
    levels = torch.tensor(BLUR_LEVELS_PX, dtype=image.dtype, device=image.device)
    sigma = sigma_px.detach().clamp(0.0, float(levels[-1]))
    top = int(torch.searchsorted(levels, sigma.max().reshape(1)).clamp_max(len(levels) - 1))
    copies = torch.stack([_gaussian_blur(image, float(s)) for s in BLUR_LEVELS_PX[: top + 1]])
    index = torch.searchsorted(levels[: top + 1], sigma.reshape(-1), right=True).clamp(1, max(top, 1)) - 1
    index = index.reshape(sigma.shape)
    if top == 0:
        return copies[0]
    low, high = levels[index], levels[index + 1]
    weight = ((sigma - low) / (high - low)).clamp(0.0, 1.0)
    below = copies.gather(0, index[None]).squeeze(0)
    above = copies.gather(0, (index + 1)[None]).squeeze(0)
    return below + (above - below) * weight
