"""One real frame is enough: split it spatially into fit and held-out pieces.

A diagnosis needs held-out data (every gap is measured there) and several held-out units (the
bootstrap of the acceptance rule resamples them). With a single scan the units are pieces of it:
the image is tiled into square blocks, and the blocks are dealt at random (seeded) into
:data:`PIECES` groups. Each piece is the frame itself with its comparison region restricted to
its blocks, so every piece sees the whole field of view -- centre and corners, object and support
plane -- and an effect fitted on some pieces must predict the others' pixels. The pieces of a
frame share its geometry and noise draws (same frame index); only the pixels that count differ.

:func:`split_single_frame` holds some pieces out and merges the others into one fit frame (the fit
then simulates the frame once per step, not once per piece).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import torch

#: Pieces a single frame is dealt into (with the default hold-out of 1/3: 5 fit, 3 held out, like 8 frames).
PIECES = 8
#: Blocks per image height (block side = height / this, at least MIN_BLOCK_PX): small enough that every piece
#: covers the whole image, large enough that the matching window (9 px) and the edge bands stay inside a block.
BLOCKS_PER_HEIGHT = 15
MIN_BLOCK_PX = 8


def block_labels(height: int, width: int, pieces: int, seed: int) -> np.ndarray:
    """(H, W) int piece label of every pixel: square blocks dealt into ``pieces`` groups of equal count.

    The blocks are shuffled (seeded) and dealt round-robin, so the groups differ in size by at most one block.
    """
    side = max(MIN_BLOCK_PX, int(round(height / BLOCKS_PER_HEIGHT)))
    rows, cols = -(-height // side), -(-width // side)
    order = np.random.default_rng([seed, 1515]).permutation(rows * cols)
    labels = np.empty(rows * cols, np.int64)
    labels[order] = np.arange(rows * cols) % pieces
    grid = labels.reshape(rows, cols)
    return np.repeat(np.repeat(grid, side, 0), side, 1)[:height, :width]


def spatial_pieces(frame, pieces: int = PIECES, seed: int = 0) -> list:
    """``frame`` as ``pieces`` frames whose comparison regions are disjoint block sets covering its region.

    Piece names are ``NAME#k`` (k = 0 .. pieces - 1); everything but ``region`` / ``object_region`` is shared.
    """
    labels = torch.from_numpy(block_labels(*frame.shape, pieces, seed))
    out = []
    for k in range(pieces):
        mask = labels == k
        out.append(dataclasses.replace(frame, name=f"{frame.name}#{k}", region=frame.region & mask,
                                       object_region=frame.object_region & mask))  # fmt: skip
    return out


def split_single_frame(frame, holdout: float, seed: int = 0, pieces: int = PIECES) -> tuple[list, list]:
    """(fit, held-out) of one frame: ``round(holdout * pieces)`` pieces (at least 2) held out, the rest merged
    into a single fit frame named ``NAME#fit``."""
    parts = spatial_pieces(frame, pieces, seed)
    n_held = min(max(int(round(holdout * pieces)), 2), pieces - 1)
    order = np.random.default_rng([seed, 1516]).permutation(pieces)
    held = [parts[i] for i in sorted(order[:n_held].tolist())]
    rest = [parts[i] for i in sorted(order[n_held:].tolist())]
    region = torch.stack([p.region for p in rest]).any(0)
    fit = dataclasses.replace(frame, name=f"{frame.name}#fit", region=region, object_region=frame.object_region & region)
    return [fit], held


def split_note(frame, fit: list, held: list, pieces: int = PIECES) -> str:
    """The sentence the report gives about a spatial split."""
    h, w = frame.shape
    side = max(MIN_BLOCK_PX, int(round(h / BLOCKS_PER_HEIGHT)))
    return (f"One frame only: it was split spatially into {pieces} pieces of {side} x {side} px blocks dealt at "
            f"random over the whole image ({w} x {h} px), {len(held)} pieces held out and the other "
            f"{pieces - len(held)} fitted together; fit and held-out parts are disjoint pixel sets of that "
            f"frame, so the held-out gaps measure how well an effect fitted on some pixels predicts the others, "
            f"not another scene.")  # fmt: skip
