"""Optional physics as stages: the preset's effects plugged into the sensor's composition where they act.

An effect (:mod:`ddsgen.sensor.effects`) declares which signal it acts on (its ``stage``); the sensor gives each
signal one :class:`EffectStage` holding the effects that act on it, in the preset's order, and runs it at its place::

    IR image -> ir effects -> matcher -> row smoothing -> disparity effects -> z = f b / d -> depth effects
    -> validity effects -> validity -> image effects -> clean-up -> ...

A stage with no effects passes its input through unchanged (the same tensor).
"""

from __future__ import annotations

import dataclasses

import torch

from ddsgen.sensor.effects import Effect
from ddsgen.sensor.effects.context import EffectContext

#: The signals effects act on, in the order a frame passes them: the IR image (counts), the disparity (px), the
#: depth (m), the keep-probability (a factor in [0, 1] each validity effect computes from the depth), and the image
#: grid: every map of the frame at once, a tuple (depth m, disparity px, valid bool, keep-probability, confidence, IR
#: counts), each (H, W), resampled together where the device's pixels look.
SIGNALS = ("ir", "disparity", "depth", "validity", "image")


@dataclasses.dataclass(frozen=True)
class EffectStage:
    """The effects acting on one signal (:data:`SIGNALS`), applied in the preset's order. The sensor owns the
    effects (their parameters); a stage only holds them in order."""

    signal: str
    effects: tuple[Effect, ...] = ()

    def __call__(self, x, ctx: EffectContext):
        """``x`` (H, W) in the signal's units (the image grid: its tuple of maps, see :data:`SIGNALS`) through each
        effect."""
        for effect in self.effects:
            x = effect(x, ctx)
        return x


@dataclasses.dataclass(frozen=True)
class ValidityEffects(EffectStage):
    """Validity effects: each gives a keep-probability (H, W) in [0, 1] from the depth; they multiply."""

    signal: str = "validity"

    def __call__(self, keep: torch.Tensor, depth: torch.Tensor, ctx: EffectContext) -> torch.Tensor:  # type: ignore[override]
        """``keep`` (H, W) times every effect's keep-probability for ``depth`` (H, W) m."""
        for effect in self.effects:
            keep = keep * effect(depth, ctx)
        return keep


def effect_stages(effects) -> dict[str, EffectStage]:
    """{signal: its stage} for every signal of :data:`SIGNALS`, each holding those of ``effects`` that act on it."""
    stages = {signal: EffectStage(signal, tuple(e for e in effects if e.stage == signal)) for signal in SIGNALS}
    stages["validity"] = ValidityEffects(effects=stages["validity"].effects)
    return stages
