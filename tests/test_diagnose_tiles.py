"""The diagnosis searches the library's depth effects on fixed tiles of its grid frames (ddsgen.diagnose.search_tiles):
four corners and the centre of each frame, windows that see the same surfaces at the same depths as the frame, and
a hidden disparity offset is found on them as on the whole frames."""

from __future__ import annotations

import pytest
import torch

from ddsgen.diagnose import DiagnoseConfig
from ddsgen.diagnose.candidates import fit_candidate
from ddsgen.diagnose.evaluation import evaluate
from ddsgen.diagnose.loop import search_set_of
from ddsgen.diagnose.plane import replaned
from ddsgen.diagnose.search_tiles import search_tiles, tile_boxes
from ddsgen.fit.simulate import prepare_frames, simulate
from ddsgen.io.scanfolder import read_scan_folder
from ddsgen.preset import save_preset
from ddsgen.sensor.depth_sensor import DepthSensor
from effects_geometry import small_preset

SCENES = __import__("pathlib").Path(__file__).with_name("diagnose_scenes.yaml")
#: Tile side for the 240 x 180 test frames: a third of their height, as 160 px is of the Kinect's 480 rows.
SIDE = 60
HIDDEN_OFFSET_PX = 0.3


@pytest.fixture(scope="module")
def offset_frames(tmp_path_factory):
    """(stock preset, 3 prepared 240 x 180 frames of a device with a hidden 0.3 px disparity offset)."""
    from ddsgen.runner import render_dataset

    torch.set_num_threads(2)
    root = tmp_path_factory.mktemp("tiles")
    stock = small_preset(240, 180, subpixel_level=3)
    save_preset(stock.replace(effects=[{"name": "disparity_offset", "offset_px": HIDDEN_OFFSET_PX}]), root / "t.yaml")
    render_dataset(str(root / "t.yaml"), str(SCENES), 3, str(root / "scans"), workers=1, seed=11, progress=False)
    return stock, prepare_frames(stock, read_scan_folder(root / "scans"), progress=False)


def test_tile_boxes_are_the_four_corners_and_the_centre():
    boxes = tile_boxes(480, 640, 160)
    assert boxes[:4] == [(0, 0, 160, 160), (480, 0, 160, 160), (0, 320, 160, 160), (480, 320, 160, 160)]
    x0, y0, w, h = boxes[4]
    assert (x0 + w / 2, y0 + h / 2) == (320, 240)


def test_search_tiles_are_windows_of_their_frame_and_small_frames_stay_whole(offset_frames):
    stock, frames = offset_frames
    block = stock.block_size_px
    tiles = search_tiles(frames, block, SIDE)
    assert 3 < len(tiles) <= 5 * len(frames)
    assert [t.index for t in tiles] == sorted(t.index for t in tiles)  # frame by frame, in order
    border = block // 2 + 1
    for tile in tiles:
        frame = next(f for f in frames if f.index == tile.index)
        x0, y0, w, h = tile.crop
        assert (w, h) == (SIDE, SIDE) and tile.intrinsics.cx == pytest.approx(frame.intrinsics.cx - x0)
        assert torch.equal(tile.real_depth, frame.real_depth[y0 : y0 + h, x0 : x0 + w])
        assert not bool(tile.region[:border].any()) and not bool(tile.region[:, -border:].any())
    # A frame less than three tiles tall is searched whole.
    assert search_tiles(frames, block, 61) == frames


def test_a_hidden_offset_is_found_on_the_tiles_as_on_the_whole_frames(offset_frames):
    """Searched on tiles (here 5 x 60 px of 240 x 180 frames, 42 % of the pixels), the disparity offset lands on the
    same quantisation-lattice value as searched on the whole frames, within one 1/8 px step of the hidden 0.3 px."""
    stock, frames = offset_frames
    config = DiagnoseConfig(refine_rounds=1)
    sensor = DepthSensor(stock)
    found = {}
    with torch.no_grad():
        whole = replaned(sensor, frames, config.seed)
        for label, search in (("whole", whole), ("tiles", search_tiles(whole, stock.block_size_px, SIDE))):
            sims = [simulate(sensor, f, config.seed) for f in search]
            base = evaluate(sensor, search, config.seed)
            _, values, score = fit_candidate(sensor, "disparity_offset", search, config, base, sims)
            found[label] = values["offset_px"]
            assert score < -0.2, f"{label}: the offset explains {-100 * score:.0f} % of the gap"
    print(f"\noffset found: {found}")
    assert found["tiles"] == pytest.approx(HIDDEN_OFFSET_PX, abs=0.125)
    assert found["tiles"] == pytest.approx(found["whole"], abs=0.125)


def test_only_the_librarys_depth_effects_are_searched_on_tiles():
    assert search_set_of("disparity_offset") == "tiles" and search_set_of("lens_distortion") == "tiles"
    assert search_set_of("edge_dropout") == "validity" and search_set_of("low_signal_dropout") == "validity"
    assert search_set_of("edge_keeping_matches") == "depth"  # a device behaviour that changes depth: whole frames
