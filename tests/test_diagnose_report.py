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
