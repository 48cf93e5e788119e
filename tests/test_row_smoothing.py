"""The device's disparity smoothing along the rows (ddsgen.sensor.row_smoothing)."""

import numpy as np
import pytest
import torch

from ddsgen.sensor.row_smoothing import smooth_along_rows


def _correlation(a: np.ndarray, b: np.ndarray) -> float:
    a, b = a - a.mean(), b - b.mean()
    return float((a * b).sum() / np.sqrt((a * a).sum() * (b * b).sum()))


def test_white_noise_gets_the_grain_of_the_three_taps_along_the_rows_only():
    """Weights [1/4, 1/2, 1/4] on white noise: row neighbours correlate 2 w (1 - 2w) / ((1 - 2w)^2 + 2 w^2) = 2/3,
    column neighbours not at all, and the variance falls to 3/8."""
    noise = torch.from_numpy(np.random.default_rng(0).normal(0.0, 0.1, (200, 300)))
    disparity = 40.0 + noise
    out = smooth_along_rows(disparity, torch.ones_like(disparity, dtype=torch.bool), 0.25, None).numpy() - 40.0
    inner = out[:, 1:-1]
    assert _correlation(inner[:, 1:], inner[:, :-1]) == pytest.approx(2 / 3, abs=0.02)
    assert abs(_correlation(inner[1:], inner[:-1])) < 0.02
    assert inner.var() / noise.numpy().var() == pytest.approx(3 / 8, rel=0.03)


def test_the_device_averages_its_sub_pixel_matches_and_quantises_once():
    """A near surface (60 px) beside a far one (40 px) and a hole, w = 0.2, quantum 1/8 px: every pixel keeps its
    own surface's disparity, the invalid pixel is only quantised, and all land on the quantum. A match at 40.07 px
    among neighbours at 40 averages to 40.042 and rounds to 40; rounded first (40.125) it would have stayed there
    (40.075 rounds back up): the average acts below the quantum."""
    disparity = torch.full((4, 12), 40.0, dtype=torch.float64)
    disparity[:, 6:] = 60.0
    disparity[:, 2] += 0.07
    valid = torch.ones_like(disparity, dtype=torch.bool)
    valid[:, 9] = False
    disparity[:, 9] = 3.3
    out = smooth_along_rows(disparity, valid, 0.2, 0.125)
    assert torch.equal(torch.round(out * 8), out * 8)
    assert torch.equal(out[:, 6:9], disparity[:, 6:9]) and torch.equal(out[:, 10:], disparity[:, 10:])
    assert torch.all(out[:, 9] == 3.25) and torch.equal(out[:, 5], disparity[:, 5])
    assert torch.all(out[:, :6] == 40.0)
    rounded_first = torch.round(disparity * 8) / 8
    assert torch.all(smooth_along_rows(rounded_first, valid, 0.2, 0.125)[:, 2] == 40.125)


def test_zero_weight_is_the_identity_and_the_gradient_is_the_transposed_filter():
    """w = 0 returns the input itself; without the quantum the map is linear, so autograd matches finite differences
    (float64 gradcheck), edges and holes included."""
    disparity = torch.tensor([[40.0, 40.2, 40.1, 55.0, 55.3, 0.0, 41.0]], dtype=torch.float64)
    valid = disparity > 0
    assert smooth_along_rows(disparity, valid, 0.0, 0.125) is disparity
    x = disparity.clone().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda d: smooth_along_rows(d, valid, 0.3, None), (x,))


@pytest.mark.parametrize("weight, quantum", [(0.16, 0.125), (0.25, 0.25), (0.5, None), (torch.tensor(0.37), 0.125)])
def test_the_c_smoothing_is_the_torch_definition_bit_for_bit(monkeypatch, weight, quantum):
    """ddsgen/csrc/row_smoothing.c gives the torch definition's float32 disparities bit for bit: surfaces 0.9-1.1 px
    apart (both sides of the same-surface test), holes, rows' first and last pixels, values on and off the quantum's
    half steps."""
    from ddsgen.sensor import row_smoothing

    if row_smoothing._library() is None:
        pytest.skip("no C compiler: the torch definition is the only path")
    rng = np.random.default_rng(3)
    steps = rng.choice([0.0, 0.9, 1.0, 1.1, 20.0], size=(60, 80)).cumsum(axis=1) % 90
    disparity = torch.from_numpy((5.0 + steps + rng.normal(0.0, 0.2, steps.shape)).astype(np.float32))
    disparity[:, ::7] = torch.round(disparity[:, ::7] * 16) / 16  # exact half and whole quantum steps
    valid = torch.from_numpy(rng.random(steps.shape) > 0.15)
    with torch.no_grad():
        fast = smooth_along_rows(disparity, valid, weight, quantum)
        monkeypatch.setattr(row_smoothing, "_library", lambda: None)
        definition = smooth_along_rows(disparity, valid, weight, quantum)
    assert not torch.equal(fast, disparity)
    assert torch.equal(fast, definition)
