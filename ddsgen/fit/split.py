"""Fit / held-out splits that test what a fit is for: a preset that works on *other* scenes.

Frames of one scene share objects, poses and clutter; a parameter fitted on some of them can
absorb what is particular to that scene (a pose error, an unmodelled object) and still look
better on the scene's other frames. So :func:`split_fit_held_out` holds out whole scenes:

* more than one scene (BOP scene folder, the part of a frame name before its last ``/``):
  ``round(holdout x scenes)`` scenes (at least 1, at most all but one), chosen by a seeded
  permutation -- ``"scene"``;
* one scene, several frames: ``round(holdout x frames)`` frames -- ``"frame"``;
* one frame: the frame's comparison region is cut in two halves of equal pixel count along
  its longer side, fit on one, held out on the other -- ``"spatial"`` (the same view: a weak
  test, reported as such);
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
    "spatial": "one frame: fit on one half of its region, held out on the other half (same view: optimistic)",
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
    fit_half, held_half = spatial_halves(frames[0])
    return [fit_half], [held_half], "spatial"


def spatial_halves(frame) -> tuple:
    """Two copies of ``frame`` whose regions are the two halves (equal pixel counts) of its region,
    cut across its longer extent (left | right or top | bottom)."""
    region = frame.region
    ys, xs = torch.nonzero(region, as_tuple=True)
    if ys.numel() < 2:
        return frame, frame
    along_x = int(xs.max() - xs.min()) >= int(ys.max() - ys.min())
    coords = xs if along_x else ys
    cut = int(torch.sort(coords).values[coords.numel() // 2])  # the first column (row) of the second half
    grid = torch.arange(region.shape[1] if along_x else region.shape[0])
    first = (grid < cut)[None, :] if along_x else (grid < cut)[:, None]
    first = first.expand_as(region)

    def half(mask, side):
        return dataclasses.replace(frame, name=f"{frame.name}#{side}", region=frame.region & mask,
                                   object_region=frame.object_region & mask)  # fmt: skip

    return half(first, "left" if along_x else "top"), half(~first, "right" if along_x else "bottom")
