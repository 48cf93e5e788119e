"""The library of effects (each registers itself under its preset name)."""

from __future__ import annotations

import torch

from ddsgen.sensor.effects import register
from ddsgen.sensor.effects.base import Effect, EffectParam


@register
class DisparityOffset(Effect):
    """The reference pattern is mis-registered by delta px: every disparity is off by delta."""

    name = "disparity_offset"
    stage = "disparity"
    description = (
        "The factory reference pattern is mis-registered by a constant disparity offset, "
        "so depth is biased by an amount that grows with the square of the distance."
    )
    signature = "depth bias proportional to z^2 (sign of -offset), independent of angle and image position"
    axis = "depth"
    params = {
        "offset_px": EffectParam(0.0, -3.0, 3.0, "px", "disparity added to every match", typical=0.3),
    }

    def forward(self, disparity: torch.Tensor, ctx: dict) -> torch.Tensor:
        return disparity + self.value("offset_px")
