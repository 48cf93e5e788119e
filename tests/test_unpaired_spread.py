"""The scene-content interval of the unpaired fit (ddsgen/fit/unpaired/spread.py) on made-up profiles."""

from __future__ import annotations

import numpy as np
import pytest

from ddsgen.fit.unpaired.parameters import UnpairedParameter
from ddsgen.fit.unpaired.spread import scene_content_interval, scene_content_scale, search_std

FALLOFF = UnpairedParameter("projector_falloff_exponent", 0.0, 16.0, log=False, grid=5, terms=("radius",))
INTENSITY = UnpairedParameter("emitted_intensity", 2.0e5, 5.0e7, grid=8)


def test_a_flat_profile_spans_the_whole_range_and_says_so():
    points = [0.0, 4.0, 8.0, 12.0, 16.0]
    totals = [2.23e-5, 2.23e-5, 2.2e-5, 2.17e-5, 2.04e-5]  # draw 1 of the hidden-device bench: 9 % over the range
    interval = scene_content_interval(FALLOFF, points, totals, fitted=16.0, scale=1e-5)
    assert (interval["low"], interval["high"]) == (0.0, 16.0) and interval["at_bound"]
    assert interval["std"] == pytest.approx(8.0)  # two sigma reach the far end


def test_a_sharp_profile_keeps_a_narrow_interval():
    points = [0.0, 4.0, 8.0, 10.0, 12.0, 16.0]
    totals = [0.05, 0.02, 0.004, 0.001, 0.004, 0.03]
    interval = scene_content_interval(FALLOFF, points, totals, fitted=10.0, scale=0.005)
    assert (interval["low"], interval["high"]) == (8.0, 12.0) and not interval["at_bound"]
    assert interval["std"] == pytest.approx(1.0)


def test_a_log_scale_key_has_its_spread_as_a_factor():
    interval = scene_content_interval(INTENSITY, [1e6, 2e6, 4e6, 8e6], [0.3, 0.1, 0.1, 0.3], fitted=2e6, scale=0.01)
    assert interval["std_search"] == pytest.approx(np.log(2) / 2)
    assert search_std(INTENSITY, [1e6, 4e6]) == pytest.approx(np.log(2))


def _frame(valid_share_outer: float) -> dict:
    """Per-frame features with only the radius rings filled (1000 px per ring; no grain measured)."""
    from ddsgen.fit.unpaired.features import DEPTH_EDGES, HOLE_SIZE_EDGES, NOISE_EDGES, RADIUS_EDGES

    rings = len(RADIUS_EDGES) - 1
    valid = np.full(rings, 1000, np.int64)
    valid[-1] = int(1000 * valid_share_outer)
    return {"noise": np.zeros((2, len(DEPTH_EDGES) - 1, len(NOISE_EDGES) - 1), np.int64),
            "holes": np.zeros((2, len(DEPTH_EDGES) - 1, len(HOLE_SIZE_EDGES) - 1), np.int64),
            "valid": np.zeros(len(DEPTH_EDGES) - 1, np.int64),
            "radius_valid": valid, "radius_all": np.full(rings, 1000, np.int64), "grain": np.zeros((2, 6))}  # fmt: skip


def test_the_scale_is_the_distance_between_the_two_halves_of_the_fit_scenes_scaled_to_the_pools():
    same = [_frame(0.5)] * 8
    assert scene_content_scale(FALLOFF, same, real_frames=16) == 0.0  # identical scenes: nothing to tell apart
    # The built-in list deals its frames in blocks of one scene type (4 tabletop, then 4 against a wall): the halves
    # are two scene types, the shift between scene lists that the bootstrap over frames cannot see.
    blocks = [_frame(0.4)] * 4 + [_frame(0.6)] * 4
    halves = FALLOFF.objective(_terms(blocks[:4], blocks[4:]))
    # 8 fit frames against 16 real: (1/8 + 1/16) / (1/4 + 1/4) of the half-against-half distance
    assert scene_content_scale(FALLOFF, blocks, real_frames=16) == pytest.approx(0.375 * halves)
    assert halves > 0


def _terms(a, b):
    from ddsgen.fit.unpaired.features import distance_terms, pool

    return distance_terms(pool(a), pool(b))
