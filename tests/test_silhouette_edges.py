"""Outline fattening and jitter (ddsgen.silhouette_edges) on depth images with known edges."""

from __future__ import annotations

import numpy as np
import pytest

from ddsgen.silhouette_edges import edge_offsets, edge_statistics

HEIGHT, WIDTH = 60, 100
LEFT, RIGHT = 30, 70  # the object's columns [LEFT, RIGHT)


def _scene():
    """A 1.0 m box, columns 30-69 of rows 5-54, before a wall at 1.5 m: (clean depth, instance)."""
    clean = np.full((HEIGHT, WIDTH), 1.5, np.float32)
    instance = np.zeros((HEIGHT, WIDTH), np.int32)
    clean[5:55, LEFT:RIGHT] = 1.0
    instance[5:55, LEFT:RIGHT] = 1
    return clean, instance


def test_fattening_and_jitter_of_known_edges():
    clean, instance = _scene()
    measured = clean.copy()
    for row in range(5, 55):
        left = LEFT - 2 - (1 if row % 2 else -1)  # carried 2 px past the left edge, +-1 px from row to row
        measured[row, left:RIGHT + 2] = 1.0  # and 2 px past the right edge, steadily
    offsets = edge_offsets(measured, measured > 0, clean, instance)
    assert set(offsets) == {(1, -1), (1, 1)}
    assert set(offsets[(1, 1)].values()) == {2.0}
    assert set(offsets[(1, -1)].values()) == {1.0, 3.0}
    stats = edge_statistics(measured, measured > 0, clean, instance)
    assert stats["edge_rows"] == 100
    assert stats["edge_fattening_px"] == pytest.approx(2.0)
    # Left rows alternate 1, 3 around their neighbours' mean 2 (jitter 1); right rows sit on theirs (0).
    assert stats["edge_jitter_px"] == pytest.approx(np.sqrt(0.5), abs=0.05)


def test_exact_edges_and_what_does_not_count():
    clean, instance = _scene()
    measured = clean.copy()
    stats = edge_statistics(measured, measured > 0, clean, instance)
    assert stats == {"edge_rows": 100, "edge_fattening_px": 0.0, "edge_jitter_px": 0.0}
    # A lone misread pixel outside is not the edge; an edge eroded by 3 px is -3 (inside).
    measured[10, LEFT - 5] = 1.0
    measured[20, LEFT : LEFT + 3] = 0.0
    offsets = edge_offsets(measured, measured > 0, clean, instance)[(1, -1)]
    assert offsets[10] == 0.0 and offsets[20] == -3.0
    # Rows whose background is not 3 cm farther, rows outside the region, and narrow rows are not outline rows.
    flat = clean.copy()
    flat[:, :LEFT] = 1.02
    assert (1, -1) not in edge_offsets(flat, flat > 0, flat, instance)
    region = np.ones_like(instance, bool)
    region[5:25] = False
    assert edge_statistics(clean, clean > 0, clean, instance, region)["edge_rows"] == 60
    narrow = np.zeros_like(instance)
    narrow[5:55, 45:52] = 1
    assert edge_statistics(clean, clean > 0, clean, narrow)["edge_rows"] == 0


def test_no_depth_as_far_as_it_looks_is_no_edge():
    """Object-like depth at the far end of the search (the object's neighbour as near as the object): left out."""
    clean, instance = _scene()
    measured = clean.copy()
    measured[30, : LEFT] = 1.0
    offsets = edge_offsets(measured, measured > 0, clean, instance)[(1, -1)]
    assert 30 not in offsets and 31 in offsets


# ------------------------------------------------------------------------------------------------ without ground truth


def _near_far(columns_of_rows, height=80, width=120, gap=0):
    """A near surface (1.0 m) right of column c(row), a far one (2.0 m) left of it, ``gap`` invalid px between."""
    depth = np.full((height, width), 2.0)
    for row, column in enumerate(columns_of_rows):
        depth[row, column:] = 1.0
        depth[row, max(column - gap, 0):column] = 0.0
    return depth


def test_outline_jitter_of_known_outlines():
    from ddsgen.silhouette_edges import outline_jitter

    rows = np.arange(80)
    straight = outline_jitter(_near_far(np.full(80, 50)))
    assert straight["outline_rows"] == 80 - 4 and straight["outline_jitter_px"] == 0.0  # 2 end rows lack neighbours
    # A slanted straight line on the pixel grid: the rounding only (about 1/sqrt(12) px).
    slanted = outline_jitter(_near_far(np.round(30 + 0.37 * rows).astype(int)))["outline_jitter_px"]
    assert 0.15 < slanted < 0.45
    # +-1 px from row to row about a straight line: 1 px; a projector shadow's hole between does not hide it.
    ragged = outline_jitter(_near_far(50 + np.where(rows % 2, 1, -1), gap=6))
    assert ragged["outline_jitter_px"] == pytest.approx(1.0, abs=0.05)
    # A horizontal outline is not a left or right outline; a region leaves outlines out.
    horizontal = np.full((80, 120), 2.0)
    horizontal[40:] = 1.0
    assert outline_jitter(horizontal)["outline_rows"] == 0
    region = np.zeros((80, 120), bool)
    assert outline_jitter(_near_far(np.full(80, 50)), region) == {"outline_rows": 0, "outline_jitter_px": None}
