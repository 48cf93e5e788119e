"""The generated dot pattern: Kinect-like statistics and rows free of ambiguous windows."""

import cv2
import numpy as np
import pytest
import torch

from ddsgen.preset import PATTERN_DIR, load_preset
from ddsgen.sensor.pattern import (
    PatternField,
    fit_pattern,
    generate_pattern,
    load_pattern,
    pattern_requirements,
    pattern_statistics,
)


def test_generated_pattern_is_kinect_like_and_unambiguous_within_the_disparity_range():
    image = generate_pattern(390, 150, seed=3, block=9, max_shift=60, tiles=(3, 3))
    stats = pattern_statistics(image, block=9, max_shift=60)
    assert 0.10 <= stats["lit_fraction"] <= 0.125  # real Kinect V1: 11.1 %
    assert stats["second_best_zncc_max"] <= 0.75  # every window has a clear best match
    # Tiles repeat (like the real device) only beyond the disparity range:
    assert np.array_equal(image[:50, 10:120], image[:50, 140:250])
    # Like the real pattern, ordinary dots never touch, not even diagonally.
    dots = (image == image[image > 0].min()).astype(np.uint8)
    neighbours = cv2.filter2D(dots, -1, np.ones((3, 3), np.float32), borderType=cv2.BORDER_CONSTANT)
    assert (neighbours[dots > 0] == 1).mean() > 0.97  # (tile seams and markers may break the rule)
    # Centre markers are brighter than ordinary dots.
    assert image.max() == 255 and np.median(image[image > 0]) < 255


def test_same_seed_same_pattern_other_seed_other_pattern():
    a = generate_pattern(300, 90, seed=1, max_shift=40)
    assert np.array_equal(a, generate_pattern(300, 90, seed=1, max_shift=40))
    assert not np.array_equal(a, generate_pattern(300, 90, seed=2, max_shift=40))


def test_random_pattern_without_repair_is_worse():
    rng = np.random.default_rng(0)
    raw = (rng.random((150, 390)) < 0.11).astype(np.uint8) * 180
    repaired = generate_pattern(390, 150, seed=0, block=9, max_shift=60, tiles=(1, 1))
    assert pattern_statistics(raw, 9, 60)["second_best_zncc_max"] > pattern_statistics(repaired, 9, 60)[
        "second_best_zncc_max"]


@pytest.mark.parametrize("preset_name", ["kinect_v1", "matterport_pro2"])
def test_shipped_assets_cover_the_sensor(preset_name):
    preset = load_preset(preset_name)
    asset = load_pattern(PATTERN_DIR / preset.pattern)
    need = pattern_requirements(preset)
    assert asset.shape == (need["height"], need["width"])


def test_field_is_blurred_and_sub_pixel_phases_shift_it():
    pattern = np.zeros((40, 60), np.float32)
    pattern[20, 30] = 255.0
    field = PatternField(pattern, fit_pattern(pattern.shape, 60, 40, pad_left=0, margin=0), psf_px=0.5)
    g = field.geometry
    u_dot = g.u0 + 30 * g.scale
    v_dot = g.v0 + 20 * g.scale
    us = torch.linspace(u_dot - 2, u_dot + 2, 81)
    profile = field.sample(us, torch.full_like(us, v_dot))
    peak = us[profile.argmax()]
    assert abs(float(peak) - u_dot) < 0.06  # dot centred where it should be
    assert float(profile[0]) < 0.01 * float(profile.max())  # and ~1-2 px wide
    phases = field.reference_phases(60, 40, pad=4, n_sub=2)  # (4, 40, 64)
    # phase s is the reference shifted right by s/4 px: sampling it at +1/4 px matches phase 0
    row = int(round(v_dot))
    shifted = field.sample(torch.arange(64.0) - 4 - 0.25 + 0.25, torch.full((64,), float(row)))
    assert torch.allclose(phases[0, row], shifted, atol=1e-4)
    assert phases.shape == (4, 40, 64)


def test_pattern_command_writes_into_the_current_folder_not_the_package(tmp_path, monkeypatch):
    """`ddsgen pattern` without --out writes the preset's pattern file into the current folder (in a wheel
    install the package folder is site-packages); seed 0 regenerates the shipped asset exactly."""
    from ddsgen.cli import main

    monkeypatch.chdir(tmp_path)
    shipped = (PATTERN_DIR / "kinect_like_640.png").read_bytes()
    assert main(["pattern", "kinect_v1"]) == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["kinect_like_640.png"]
    assert (tmp_path / "kinect_like_640.png").read_bytes() == shipped


@pytest.mark.parametrize("density, says", [("0", "range"), ("1.5", "range"), ("0.3", "never touch")])
def test_pattern_density_it_cannot_draw_is_one_line_exit_2(density, says, tmp_path, monkeypatch, capsys):
    """Dots that never touch jam near 0.19 of the pixels: a density of 0, above 1 or beyond that limit was written
    silently as another pattern (0 % or 18.7 % lit). Now it is bad input, and nothing is written."""
    from ddsgen.cli import main

    monkeypatch.chdir(tmp_path)
    assert main(["pattern", "--density", density, "--out", "p.png"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--density" in err[0] and says in err[0], err
    assert not (tmp_path / "p.png").exists()
