"""The noise study's lateral noise: a board's vertical edges against a fitted line (ddsgen.study.lateral).

The measurement is checked on edges with known wander (a rounded slanted line, Gaussian jitter, an outlier row),
on the ray cast's own clean edges (no sensor: no lateral noise beyond the pixel grid) and on the device sensor,
whose edges before a wall wander by about a pixel, as a real Kinect V1's do (Nguyen 2012: 0.8 px).
"""

from __future__ import annotations

import numpy as np
import pytest

from ddsgen.preset import load_preset
from ddsgen.study.lateral import (
    EDGE_OFFSET,
    LateralAccumulator,
    board_edges,
    board_scene,
    edge_columns,
    line_residuals,
    nguyen_lateral_px,
    plane_depth,
    run_lateral_study,
    wall_depth,
)
from ddsgen.study.noise import study_intrinsics

ROWS = 96  # a centred crop: the same edges on fewer rows


def test_nguyen_lateral_curve():
    assert float(nguyen_lateral_px(0.0)) == pytest.approx(0.8)
    assert float(nguyen_lateral_px(60.0)) == pytest.approx(0.8 + 0.035 * (np.pi / 3) / (np.pi / 6))
    values = nguyen_lateral_px([0, 30, 60, 75, 85])
    assert np.all(np.diff(values) > 0)  # grows towards grazing


def test_line_residuals_of_known_edges():
    rng = np.random.default_rng(0)
    rows = np.arange(400)
    exact = 100.0 + 0.37 * rows
    # A straight line on the pixel grid: the rounding error alone, uniform over a pixel (1 / sqrt(12) px).
    rounded = line_residuals(rows, np.round(exact))
    assert np.sqrt(np.mean(rounded**2)) == pytest.approx(1 / np.sqrt(12), abs=0.03)
    # Gaussian wander of 1 px, rounded: sqrt(1 + 1/12) px.
    jittered = line_residuals(rows, np.round(exact + rng.normal(0.0, 1.0, rows.size)))
    assert np.sqrt(np.mean(jittered**2)) == pytest.approx(np.sqrt(1 + 1 / 12), rel=0.1)
    # One row 30 px off does not tilt the line (the others stay within the rounding) but is counted.
    columns = np.round(exact)
    columns[200] += 30
    residual = line_residuals(rows, columns)
    assert residual[200] == pytest.approx(30, abs=0.6)
    assert np.abs(np.delete(residual, 200)).max() < 0.6


def test_board_edges_are_the_outermost_board_pixels_near_the_true_edges():
    width, wall = 200, 3.0
    plane = np.full(width, 1.0)
    depth = np.full((4, width), wall)
    depth[:, 50:150] = 1.0
    valid = np.ones((4, width), bool)
    valid[1, 51:60] = False  # holes on the board near its edges do not move them
    valid[1, 140:149] = False
    depth[2, 45] = 1.05  # a wall pixel misread near the board's depth, within reach: the edge as a user sees it
    depth[2, 10] = 1.0  # ... and one far beyond reach: ignored
    valid[3, 30:170] = False  # no board pixel within reach: no edge in that row
    left, right = board_edges(depth, valid, plane, wall, true_left=49.5, true_right=149.5, reach=16)
    assert list(left[:3]) == [50, 50, 45] and list(right[:3]) == [150, 150, 150]
    assert np.isnan(left[3]) and np.isnan(right[3])


@pytest.fixture(scope="module")
def device_and_intrinsics():
    preset = load_preset("kinect_v1")
    return preset, study_intrinsics(preset, ROWS)


def test_board_edges_where_set_up_and_wall_behind(device_and_intrinsics):
    """The ray cast's own depth: edges at cx -+ EDGE_OFFSET W, straight (no lateral noise but the grid's)."""
    from ddsgen.sensor.sensor_cast import cast_for_sensor

    preset, intrinsics = device_and_intrinsics
    for z, angle in ((1.0, 0.0), (2.0, 45.0)):
        hits, _ = cast_for_sensor(board_scene(z, angle, intrinsics, 0.8), intrinsics, preset)
        depth = np.asarray(hits.depth, dtype=np.float64)
        assert np.nanmax(np.where(hits.hit, depth, np.nan)) == pytest.approx(wall_depth(z, angle, intrinsics), rel=1e-4)
        true_left, true_right = edge_columns(z, angle, intrinsics)
        assert true_left == pytest.approx(intrinsics.cx - EDGE_OFFSET * intrinsics.width)
        left, right = board_edges(depth, np.asarray(hits.hit), plane_depth(z, angle, intrinsics),
                                  wall_depth(z, angle, intrinsics), true_left, true_right)  # fmt: skip
        offset = EDGE_OFFSET * intrinsics.width
        assert np.abs(left - (intrinsics.cx - offset)).max() <= 1.0, (z, angle)
        assert np.abs(right - (intrinsics.cx + offset)).max() <= 1.0, (z, angle)
        accumulator = LateralAccumulator(z, angle, intrinsics)
        accumulator.add(depth, np.asarray(hits.hit))
        clean = accumulator.result()
        assert clean.left_px < 0.3 and clean.right_px < 0.3, clean
        assert abs(clean.left_fattening_px) <= 0.5 and abs(clean.right_fattening_px) <= 0.5, clean  # the grid only


def test_device_edges_wander_by_about_a_pixel_and_fatten(device_and_intrinsics):
    """Through the device sensor the edges wander (the correlation window's decision follows the dots it sees):
    clearly more than the clean edges' grid error, of the order of a real Kinect's 0.8 px. And the board is carried
    past its edges onto the wall by a few pixels, as a real Kinect carries a partition 2.4 m away past its edges
    over a background at 7-8 m (TUM frame against its RGB edges: about 3 px a side, docs/validation.md)."""
    preset, _ = device_and_intrinsics
    points = run_lateral_study(preset, [1.0, 2.0], [0.0], frames=2, rows=ROWS)
    for point in points:
        assert point.rows == 2 * 2 * (ROWS // 2), point  # both edges found in every measured row
        assert 0.4 < point.lateral_px < 2.5, point
        assert 1.0 < point.left_fattening_px < 5.0 and 1.0 < point.right_fattening_px < 5.0, point


def test_no_lateral_writes_the_axial_study_only(tmp_path):
    import json

    from ddsgen.cli import main

    out = tmp_path / "o"
    code = main(["study", "noise", "kinect_v1", "--z", "1", "--angles", "0", "--frames", "1", "--rows", "48",
                 "--no-lateral", "--out", str(out), "--quiet"])  # fmt: skip
    assert code == 0
    assert list(json.loads((out / "noise.json").read_text())) == ["points", "verdict"]
    assert "Lateral noise" not in (out / "noise_table.md").read_text()


def test_an_edge_over_empty_space_is_carried_like_one_over_a_far_wall(device_and_intrinsics):
    """kinect_v1 has no mask of where rays meet nothing (``no_hit_always_invalid: false``): a window at the board's
    edge that still holds its dots keeps its depth, so the board is carried past its edges over empty space and its
    edges wander, as before a wall; with the ray cast's mask (the paper's) they stay straight at the true edge. Empty
    space itself stays without depth."""
    import dataclasses

    import torch

    from ddsgen.sensor.depth_sensor import DepthSensor
    from ddsgen.sensor.sensor_cast import cast_for_sensor

    device, intrinsics = device_and_intrinsics
    assert not device.no_hit_always_invalid
    scene = dataclasses.replace(board_scene(1.5, 0.0, intrinsics, 0.8), background=[])
    empty = dataclasses.replace(scene, objects=[])
    results = {}
    for masked in (False, True):
        preset = dataclasses.replace(device, no_hit_always_invalid=masked)
        sensor = DepthSensor(preset, intrinsics=intrinsics).eval()
        _, geometry = cast_for_sensor(scene, intrinsics, preset)
        accumulator = LateralAccumulator(1.5, 0.0, intrinsics)
        with torch.no_grad():
            for seed in range(2):
                out = sensor(geometry, seed=[seed])
                accumulator.add(out.depth.numpy(), out.valid.numpy())
            nothing = sensor(cast_for_sensor(empty, intrinsics, preset)[1], seed=[0])
        assert not nothing.valid.any()
        results[masked] = accumulator.result()
    free, masked = results[False], results[True]
    assert free.fattening_px > 1.5 and free.lateral_px > 0.5, free
    assert masked.fattening_px < 1.0 and masked.lateral_px < 0.5, masked
