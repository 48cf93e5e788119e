"""Fixed tiles of the search frames: the library's depth effects are searched on five windows of each grid frame.

A depth candidate's trial re-plans and re-simulates its search frames (the re-plane, the simulation and its twin:
three simulations per frame), and the matcher's cost grows with the pixels. The evidence a depth effect leaves is
spread over the image (an offset or a scale error on every object, a lens distortion growing toward the corners), so
five :data:`SEARCH_TILE_PX` windows per frame carry it: the four corners, where a lens distortion is strongest, and
the centre, where the objects are. At 640 x 480 they hold 42 % of the pixels.

Measured on ``bench/bench_diagnose.py``'s frames (hidden 0.3 px offset; session 29, ``fit_candidate`` on the four
grid frames whole vs on their tiles, each result judged on the whole held-out frames as the diagnosis judges it):

===================  =================  ==========================  ===============================
candidate            time, tiles/whole  value, whole -> tiles       credited held-out fall
===================  =================  ==========================  ===============================
disparity_offset     0.62               0.2687 -> 0.2687 px         +46.9 -> +48.6 %
depth_scale          0.65               -0.0088 -> -0.0094          +45.4 -> +46.2 %
lens_distortion      0.53               k1 -0.0030 -> -0.0007       +0.6 -> +1.3 % (not in the data)
===================  =================  ==========================  ===============================

(Less than the pixel share: each simulation has a fixed cost and a tile's IR image its margins.) The candidates are
still *judged* on whole held-out frames; only their search sees tiles. Frames less than :data:`MIN_TILES_ACROSS`
tiles tall or wide are searched whole: their tiles would overlap, and their searches are cheap anyway.

A tile is a pinhole image of its own (:func:`ddsgen.fit.tiles.crop_frame`): the same geometry, support plane,
parameters and noise law, its region without the matcher's border; it keeps its frame's index (its noise seed).
"""

from __future__ import annotations

from ddsgen.fit.simulate import FrameData
from ddsgen.fit.tiles import crop_frame

#: Side (px) of a search tile: a third of the Kinect's 480 rows.
SEARCH_TILE_PX = 160
#: Frames are tiled only when they are at least this many tiles tall and wide.
MIN_TILES_ACROSS = 3
#: A tile whose comparison region holds fewer pixels than this share of it is left out (it carries no evidence).
MIN_REGION_SHARE = 0.05


def tile_boxes(height: int, width: int, size: int = SEARCH_TILE_PX) -> list[tuple[int, int, int, int]]:
    """(x0, y0, width, height) of the five search tiles of an image: the four corners, then the centre."""
    right, bottom = width - size, height - size
    corners = [(0, 0), (right, 0), (0, bottom), (right, bottom), (right // 2, bottom // 2)]
    return [(x0, y0, size, size) for x0, y0 in corners]


def tiles_apply(frame: FrameData, size: int = SEARCH_TILE_PX) -> bool:
    """Whether ``frame`` is large enough to be searched on tiles (see :data:`MIN_TILES_ACROSS`)."""
    height, width = frame.shape
    return min(height, width) >= MIN_TILES_ACROSS * size


def search_tiles(frames: list[FrameData], block_px: int, size: int = SEARCH_TILE_PX) -> list[FrameData]:
    """The search tiles of ``frames`` (frame by frame, in order), or a frame itself when it is too small to tile.

    Args:
        frames: prepared frames (re-planed under the current model).
        block_px: the matcher's block size; a tile's region leaves out ``block_px // 2 + 1`` px at its border.
        size: tile side (px).
    """
    out = []
    for frame in frames:
        if not tiles_apply(frame, size):
            out.append(frame)
            continue
        for box in tile_boxes(*frame.shape, size):
            tile = crop_frame(frame, box, block_px // 2 + 1)
            if int(tile.region.sum()) >= MIN_REGION_SHARE * size * size:
                out.append(tile)
    return out or list(frames)
