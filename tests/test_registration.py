"""Depth registered to the RGB camera (ddsgen/sensor/registration.py): the IR camera's depth written in the
colour camera's image, on ray-cast walls and boxes, and against the real LineMOD cat frame."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh

from ddsgen.preset import load_preset
from ddsgen.scene.sampling import FrameScene, PlacedObject
from ddsgen.scene.shapes import plane_mesh
from ddsgen.sensor.depth_sensor import DepthSensor
from ddsgen.sensor.ir_margin import cast_for_sensor
from ddsgen.sensor.registration import cropped_index, output_projector_x_m, register

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


def _translation(x=0.0, y=0.0, z=0.0) -> np.ndarray:
    pose = np.eye(4)
    pose[:3, 3] = (x, y, z)
    return pose


def _scene(wall_z: float, box_z: float | None = None) -> FrameScene:
    wall = PlacedObject(0, "wall", "plane", plane_mesh(40.0, 40.0), _translation(z=wall_z), 0.8)
    objects = []
    if box_z is not None:  # front face at box_z, 0.2 m wide, centred
        box = trimesh.creation.box(extents=[0.2, 0.2, 0.02])
        objects.append(PlacedObject(1, "box", "box", box, _translation(z=box_z + 0.01), 0.8))
    return FrameScene(objects, [wall], np.eye(4), 0, 0)


def _strip(rows: int = 48, **changes):
    """kinect_v1 (registered) at full width, ``rows`` rows around the centre."""
    base = load_preset("kinect_v1")
    return base.replace(height_px=rows, cy_px=(rows - 1) / 2.0, **changes)


def _first_valid_column(valid: np.ndarray) -> float:
    rows = [np.flatnonzero(r)[0] for r in valid if r.any()]
    return float(np.median(rows))


@pytest.mark.parametrize("z", [0.8, 2.0])
def test_the_left_band_narrows_with_depth_like_the_real_linemod_frame(z):
    """A wall at z: the registered depth begins at column L + s - f b_r / z (the IR frame's blind columns seen
    from the RGB camera), as the real cat frame's band (24.4 - 15.6 / z); unregistered it is L whatever z."""
    preset = _strip()
    f, b_r, s, left = preset.focal_px, preset.registration_ir_offset_m, preset.registration_shift_px, 8
    unregistered = preset.replace(registration_ir_offset_m=0.0, registration_shift_px=0.0)
    with torch.no_grad():
        registered = DepthSensor(preset).eval()(cast_for_sensor(_scene(z), preset.intrinsics, preset)[1], seed=1)
        plain = DepthSensor(unregistered).eval()(cast_for_sensor(_scene(z), preset.intrinsics, unregistered)[1],
                                                 seed=1)  # fmt: skip
    predicted = left + s - f * b_r / z
    assert _first_valid_column(registered.valid.numpy()) == pytest.approx(predicted, abs=1.0)
    assert _first_valid_column(plain.valid.numpy()) == pytest.approx(left, abs=0.5)
    # On the wall the registered depth is the wall's (a pure x offset keeps z), to a few 1/8-px levels.
    step = z**2 / (8 * f * preset.baseline_m)
    valid = registered.valid.numpy()
    assert valid[:, 40:-40].mean() > 0.97
    assert np.median(np.abs(registered.depth.numpy()[valid] - z)) < 2 * step


def test_the_rgb_camera_sees_behind_a_near_box_what_the_ir_camera_does_not():
    """A box at 0.8 m before a wall at 1.5 m. In the registered image the wall just right of the box has no
    depth, a band f b_r (1/z_box - 1/z_wall) px wide (the IR camera, left of the RGB camera, sees the box
    there); the projector's shadow left of the box is f (b - b_r) (1/z_box - 1/z_wall) px wide, narrower than
    in the IR camera's own image (f b (...)), because the RGB camera sits between the IR camera and projector."""
    preset = _strip(rows=96)
    f, b, b_r = preset.focal_px, preset.baseline_m, preset.registration_ir_offset_m
    z_box, z_wall = 0.8, 1.5
    hits, geometry = cast_for_sensor(_scene(z_wall, z_box), preset.intrinsics, preset)
    index = geometry.registration.numpy()
    inverse_gap = 1.0 / z_box - 1.0 / z_wall
    rows = range(30, 66)  # rows well inside the box (0.2 m at 0.8 m: 143 px tall)
    box_cols = np.flatnonzero(hits.instance[48] == 1)
    right_edge = box_cols.max()
    unseen_right = [np.flatnonzero(index[v, right_edge + 1 : right_edge + 40] < 0).size for v in rows]
    assert np.median(unseen_right) == pytest.approx(f * b_r * inverse_gap, abs=1.5)  # nearest-pixel sampling: +-1 px and rounding
    # The projector shadow as the output camera sees it (the output cast's projector sits at b - b_r).
    assert output_projector_x_m(preset) == pytest.approx(b - b_r)
    shadow_left = [np.flatnonzero(hits.shadow[v, : box_cols.min()]).size for v in rows]
    assert np.median(shadow_left) == pytest.approx(f * (b - b_r) * inverse_gap, abs=1.5)  # nearest-pixel sampling: +-1 px and rounding
    ir_shadow_left = [np.flatnonzero(geometry.shadow[v].numpy() & (geometry.clean_depth[v].numpy() > 1.0)).size
                      for v in rows]  # fmt: skip
    assert np.median(ir_shadow_left) == pytest.approx(f * b * inverse_gap, abs=1.5)  # nearest-pixel sampling: +-1 px and rounding

    # Through the sensor: the unseen band and the shadow are empty, the wall beyond them and the box are measured.
    sensor = DepthSensor(preset).eval()
    with torch.no_grad():
        out = sensor(geometry, seed=2)
    valid = out.valid.numpy()[30:66]
    assert not valid[:, right_edge + 1 : right_edge + 1 + int(f * b_r * inverse_gap) - 1].any()
    assert valid[:, right_edge + 20 : right_edge + 60].mean() > 0.95
    assert valid[:, box_cols.min() + 8 : right_edge - 8].mean() > 0.95
    depth = out.depth.numpy()[30:66]
    assert np.median(depth[:, box_cols.min() + 8 : right_edge - 8][valid[:, box_cols.min() + 8 : right_edge - 8]]) \
        == pytest.approx(z_box, abs=0.005)  # fmt: skip


def test_registered_depth_is_the_ir_frames_depth_gathered_and_keeps_its_gradient():
    """The registration is the last stage: the output is the IR-frame result at the index (the device's
    quantised levels survive: every registered value is an IR-frame value), and gradients flow through it."""
    preset = _strip(rows=32)
    _, geometry = cast_for_sensor(_scene(1.5, 0.9), preset.intrinsics, preset)
    sensor = DepthSensor(preset)
    out = sensor(geometry, seed=4)
    import dataclasses

    with torch.no_grad():
        ir_frame = sensor(dataclasses.replace(geometry, registration=None), seed=4)
    assert torch.equal(out.depth.detach(), register(ir_frame.depth, geometry.registration))
    values = set(np.unique(ir_frame.depth.numpy()).tolist())
    assert set(np.unique(out.depth.detach().numpy()).tolist()) <= values
    (out.depth[out.valid]).sum().backward()
    assert sensor.log_baseline.grad is not None and float(sensor.log_baseline.grad.abs()) > 0


def test_a_crop_of_a_registered_geometry_keeps_the_sources_inside_its_window():
    full = torch.tensor([[0, 1, 2, 3], [4, 5, 6, 7], [-1, 9, 10, 11]])  # (3, 4): identity but one unseen pixel
    shifted = torch.tensor([[1, 2, 3, -1], [5, 6, 7, -1], [9, 10, 11, -1]])  # each pixel shows its right neighbour
    assert torch.equal(cropped_index(full, 4, 0, 1, 2, 2), torch.tensor([[0, 1], [-1, 3]]))
    assert torch.equal(cropped_index(shifted, 4, 1, 0, 2, 3), torch.tensor([[1, -1], [3, -1], [5, -1]]))


def test_the_paper_preset_is_not_registered_and_the_device_preset_is():
    assert load_preset("kinect_v1_paper").registration_ir_offset_m == 0.0
    device = load_preset("kinect_v1")
    assert 0.02 <= device.registration_ir_offset_m <= 0.035  # the Kinect's IR-RGB spacing is about 25 mm


def test_registered_corners_and_left_band_match_the_real_cat_frame():
    """The LineMOD cat frame at its GT pose: in the compare region the simulated corner valid share is within
    0.08 of the real one (issue 12's target; unregistered it was 0.092 off), and so is the whole region's."""
    scene = DATA / "linemod_bop" / "test" / "000006"
    if not scene.is_dir():
        pytest.skip(f"{scene} absent (real data is not part of a fresh checkout)")
    from ddsgen.depth_statistics import realism_statistics
    from ddsgen.fit.inputs import load_inputs
    from ddsgen.fit.simulate import simulate

    _, preset, _, frames = load_inputs("kinect_v1", str(scene), progress=False)
    frame = frames[0]
    with torch.no_grad():
        out = simulate(DepthSensor(preset).eval(), frame, seed=0)
    region, real = frame.region.numpy(), frame.real_depth.numpy()
    real_stats = realism_statistics(real, real > 0, region)
    sim_stats = realism_statistics(out.depth.numpy(), out.valid.numpy(), region)
    assert abs(sim_stats["corner_valid_share"] - real_stats["corner_valid_share"]) <= 0.08
    assert abs(sim_stats["valid_share"] - real_stats["valid_share"]) <= 0.04
    # The left band: in the rows where the region reaches the image's left edge, the first valid column of the
    # simulation is the real one's within 2 px (median), at near rows (~1 m) and far rows (~1.7 m) alike.
    sim_valid = out.valid.numpy()
    errors = []
    for v in range(real.shape[0]):
        if region[v, 8:40].all() and (real[v, :40] > 0).any() and sim_valid[v, :40].any():
            errors.append(np.flatnonzero(sim_valid[v, :40])[0] - np.flatnonzero(real[v, :40] > 0)[0])
    assert len(errors) > 50 and abs(np.median(errors)) <= 2
