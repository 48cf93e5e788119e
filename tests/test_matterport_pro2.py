"""The shipped matterport_pro2 preset at its full 1280x1024: a dataset render whose records state the preset's
camera, and planes measured at their distance with a disparity noise that does not depend on it (depth noise grows as
z^2, as a triangulating sensor's must).

Full resolution is cheap enough: a frame renders in about 3 s, a plane's sensor pass in about 0.3 s.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from sensor_scenes import plane_geometry

from ddsgen.io.exr import read_exr
from ddsgen.io.manifest import read_manifest
from ddsgen.io.png import read_depth_png
from ddsgen.preset import load_preset
from ddsgen.runner import render_dataset
from ddsgen.sensor.depth_sensor import DepthSensor

PRESET = "matterport_pro2"


@pytest.fixture(scope="module")
def preset():
    return load_preset(PRESET)


@pytest.mark.slow
def test_a_render_states_the_presets_camera_and_measures_its_scene(preset, tmp_path, monkeypatch):
    """Two frames of the default scene list: each record's intrinsics are the preset's, the depth image has its
    size, the valid share is a depth camera's (measured 0.73 and 0.95: projector shadows are holes, but not most of
    the image), and the valid depths agree with the ray-cast truth to a small fraction of a disparity pixel."""
    monkeypatch.setenv("DDSGEN_NO_COMPILE", "1")  # torch.compile costs seconds and is not the subject
    out = tmp_path / "out"
    render_dataset(PRESET, None, 2, str(out), workers=1, seed=3, progress=False)
    intr = preset.intrinsics
    expected = {"width": 1280, "height": 1024, "fx": intr.fx, "fy": intr.fy, "cx": intr.cx, "cy": intr.cy}
    assert (intr.width, intr.height) == (1280, 1024)
    fb = intr.fx * preset.baseline_m  # disparity (px) x depth (m)
    records = read_manifest(out / "manifest.jsonl")
    assert [r["frame"] for r in records] == [0, 1]
    for record in records:
        assert record["intrinsics"] == pytest.approx(expected)
        depth = read_depth_png(out / record["depth"], record["depth_scale"])
        assert depth.shape == (1024, 1280)
        valid = depth > 0
        assert record["valid_fraction"] == pytest.approx(valid.mean(), abs=1e-6)
        assert 0.5 < record["valid_fraction"] < 0.99, record["valid_fraction"]
        measured, truth = read_exr(out / record["depth_exr"]), read_exr(out / record["clean"])
        both = (measured > 0) & (truth > 0)
        assert both.mean() > 0.5
        assert (measured[valid] >= preset.z_min_m * 0.99).all() and (measured[valid] <= preset.z_max_m * 1.01).all()
        disparity_error = fb / measured[both] - fb / truth[both]  # px; edges and wrong matches in the tails
        assert abs(np.median(disparity_error)) < 0.05, np.median(disparity_error)  # measured 0.0015, 0.0002
        assert np.median(np.abs(disparity_error)) < 0.15, np.median(np.abs(disparity_error))  # measured 0.054, 0.055


def test_a_frontal_plane_measures_at_its_distance_within_its_noise(preset):
    """A white wall at 1, 2.5 and 5 m, seen head-on: nearly all valid (a band at the image side the projector does
    not light is not), the median depth within a small fraction of a disparity pixel of the truth (at 2.5 m within
    the depth noise itself), and a disparity noise of a few hundredths of a pixel at every distance (measured
    0.055-0.08 px), so that the depth noise grows as z^2 (0.7 mm at 1 m, 25 mm at 5 m)."""
    sensor = DepthSensor(preset).eval()
    fb = preset.focal_px * preset.baseline_m
    disparity_noise = {}
    for z in (1.0, 2.5, 5.0):
        with torch.no_grad():
            depth = sensor(plane_geometry(preset.intrinsics, z), seed=[1, 2, 3]).depth.numpy()
        assert (depth > 0).mean() > 0.97, (z, (depth > 0).mean())
        height, width = depth.shape
        inner = depth[height // 8 : -height // 8, width // 8 : -width // 8]
        assert (inner > 0).all(), z
        median, noise = float(np.median(inner)), float(inner.std())
        assert abs(fb / median - fb / z) < 0.2, (z, median)  # disparity bias, px (measured 0.05-0.16)
        if z == 2.5:
            assert abs(median - z) < noise, (median, noise)
        disparity_noise[z] = noise * fb / z**2
    assert all(0.02 < sigma < 0.2 for sigma in disparity_noise.values()), disparity_noise
    assert max(disparity_noise.values()) < 2 * min(disparity_noise.values()), disparity_noise
