"""Local patches: a gap that no sensor axis explains because it sits in a few places of the scene.

A sensor effect is smooth along the image and with depth: the axes of :mod:`ddsgen.diagnose.residuals`
see it. When no structure remains along them but the held-out gap is still well beyond its noise floor,
the disagreement is *local*: patches where the real surface lies at another depth than the modelled one,
several windows wide, with edges of their own. That is what a scene the model lacks produces (a support
that is not one plane, objects that are not modelled, their fringes), not a sensor. This module finds
those patches and measures how much of the gap they carry, so the report can say where the gap is
instead of "nothing remains".

A patch is a connected set (one sign) of pixels whose *local offset* -- the mean of simulated minus real
depth (mm) over the ``compare`` window (15 px at the Kinect's focal length), where both are valid -- is
larger than another unit of the same simulated sensor shows on all but 0.1 % of its pixels: the threshold is
the :data:`TWIN_QUANTILE` quantile of the same local offset between the simulation and its twin
(:func:`~ddsgen.fit.simulate.simulate_twin`), at least :data:`MIN_OFFSET_MM`. Patches smaller than
:data:`MIN_PATCH_WINDOWS` windows are dropped. Only depth offsets are read; holes in one map and not
the other are not patches.
"""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import torch

from ddsgen.fit.losses import local_window, masked_local_mean
from ddsgen.fit.simulate import simulate, simulate_twin

#: The twin's local offsets exceed the patch threshold on this fraction of the pixels at most.
TWIN_QUANTILE = 0.999
#: Every residual is clipped to the twin's per-pixel quantile of this order first: a flying pixel at a depth edge
#: (one unit puts it on the near surface, the other on the far one) would move a window's mean by centimetres.
CLIP_QUANTILE = 0.99
#: The threshold is at least this (mm): the precision the gaps are reported with.
MIN_OFFSET_MM = 1.0
#: A patch covers at least this many compare windows (2 x 15 x 15 px at 640 x 480).
MIN_PATCH_WINDOWS = 2
#: A window's local offset counts only where at least this fraction of it has both depths.
MIN_SUPPORT = 0.5


@dataclasses.dataclass
class FramePatches:
    """The patches of one whole frame.

    labels: (H, W) int32, 0 outside any patch, k = 1 .. n inside patch k; offsets_mm: median simulated
    minus real depth (mm) inside each patch; sizes_px: pixels of each patch; threshold_mm: the local offset
    a patch exceeds; compared_px: pixels compared (both depths valid in the region).
    """

    name: str
    labels: np.ndarray
    offsets_mm: list[float]
    sizes_px: list[int]
    threshold_mm: float
    compared_px: int

    @property
    def mask(self) -> np.ndarray:
        return self.labels > 0


def local_offset(residual_mm: np.ndarray, window: int) -> np.ndarray:
    """(H, W) mean of the finite values of ``residual_mm`` (H, W; NaN = not compared) over each
    ``window`` x ``window`` box, NaN where less than :data:`MIN_SUPPORT` of the box is finite."""
    finite = np.isfinite(residual_mm)
    values = torch.from_numpy(np.where(finite, residual_mm, 0.0).astype(np.float64))
    mean, support = masked_local_mean(values, torch.from_numpy(finite), window)
    return torch.where(support >= MIN_SUPPORT, mean, torch.full_like(mean, float("nan"))).numpy()


def find_patches(name: str, residual_mm: np.ndarray, twin_residual_mm: np.ndarray, window: int) -> FramePatches:
    """Patches of one frame from its residual (simulated minus real depth, mm, NaN where not compared) and
    its twin's (simulated minus another unit's depth, same convention), both (H, W)."""
    pixels = np.abs(twin_residual_mm[np.isfinite(twin_residual_mm)])
    clip = float(np.quantile(pixels, CLIP_QUANTILE)) if pixels.size else MIN_OFFSET_MM
    twin = np.abs(local_offset(np.clip(twin_residual_mm, -clip, clip), window))
    twin = twin[np.isfinite(twin)]
    threshold = max(float(np.quantile(twin, TWIN_QUANTILE)) if twin.size else 0.0, MIN_OFFSET_MM)
    offset = local_offset(np.clip(residual_mm, -clip, clip), window)
    labels = np.zeros(residual_mm.shape, np.int32)
    offsets, sizes = [], []
    min_px = MIN_PATCH_WINDOWS * window * window
    with np.errstate(invalid="ignore"):
        signs = (offset > threshold, offset < -threshold)
    for above in signs:
        n, comp, stats, _ = cv2.connectedComponentsWithStats(above.astype(np.uint8), connectivity=8)
        for k in range(1, n):
            if stats[k, cv2.CC_STAT_AREA] < min_px:
                continue
            inside = comp == k
            labels[inside] = len(sizes) + 1
            sizes.append(int(stats[k, cv2.CC_STAT_AREA]))
            values = residual_mm[inside]
            offsets.append(float(np.median(values[np.isfinite(values)])))
    return FramePatches(name, labels, offsets, sizes, threshold, int(np.isfinite(residual_mm).sum()))


def _residual(sim, frame, other) -> np.ndarray:
    """Simulated minus ``other`` depth (mm) where both are valid in the frame's region, NaN elsewhere."""
    depth, valid = other
    both = (frame.region & sim.valid & valid).numpy()
    diff = 1000.0 * (sim.depth.numpy().astype(np.float64) - depth.numpy().astype(np.float64))
    return np.where(both, diff, np.nan)


def frame_patches(sensor, frames, seed: int) -> list[FramePatches]:
    """:func:`find_patches` of every frame in ``frames`` (prepared, whole frames) under ``sensor``, noise draw
    ``seed``; the twin is unit 1 (:func:`~ddsgen.fit.simulate.simulate_twin` draw 0)."""
    out = []
    with torch.no_grad():
        for frame in frames:
            sim = simulate(sensor, frame, seed)
            twin = simulate_twin(sensor, frame, seed, 0)
            window = local_window(frame.intrinsics.fx)
            out.append(find_patches(frame.name, _residual(sim, frame, (frame.real_depth, frame.real_valid)),
                                    _residual(sim, frame, (twin.depth, twin.valid)), window))  # fmt: skip
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
        return sum(len(p.sizes_px) for p in self.patches)

    @property
    def share(self) -> float:
        """Fraction of the compared pixels inside a patch."""
        compared = sum(p.compared_px for p in self.patches)
        return sum(sum(p.sizes_px) for p in self.patches) / compared if compared else 0.0

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
    ``replane_steps``, as the pieces' were); several frames: on each held-out frame. ``before`` is the model's
    evaluation on ``held_frames`` (:class:`~ddsgen.diagnose.evaluation.Evaluation`) and ``floor_draws`` the units
    it averaged its floor over, so both evaluations report the same floor.
    """
    from ddsgen.diagnose.evaluation import evaluate
    from ddsgen.diagnose.plane import replaned

    split = len(frames) == 1
    whole = replaned(sensor, frames, seed, replane_steps) if split else held_frames
    patches = frame_patches(sensor, whole, seed)
    masks = {p.name: torch.from_numpy(p.mask) for p in patches}
    outside = [dataclasses.replace(h, region=h.region & ~masks[frames[0].name if split else h.name])
               for h in held_frames]  # fmt: skip
    return LocalReading(patches, before, evaluate(sensor, outside, seed, floor_draws=floor_draws))
