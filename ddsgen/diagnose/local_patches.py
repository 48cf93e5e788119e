"""Where the gap is when no sensor axis explains it: the local patches that carry it (diagnose's step 5).

A sensor effect is smooth along the image and with depth: the axes of :mod:`ddsgen.diagnose.residuals`
see it. When no structure remains along them but the held-out gap is still well beyond its noise floor,
the disagreement is *local*: patches (:mod:`ddsgen.realscan.local_patches`) where the real surface lies at another
depth than the modelled one, several windows wide, with edges of their own. That is what a scene the model
lacks produces (a support that is not one plane, objects that are not modelled, their fringes), not a
sensor. This module finds them on the held-out data and measures how much of the gap they carry, so the
report can say where the gap is instead of "nothing remains".
"""

from __future__ import annotations

import dataclasses

import numpy as np
import torch

from ddsgen.diagnose.evaluation import evaluate
from ddsgen.diagnose.plane import replaned
from ddsgen.realscan.local_patches import (
    FramePatches,
    patch_count,
    patch_share,
    patches_against,
)
from ddsgen.realscan.losses import local_window
from ddsgen.realscan.simulate import simulate, simulate_twin


def frame_patches(sensor, frames, seed: int) -> list[FramePatches]:
    """The patches (:func:`~ddsgen.realscan.local_patches.patches_against`) of every frame in ``frames`` (prepared, whole
    frames) under ``sensor``, noise draw ``seed``; the twin is unit 1 (:func:`~ddsgen.realscan.simulate.simulate_twin`
    draw 0)."""
    out = []
    with torch.no_grad():
        for frame in frames:
            out.append(patches_against(simulate(sensor, frame, seed), frame, simulate_twin(sensor, frame, seed, 0),
                                       local_window(frame.intrinsics.fx)))  # fmt: skip
    return out


@dataclasses.dataclass
class LocalReading:
    """How much of a held-out gap the local patches carry. ``before``/``without``: evaluations (gap and floor,
    mm) of the same model on the held-out frames with and without the patches' pixels."""

    patches: list[FramePatches]
    before: object
    without: object

    @property
    def count(self) -> int:
        return patch_count(self.patches)

    @property
    def share(self) -> float:
        """Fraction of the compared pixels inside a patch."""
        return patch_share(self.patches)

    @property
    def carried(self) -> float:
        """Fraction of the gap beyond the floor that goes with the patches."""
        return 1.0 - self.without.excess / self.before.excess if self.before.excess > 0 else 0.0

    def sentence(self) -> str:
        if not self.count:
            return (f"{self.before.excess:.2f} mm beyond the noise floor remains, along no axis and in no local patch: "
                    "it is spread over the image.")  # fmt: skip
        offsets = np.abs(np.concatenate([p.offsets_mm for p in self.patches]))
        threshold = min(p.threshold_mm for p in self.patches)
        return (
            f"What remains is local, not along a sensor axis: {self.count} patch(es) covering "
            f"{100 * self.share:.0f} % of the compared pixels, where the real surface lies "
            f"{offsets.min():.0f}-{offsets.max():.0f} mm off the simulated one (median per patch; another unit of the "
            f"simulated sensor stays within {threshold:.1f} mm locally), carry {100 * self.carried:.0f} % of the "
            f"held-out gap beyond the noise floor: without them it is {self.without.excess:.2f} mm instead of "
            f"{self.before.excess:.2f} mm (compare gap {self.without.gap:.2f} instead of {self.before.gap:.2f} mm). "
            f"A sensor effect varies smoothly along the image and with depth, and no axis shows structure beyond "
            f"noise; patches with edges of their own are the scene the model lacks (a support that is not one "
            f"plane, objects not in the scene, their fringes). "
            f"Model that geometry, or compare only the modelled objects (--region objects); the patches are "
            f"outlined on the residual map.")  # fmt: skip

    def to_dict(self) -> dict:
        return {"patches": self.count, "share": round(self.share, 4), "carried": round(self.carried, 4),
                "gap_beyond_floor_without": round(float(self.without.excess), 6),
                "offsets_mm": [round(o, 2) for p in self.patches for o in p.offsets_mm]}  # fmt: skip


def local_reading(sensor, frames, held_frames, seed: int, before, floor_draws: int, replane_steps: int) -> LocalReading:
    """Find the patches and re-evaluate ``held_frames`` without them.

    ``frames``: the diagnosis's prepared frames; one frame was split into pieces (``held_frames`` are pieces of
    it), so its patches are found on it whole (support plane re-estimated under ``sensor`` with
    ``replane_steps``, as the pieces' were); several frames: on each held-out frame. Without the patches the
    held-out frames' support planes are re-estimated (``replane_steps``) before their gaps. ``before`` is the model's
    evaluation on ``held_frames`` (:class:`~ddsgen.diagnose.evaluation.Evaluation`) and ``floor_draws`` the units
    it averaged its floor over, so both evaluations report the same floor.
    """
    split = len(frames) == 1
    whole = replaned(sensor, frames, seed, replane_steps) if split else held_frames
    patches = frame_patches(sensor, whole, seed)
    masks = {p.name: torch.from_numpy(p.mask) for p in patches}
    outside = [dataclasses.replace(h, region=h.region & ~masks[frames[0].name if split else h.name])
               for h in held_frames]  # fmt: skip
    # The support plane is a nuisance fitted to the compared pixels: fitted again without the patches, as it would
    # have been had they never been compared (the cat: 35 % carried with the planes fitted through them, 49 % so).
    outside = replaned(sensor, outside, seed, replane_steps)
    return LocalReading(patches, before, evaluate(sensor, outside, seed, floor_draws=floor_draws))
