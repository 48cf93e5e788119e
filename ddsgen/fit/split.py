"""Fit / held-out splits that test what a fit is for: a preset that works on *other* scenes.

Frames of one scene share objects, poses and clutter; a parameter fitted on some of them can
absorb what is particular to that scene (a pose error, an unmodelled object) and still look
better on the scene's other frames. So :func:`split_fit_held_out` holds out whole scenes:

* more than one scene (BOP scene folder, the part of a frame name before its last ``/``):
  ``round(holdout x scenes)`` scenes (at least 1, at most all but one), chosen by a seeded
  permutation -- ``"scene"``;
* one scene, several frames: ``round(holdout x frames)`` frames -- ``"frame"``;
* one frame: the frame's comparison region is tiled into square blocks dealt into two interleaved halves, so that
  each half holds as many of the annotated objects' pixels as the other (then as many of the rest), fit on one,
  held out on the other -- ``"spatial"`` (the same view: a weak test, reported as such). A cut into two
  contiguous halves could put an object at the image's edge almost wholly on one side, leaving the fit nothing
  of it to learn from or the held-out part nothing to judge by;
* ``holdout == 0``: every frame is both fit and held out -- ``"none"`` (in-sample).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import torch

from ddsgen.errors import InputError

#: What each split kind means, for reports.
SPLIT_MEANING = {
    "scene": "held-out frames are of other scenes (a real test of transfer)",
    "frame": "held-out frames are other frames of the same scene (optimistic: same objects and poses)",
    "spatial": "one frame: fit on half of its region's blocks, held out on the other half, the annotated objects' "
               "pixels shared equally (same view: optimistic)",
    "none": "no held-out frames: the gap is measured on the fit frames (in-sample)",
}


def scene_of(name: str) -> str:
    """The scene of a frame name ``SCENE/NNNNNN`` (the whole name if it has no ``/``)."""
    return name.rsplit("/", 1)[0]


def _count(holdout: float, n: int) -> int:
    k = int(round(holdout * n))
    return min(max(k, 1), n - 1)


def split_fit_held_out(frames: list, holdout: float, seed: int = 0) -> tuple[list, list, str]:
    """(fit frames, held-out frames, kind) -- see the module docstring.

    Args:
        frames: :class:`~ddsgen.realscan.simulate.FrameData` in folder order.
        holdout: fraction in [0, 1) of scenes (or frames) held out.
        seed: permutation seed.

    Raises:
        InputError: holdout outside [0, 1).
    """
    if not 0.0 <= holdout < 1.0:
        raise InputError(f"--holdout: must be in [0, 1), got {holdout}")
    if holdout == 0.0 or not frames:
        return list(frames), list(frames), "none"
    scenes = list(dict.fromkeys(scene_of(f.name) for f in frames))
    rng = np.random.default_rng(seed)
    if len(scenes) > 1:
        held_scenes = {scenes[i] for i in rng.permutation(len(scenes))[: _count(holdout, len(scenes))]}
        return ([f for f in frames if scene_of(f.name) not in held_scenes],
                [f for f in frames if scene_of(f.name) in held_scenes], "scene")  # fmt: skip
    if len(frames) > 1:
        held = set(rng.permutation(len(frames))[: _count(holdout, len(frames))].tolist())
        return ([f for i, f in enumerate(frames) if i not in held],
                [f for i, f in enumerate(frames) if i in held], "frame")  # fmt: skip
    fit_half, held_half = interleaved_halves(frames[0], seed)
    return [fit_half], [held_half], "spatial"


#: Blocks of a one-frame split per image height (side at least MIN_BLOCK_PX): small enough that both halves cover
#: the whole view and share an object between them, large enough that a matching window (9 px) and the bands at
#: depth edges mostly stay inside one block.
BLOCKS_PER_HEIGHT = 15
MIN_BLOCK_PX = 8


def _block_sums(mask: torch.Tensor, side: int) -> np.ndarray:
    """(rows, cols) count of ``mask``'s pixels in each ``side`` x ``side`` block (the last ones may be partial)."""
    h, w = mask.shape
    rows, cols = -(-h // side), -(-w // side)
    padded = np.zeros((rows * side, cols * side), np.int64)
    padded[:h, :w] = mask.numpy()
    return padded.reshape(rows, side, cols, side).sum(axis=(1, 3))


def interleaved_halves(frame, seed: int = 0) -> tuple:
    """Two copies of ``frame`` whose regions are disjoint sets of square blocks of its region (together all of it).

    Blocks are dealt largest first -- by the annotated objects' pixels, then by the region's -- each to the half that
    holds fewer of them so far (a tie to a seeded coin), so the halves are balanced in the objects' pixels to within
    about one block, and interleave across the whole view.
    """
    region, objects = frame.region, frame.object_region
    side = max(MIN_BLOCK_PX, int(round(region.shape[0] / BLOCKS_PER_HEIGHT)))
    object_px, region_px = _block_sums(objects, side), _block_sums(region, side)
    rng = np.random.default_rng([seed, 2024])
    tiebreak = rng.random(object_px.size)
    order = np.lexsort((tiebreak, -region_px.ravel(), -object_px.ravel()))
    totals = np.zeros((2, 2), np.int64)  # per half: object pixels, region pixels
    half_of = np.zeros(object_px.size, np.int64)
    for block in order:
        counts = np.array([object_px.flat[block], region_px.flat[block]])
        if not counts.any():
            continue
        column = 0 if counts[0] else 1
        lower = np.flatnonzero(totals[:, column] == totals[:, column].min())
        half = int(lower[0]) if len(lower) == 1 else int(rng.integers(2))
        half_of[block] = half
        totals[half] += counts
    labels = np.repeat(np.repeat(half_of.reshape(object_px.shape), side, 0), side, 1)
    first = torch.from_numpy(labels[: region.shape[0], : region.shape[1]] == 0)

    def half(mask, index):
        return dataclasses.replace(frame, name=f"{frame.name}#half{index}", region=region & mask,
                                   object_region=objects & mask)  # fmt: skip

    return half(first, 1), half(~first, 2)
