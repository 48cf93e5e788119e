"""The diagnose report's figures: residual maps at the frame's full resolution, with a colour scale in millimetres."""

from __future__ import annotations

import cv2
import numpy as np

from ddsgen.diagnose.maps import ResidualMap
from ddsgen.diagnose.report import NOT_COMPARED_RGB, REAL_ONLY_RGB, SIM_ONLY_RGB, residual_map_figure

HEIGHT, WIDTH = 96, 128


def synthetic_map(offset_mm: float) -> ResidualMap:
    """Left half: sim deeper than real by ``offset_mm``; right half: shallower; a block only the real scan sees,
    a block only the simulation sees, and a border outside the compared region."""
    residual = np.full((HEIGHT, WIDTH), offset_mm, np.float32)
    residual[:, WIDTH // 2 :] = -offset_mm
    region = np.zeros((HEIGHT, WIDTH), bool)
    region[8:-8, 8:-8] = True
    real_only = np.zeros_like(region)
    real_only[20:30, 20:30] = True
    sim_only = np.zeros_like(region)
    sim_only[60:70, 90:100] = True
    residual[~region | real_only | sim_only] = np.nan
    return ResidualMap("scan/000001", residual, real_only, sim_only, region)


def test_residual_map_is_drawn_pixel_for_pixel_with_signed_colours(tmp_path):
    path = tmp_path / "map.png"
    boxes = residual_map_figure([("base", synthetic_map(5.0)), ("final", synthetic_map(1.0))], path, "frame")
    image = cv2.cvtColor(cv2.imread(str(path)), cv2.COLOR_BGR2RGB).astype(float) / 255.0
    assert len(boxes) == 2 and boxes[0][2] <= boxes[1][0], "two panels side by side"
    panels = []
    for x0, y0, x1, y1 in boxes:
        assert (x1 - x0, y1 - y0) == (WIDTH, HEIGHT), "one PNG pixel per frame pixel"
        panel = image[y0:y1, x0:x1]
        left, right = panel[50, 40], panel[50, 80]
        assert left[0] > left[2] + 0.1 and right[2] > right[0] + 0.1, "sim deeper is red, shallower blue"
        np.testing.assert_allclose(panel[25, 25], REAL_ONLY_RGB, atol=0.02)
        np.testing.assert_allclose(panel[65, 95], SIM_ONLY_RGB, atol=0.02)
        np.testing.assert_allclose(panel[2, 2], NOT_COMPARED_RGB, atol=0.02)
        # a pixel-sharp map: the edge of the real-only block is one pixel wide
        np.testing.assert_allclose(panel[25, 20], REAL_ONLY_RGB, atol=0.02)
        assert np.abs(panel[25, 19] - np.asarray(REAL_ONLY_RGB)).max() > 0.2
        panels.append(panel)
    # one colour scale for both: the 1 mm residual is paler than the 5 mm one
    base, final = panels[0][50, 40], panels[1][50, 40]
    assert (base[0] - base[2]) > (final[0] - final[2]) > 0


def test_a_small_region_is_cropped_enlarged_and_keeps_its_place(tmp_path):
    """With --region objects one object is a small patch of the frame: the map shows the region's box (plus a
    margin), each pixel enlarged by a whole factor, the axes in the frame's own pixel coordinates."""
    from ddsgen.diagnose.maps import CROP_MARGIN_PX, crop_zoom, region_box

    whole = synthetic_map(5.0)
    assert region_box([whole]) is None, "a region over most of the frame: the whole map"
    small = synthetic_map(5.0)
    small.region[:] = False
    small.region[40:60, 30:50] = True  # a 20 x 20 px object
    small.residual_mm[~small.region] = np.nan  # as residual_maps writes it
    small.real_only[:] = small.sim_only[:] = False
    box = region_box([small])
    m = CROP_MARGIN_PX
    assert box == (30 - m, 40 - m, 50 + m, 60 + m)
    crop = small.cropped(box)
    assert crop.origin == (30 - m, 40 - m) and crop.residual_mm.shape == (20 + 2 * m, 20 + 2 * m)
    np.testing.assert_array_equal(crop.region, small.region[40 - m : 60 + m, 30 - m : 50 + m])
    path = tmp_path / "crop.png"
    assert crop_zoom(crop.residual_mm.shape[1]) == 4 and crop_zoom(640) == 1
    (x0, y0, x1, y1), = residual_map_figure([("base", crop)], path, "frame", zoom=4)
    zoom = (x1 - x0) // crop.residual_mm.shape[1]
    assert zoom == 4 and (x1 - x0, y1 - y0) == (4 * (20 + 2 * m), 4 * (20 + 2 * m)), "enlarged 4x, pixel for pixel"
    image = cv2.cvtColor(cv2.imread(str(path)), cv2.COLOR_BGR2RGB).astype(float) / 255.0
    panel = image[y0:y1, x0:x1]
    inside, outside = panel[4 * (m + 10), 4 * (m + 5)], panel[2, 2]  # frame pixel (45, 50): compared; a margin pixel
    assert inside[0] > inside[2] + 0.1, "the compared residual (+5 mm, left half) is red"
    np.testing.assert_allclose(outside, NOT_COMPARED_RGB, atol=0.02)
