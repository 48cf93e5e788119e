"""Random tiles of the fit frames: one Adam step on a window of each frame instead of the whole image.

An Adam step on whole 640 x 480 frames costs a forward, the loss and a backward over every
pixel, most of which carry the same evidence as their neighbours. A step on a random
``tile x tile`` window of each frame is a stochastic gradient of the same loss at a fraction
of the price (a 192-px tile is 12 % of a 640 x 480 frame); over the steps the windows cover the
frames. A sub-window of a pinhole image is a pinhole image with a shifted principal point
(:func:`ddsgen.realscan.simulate.crop_intrinsics`), so a tile is simulated like ``compare --crop``
simulates a crop: the same geometry, parameters and noise law; only the placement of the dot
pattern on the window differs (the pattern is centred on each window), which no sensor
parameter depends on.

Tiles are centred on a random pixel of the frame's comparison region (so that they hold
evidence) and chosen from ``rng([seed, step, frame.index])``: the same seed gives the same tiles.
A border of ``block // 2 + 1`` px is left out of a tile's region (the matcher cannot match there,
the real sensor could), as in cropped frames; with an IR lens, the border its bent rays need
(:meth:`ddsgen.sensor.ir_lens.IRLens.usable`).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import torch

from ddsgen.realscan.simulate import FrameData, crop_intrinsics

#: The noise stream of tile positions (distinct from the IR noise streams).
TILE_STREAM = 4099


def tile_box(frame: FrameData, size: int, rng: np.random.Generator) -> tuple[int, int, int, int]:
    """(x0, y0, width, height) of a ``size`` x ``size`` window (clipped to the frame) around a random region pixel."""
    height, width = frame.shape
    tw, th = min(size, width), min(size, height)
    rows, cols = torch.nonzero(frame.region, as_tuple=True)
    if len(rows):
        k = int(rng.integers(len(rows)))
        cy, cx = int(rows[k]), int(cols[k])
    else:
        cy, cx = height // 2, width // 2
    x0 = min(max(cx - tw // 2, 0), width - tw)
    y0 = min(max(cy - th // 2, 0), height - th)
    return x0, y0, tw, th


def crop_frame(frame: FrameData, box: tuple[int, int, int, int], sensor=None) -> FrameData:
    """The sub-window ``box`` = (x0, y0, width, height) of a prepared frame; with ``sensor``, its region without the
    pixels the window's own IR image cannot match (:meth:`ddsgen.sensor.ir_lens.IRLens.usable`: a border of
    ``block // 2 + 1`` px, bent by the sensor's IR lens)."""
    x0, y0, w, h = box
    if (w, h) == (frame.shape[1], frame.shape[0]):
        return frame
    sl = (slice(y0, y0 + h), slice(x0, x0 + w))
    geometry = frame.geometry.cropped(x0, y0, w, h)
    intrinsics = crop_intrinsics(frame.intrinsics, box)
    region = frame.region[sl]
    if sensor is not None:
        region = region & sensor.ir_lens.usable(intrinsics, geometry.registration_shift_px, sensor.preset.block_size_px)
    instance = frame.instance[sl]
    fx0, fy0 = frame.crop[0], frame.crop[1]
    return dataclasses.replace(
        frame, intrinsics=intrinsics, crop=(fx0 + x0, fy0 + y0, w, h), geometry=geometry,
        instance=instance, real_depth=frame.real_depth[sl], real_valid=frame.real_valid[sl], region=region,
        object_region=region & (instance > 0), incidence_deg=frame.incidence_deg[sl], radius=frame.radius[sl],
        clean_depth=frame.clean_depth[sl], hit=frame.hit[sl],
    )  # fmt: skip


def step_tiles(frames: list[FrameData], size: int | None, step: int, seed: int, sensor) -> list[FrameData]:
    """The frames of one Adam step: each cut to a random ``size``-px tile (``None``/0: the whole frames), its region
    the pixels ``sensor`` can match from the tile alone (:func:`crop_frame`)."""
    if not size:
        return list(frames)
    out = []
    for frame in frames:
        rng = np.random.default_rng([int(seed), int(step), int(frame.index), TILE_STREAM])
        tile = crop_frame(frame, tile_box(frame, size, rng), sensor)
        out.append(tile if bool(tile.region.any()) else frame)
    return out
