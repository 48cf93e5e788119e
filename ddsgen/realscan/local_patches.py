"""Local patches: the places where a real scan lies off the simulation by more than another unit of the
simulated sensor does.

A sensor effect is smooth along the image and with depth; a scene the model lacks (a support that is not
one plane, objects that are not modelled, their fringes) puts the disagreement in patches with edges of
their own. ``compare`` reports how much of its excess they carry; ``diagnose``
(:mod:`ddsgen.diagnose.local_patches`) reads them when no sensor axis explains what remains.

A patch is a connected set (one sign) of pixels whose *local offset* -- the mean of simulated minus real
depth (mm) over the ``compare`` window (15 px at the Kinect's focal length), where both are valid -- is
larger than another unit of the same simulated sensor shows on all but 0.1 % of its pixels: the threshold is
the :data:`TWIN_QUANTILE` quantile of the same local offset between the simulation and its twin
(:func:`~ddsgen.realscan.simulate.simulate_twin`), at least :data:`MIN_OFFSET_MM`. Patches smaller than
:data:`MIN_PATCH_WINDOWS` windows are dropped. Only depth offsets are read; holes in one map and not
the other are not patches.
"""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import torch

from ddsgen.realscan.losses import depth_compared, frame_gap_mm, masked_local_mean

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


def residual_mm(sim, region: torch.Tensor, depth: torch.Tensor, valid: torch.Tensor) -> np.ndarray:
    """(H, W) float64: simulated (``sim``, a SensorOutput) minus ``depth`` (m, (H, W)) in mm where both are valid
    (``valid``) inside ``region`` (bool (H, W)), NaN elsewhere."""
    both = (region & sim.valid & valid).numpy()
    diff = 1000.0 * (sim.depth.numpy().astype(np.float64) - depth.numpy().astype(np.float64))
    return np.where(both, diff, np.nan)


def patches_against(sim, frame, twin, window: int) -> FramePatches:
    """:func:`find_patches` of ``frame`` (FrameData; the pixels whose depth is compared:
    :func:`~ddsgen.realscan.losses.depth_compared`) from its simulation ``sim`` and one twin ``twin`` (SensorOutputs)."""
    compared = depth_compared(frame)
    return find_patches(frame.name, residual_mm(sim, compared, frame.real_depth, frame.real_valid),
                        residual_mm(sim, compared, twin.depth, twin.valid), window)  # fmt: skip


def patch_count(patches: list[FramePatches]) -> int:
    """Patches over all frames."""
    return sum(len(p.sizes_px) for p in patches)


def patch_share(patches: list[FramePatches]) -> float:
    """Fraction of the compared pixels (all frames) inside a patch; 0 without compared pixels."""
    compared = sum(p.compared_px for p in patches)
    return sum(sum(p.sizes_px) for p in patches) / compared if compared else 0.0


@dataclasses.dataclass
class PatchGap:
    """One frame's patches, and its gap and noise floors (against each twin) with the patches left out (mm)."""

    patches: FramePatches
    gap_without: float
    floors_without: list[float]


def patch_gap(sim, frame, twins: list, window: int) -> PatchGap:
    """:func:`find_patches` of one frame (``frame.region``: the pixels compared) against its first twin, and the
    ``compare`` gap and floors without them. ``twins``: SensorOutputs of other units (at least one)."""

    patches = patches_against(sim, frame, twins[0], window)
    outside = dataclasses.replace(frame, region=frame.region & ~torch.from_numpy(patches.mask))
    floors = [frame_gap_mm(sim, dataclasses.replace(outside, real_depth=t.depth, real_valid=t.valid)) for t in twins]
    return PatchGap(patches, frame_gap_mm(sim, outside), floors)


def patch_summary(rows: list[PatchGap], gap: float, floor: float) -> dict:
    """``comparison.json``'s ``local_patches``: count, share of the compared pixels, the gap, floor and excess
    without the patches (means over frames, mm) and the share of the excess ``gap - floor`` they carry."""
    found = [r.patches for r in rows]
    gap_without = float(np.mean([r.gap_without for r in rows]))
    floor_without = float(np.mean([np.mean(r.floors_without) for r in rows]))
    excess = gap - floor
    return {"patches": patch_count(found), "share": round(patch_share(found), 4),
            "gap_without": round(gap_without, 4), "noise_floor_without": round(floor_without, 4),
            "excess_without": round(gap_without - floor_without, 4),
            "carried": round(1.0 - (gap_without - floor_without) / excess, 4) if excess > 0 else 0.0,
            "offsets_mm": [round(o, 2) for r in rows for o in r.patches.offsets_mm]}  # fmt: skip


def patch_line(summary: dict) -> str:
    """The ``compare`` table's line about the local patches."""
    if not summary["patches"]:
        return "local patches: none (no connected area where the real depth lies off more than another unit's)"
    return (f"local patches: {summary['patches']} over {100 * summary['share']:.0f} % of the compared pixels, where "
            f"the real depth lies off more than another unit's does, carry {100 * summary['carried']:.0f} % of the "
            f"excess (without them: gap {summary['gap_without']:.2f} mm, excess {summary['excess_without']:.2f} mm); "
            f"outlined on the difference pictures; `ddsgen diagnose` tells a scene the model lacks from a sensor "
            f"effect")  # fmt: skip
