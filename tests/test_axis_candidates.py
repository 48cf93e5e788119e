"""Generic axis terms cannot run away: a shape beyond the physical bounds, or one that does not lower the gap on the
frames it was fitted on, is a failed fit and never reaches the held-out frames."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import torch

from ddsgen.diagnose import axis_candidates
from ddsgen.diagnose.axis_candidates import DISPARITY_TERM, VALIDITY_TERM, FailedFit, fit_axis_candidate
from ddsgen.preset import load_preset
from ddsgen.sensor.depth_sensor import DepthSensor


@pytest.fixture
def stand_ins(monkeypatch):
    """The search's simulations replaced by a table: each scale of the shape gets the gap ``falls[scale]``."""
    falls = {}

    def with_effect(sensor, name, values):
        candidate = SimpleNamespace(effects=[SimpleNamespace(values=lambda: dict(values))], values=values)
        return candidate

    def relative_fall(base, evaluation):
        return falls[round(evaluation, 6)]

    monkeypatch.setattr(axis_candidates, "with_effect", with_effect)
    monkeypatch.setattr(axis_candidates, "replaned", lambda candidate, frames, seed: frames)
    monkeypatch.setattr(axis_candidates, "evaluate", lambda candidate, frames, seed: candidate.values["c0"])
    monkeypatch.setattr(axis_candidates, "relative_fall", relative_fall)
    return falls


def test_a_shape_at_its_bounds_is_a_failed_fit_and_is_not_evaluated(monkeypatch, stand_ins):
    sensor = DepthSensor(load_preset("kinect_v1_paper"))
    monkeypatch.setattr(axis_candidates, "validity_guess", lambda axis, frames, sims: [-6.2, -25.0, -10.0, -8.3, -7.9])
    result = fit_axis_candidate(sensor, VALIDITY_TERM, "incidence", [], SimpleNamespace(seed=0), None, [])
    assert isinstance(result, FailedFit) and "bounds" in result.reason
    assert not stand_ins  # nothing was simulated


def test_a_term_that_does_not_lower_the_fit_frames_gap_is_a_failed_fit(monkeypatch, stand_ins):
    sensor = DepthSensor(load_preset("kinect_v1_paper"))
    shape = [0.2, 0.1, 0.0, 0.0, 0.0]
    monkeypatch.setattr(axis_candidates, "disparity_guess", lambda axis, sensor, frames, sims: shape)
    config = SimpleNamespace(seed=0)
    stand_ins.update({round(m * 0.2, 6): -0.05 * m for m in axis_candidates.SCALES})  # every scale raises the gap
    failed = fit_axis_candidate(sensor, DISPARITY_TERM, "row", [], config, None, [])
    assert isinstance(failed, FailedFit) and "does not lower the gap" in failed.reason
    stand_ins.update({round(m * 0.2, 6): 0.3 - abs(m - 0.75) for m in axis_candidates.SCALES})  # best at 0.75
    candidate, values, score = fit_axis_candidate(sensor, DISPARITY_TERM, "row", [], config, None, [])
    assert values["c0"] == pytest.approx(0.15) and score == pytest.approx(-0.3)


def test_the_grazing_angle_is_read_off_where_the_real_frames_lose_the_models_valid_pixels():
    """Real frames that lose every pixel seen beyond 62 deg (and 3 % at random elsewhere): the guess is 62 deg within
    the 1-deg grid; frames that lose only random pixels give no guess (nothing along incidence to find), so the
    search never starts where it would remove more valid pixels than the frames miss."""

    from ddsgen.diagnose.candidates import grazing_angle_guess

    rng = np.random.default_rng(4)
    incidence = torch.tensor(rng.uniform(0.0, 85.0, (120, 160)), dtype=torch.float32)
    everywhere = torch.ones(120, 160, dtype=torch.bool)
    random_loss = torch.tensor(rng.random((120, 160)) < 0.03)

    def frame(real_valid):
        return SimpleNamespace(incidence_deg=incidence, region=everywhere, real_valid=real_valid)

    sims = [SimpleNamespace(valid=everywhere)]
    assert grazing_angle_guess([frame((incidence <= 62.0) & ~random_loss)], sims) == pytest.approx(62.0, abs=1.0)
    assert grazing_angle_guess([frame(~random_loss)], sims) is None
