"""Optional post-processing CNN (DDS, Planche & Singh 2021): two conv layers on [sim depth, clean depth, shadow].

    x  = [ (z_sim - z_clean) / 1 cm  where z_sim is valid, else 0,     (simulated depth)
           z_clean - 1 m,                                            (clean depth)
           shadow (0/1) ]                                            (shadow map)
    h  = ReLU(conv5x5(x; 32 filters))                  3*32*25 + 32 = 2,432 weights
    o  = conv1x1(h; 3 outputs)                         32*3    + 3  =    99 weights
    z' = z_clean + (z_sim - z_clean) * exp(o_1) + 1 cm * o_0         (depth correction, noise rescale)
    keep = sigmoid(o_2 + 4.6)                                       (validity; 0.99 at o_2 = 0)

2,531 trainable weights; with the 4 fitted sensor parameters (eta_c, read-noise std, beta,
baseline) that is the paper's count of 2,535. The paper's 1x1 layer maps the 32 features
back to the 3 input channels; here those 3 outputs are given a meaning each (a depth offset,
a log-scale of the simulated error, a validity logit). The first channel is the simulated
depth expressed relative to the clean depth, an exact reparameterisation of a conv on raw
[z_sim, z_clean] (a conv weight pair (a, b) on them equals (a, a + b) on [z_sim - z_clean,
z_clean]) that keeps inputs O(1); invalid simulated pixels enter as 0. The 1x1 layer starts
at zero, so an untrained network is the identity (keep = 0.99 > 0.5 leaves validity alone).

Weights are saved with :func:`save_postprocess` (a torch state dict, loaded with
``weights_only=True``) and named by a preset's ``postprocess:`` key.
"""

from __future__ import annotations

from pathlib import Path

import torch
from torch import nn

from ddsgen.atomic import atomic_write_bytes
from ddsgen.errors import InputError

DEPTH_UNIT_M = 0.01
DEPTH_CENTRE_M = 1.0
KEEP_BIAS = 4.6


class PostProcessCNN(nn.Module):
    """The 2-layer CNN. Call: ``(depth, valid, valid_soft, geometry) -> (depth, valid, valid_soft)``, all (H, W)."""

    def __init__(self, hidden: int = 32, kernel: int = 5):
        super().__init__()
        self.conv1 = nn.Conv2d(3, hidden, kernel, padding=kernel // 2, padding_mode="replicate")
        self.conv2 = nn.Conv2d(hidden, 3, 1)
        nn.init.zeros_(self.conv2.weight)
        nn.init.zeros_(self.conv2.bias)

    def forward(self, depth, valid, valid_soft, geometry):
        clean = geometry.clean_depth
        sim_error = torch.where(valid, depth - clean, torch.zeros_like(depth))
        x = torch.stack([sim_error / DEPTH_UNIT_M,
                         torch.where(geometry.hit, clean - DEPTH_CENTRE_M, torch.zeros_like(clean)),
                         geometry.shadow.to(depth.dtype)])  # fmt: skip
        o = self.conv2(torch.relu(self.conv1(x[None])))[0]
        corrected = clean + sim_error * torch.exp(o[1].clamp(-5, 5)) + DEPTH_UNIT_M * o[0]
        keep = torch.sigmoid(o[2] + KEEP_BIAS)
        valid = valid & (keep > 0.5)
        depth = torch.where(valid, corrected, torch.zeros_like(depth))
        return depth, valid, valid_soft * keep


def parameter_count(module: nn.Module) -> int:
    return sum(p.numel() for p in module.parameters())


def save_postprocess(module: PostProcessCNN, path: str | Path) -> None:
    """Write the weights (atomic)."""
    import io

    buffer = io.BytesIO()
    torch.save({"format": "ddsgen-postprocess-v1", "state_dict": module.state_dict()}, buffer)
    atomic_write_bytes(path, buffer.getvalue())


def load_postprocess(path: str | Path) -> PostProcessCNN:
    """Read weights written by :func:`save_postprocess`; InputError if missing or malformed."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: postprocess: weights file not found")
    try:
        data = torch.load(path, map_location="cpu", weights_only=True)
        module = PostProcessCNN()
        module.load_state_dict(data["state_dict"])
    except Exception as error:  # noqa: BLE001 - any unreadable file is bad input
        raise InputError(f"{path}: postprocess: not a ddsgen post-processing weights file ({type(error).__name__})") from None
    return module
