"""The speckle of the device's stored reference image (ddsgen.sensor.reference_speckle)."""

import numpy as np
import pytest
import torch

from ddsgen.sensor.reference_speckle import reference_speckle_factor
from sensor_scenes import plane_geometry, small_kinect


def test_each_phase_carries_the_stored_pixels_values_shifted_with_it():
    """One value per stored pixel, mean 1 and spread c; phases up to 1/2 px take the pixel at their column, phases
    past 1/2 px the pixel left of it (the nearest to u = j - pad - s/S); another unit has its own capture, the same
    unit the same in every call."""
    factor = reference_speckle_factor(8, 60, 300, 0.3)
    assert factor.shape == (8, 60, 300) and factor.dtype == torch.float32
    assert float(factor.mean()) == pytest.approx(1.0, abs=0.01) and float(factor.std()) == pytest.approx(0.3, rel=0.03)
    for s in range(1, 5):
        assert torch.equal(factor[s], factor[0])
    for s in range(5, 8):
        assert torch.equal(factor[s][:, 1:], factor[0][:, :-1]) and not torch.equal(factor[s], factor[0])
    assert torch.equal(factor, reference_speckle_factor(8, 60, 300, 0.3))
    assert not torch.equal(factor, reference_speckle_factor(8, 60, 300, 0.3, unit=1))
    assert torch.equal(reference_speckle_factor(4, 10, 20, 0.0), torch.ones(4, 10, 20))
    assert float(reference_speckle_factor(2, 200, 200, 2.0).min()) == 0.0  # clipped, never negative


def _plane_noise(contrast: float, z: float, albedo: float) -> tuple[float, float, float]:
    """(flat roughness px, row correlation, valid share) of a plane 5 deg off fronto-parallel, kinect_v1 at
    320 x 240 without its row smoothing (so the reference's own grain is what is measured)."""
    from ddsgen.sensor.depth_sensor import DepthSensor
    from ddsgen.surface_roughness import surface_roughness

    preset = small_kinect(320, 240, reference_speckle_contrast=contrast, row_smoothing_weight=0.0)
    with torch.no_grad():
        out = DepthSensor(preset)(plane_geometry(preset.intrinsics, z, 5.0, albedo=albedo), seed=1)
    stats = surface_roughness(out.depth.numpy().astype(np.float64), preset.focal_px * preset.baseline_m)
    return stats["flat_roughness_px"], stats["noise_correlation_row"], float(out.valid.float().mean())


def test_the_reference_speckle_adds_the_same_disparity_noise_at_every_depth_and_albedo(set_torch_threads):
    """Noise on the reference side does not depend on the scene: the disparity variance it adds (c = 0.3) is about
    the same near, far and on a dark surface (measured 0.9-1.3e-3 px^2), so in depth it grows as z^2 like the
    device's; spread by the overlapping windows, it raises the noise's correlation along the rows; a white plane
    keeps its validity."""
    set_torch_threads(1)
    added = []
    for z, albedo in ((0.8, 0.8), (2.5, 0.8), (1.5, 0.2)):
        rough0, row0, valid0 = _plane_noise(0.0, z, albedo)
        rough, row, valid = _plane_noise(0.3, z, albedo)
        assert rough > 1.15 * rough0, (z, albedo, rough0, rough)
        assert row > row0 + 0.05, (z, albedo, row0, row)
        assert valid == pytest.approx(valid0, abs=0.005)
        added.append(rough**2 - rough0**2)
    assert max(added) < 1.6 * min(added), added


def test_zero_contrast_leaves_the_reference_untouched():
    """The stock presets (c = 0) match against the ideal pattern's phases, byte for byte."""
    from ddsgen.sensor.depth_sensor import DepthSensor

    plain = DepthSensor(small_kinect(160, 120)).reference_phases()
    speckled = DepthSensor(small_kinect(160, 120, reference_speckle_contrast=0.3)).reference_phases()
    assert torch.equal(plain, DepthSensor(small_kinect(160, 120, reference_speckle_contrast=0.0)).reference_phases())
    known = torch.isfinite(plain) & (plain > 0)
    ratio = speckled[known] / plain[known]
    assert float(ratio.std()) == pytest.approx(0.3, rel=0.1)
