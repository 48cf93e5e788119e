"""The differentiable sensor end to end: depth of planes, noise growth, IR physics, gradients."""

import dataclasses
import math

import numpy as np

import pytest
import torch

from ddsgen.preset import load_preset
from ddsgen.sensor.depth_sensor import DepthSensor
from ddsgen.sensor.geometry import SensorGeometry
from ddsgen.sensor.matcher import match
from ddsgen.sensor.stages import BlockMatcher
from gradient_check import autograd_and_difference
from sensor_scenes import plane_geometry, small_kinect


@pytest.fixture(scope="module")
def kinect():
    return DepthSensor(load_preset("kinect_v1"))


def _depth_errors(sensor, z, tilt=0.0, seed=1):
    geometry = plane_geometry(sensor.intr, z, tilt)
    with torch.no_grad():
        out = sensor(geometry, seed=seed)
    return out, (out.depth - geometry.clean_depth)[out.valid]


@pytest.mark.parametrize("z", [0.6, 1.0, 1.5, 2.0])
def test_plane_depth_within_one_quantisation_step(kinect, z):
    preset = kinect.preset
    step = z * z / (preset.focal_px * preset.baseline_m) * preset.subpixel_step_px  # depth step of one disparity step
    out, error = _depth_errors(kinect, z)
    assert out.valid.float().mean() > 0.9  # a fronto-parallel plane in range is nearly all valid
    assert error.abs().median() <= 0.6 * step  # the nearest quantisation level is up to half a step away
    assert (error.abs() <= step).float().mean() > 0.85
    # No systematic bias beyond the quantisation: the true z may sit between two levels.
    assert abs(float(error.mean())) < 0.5 * step


def test_depth_values_are_quantised_in_disparity(kinect):
    out, _ = _depth_errors(kinect, 1.2)
    d = kinect.intr.fx * kinect.preset.baseline_m / out.depth[out.valid].double()
    steps = d * 2**kinect.preset.subpixel_level
    assert torch.allclose(steps, steps.round(), atol=1e-3)  # disparity lands on the 1/4-px grid


def test_noise_grows_with_distance_like_z_squared_and_with_tilt(kinect):
    rms = {}
    for z in (1.0, 3.0):
        _, error = _depth_errors(kinect, z)
        rms[z] = float(error.pow(2).mean().sqrt())
    assert 4.0 <= rms[3.0] / rms[1.0] <= 16.0, rms  # structured light: sigma_z ~ z^2 (ratio 9)
    _, flat = _depth_errors(kinect, 2.0, tilt=0.0)
    _, tilted = _depth_errors(kinect, 2.0, tilt=60.0)
    assert float(tilted.std()) > float(flat.std())


def test_far_plane_loses_validity_beyond_range(kinect):
    near, _ = _depth_errors(kinect, 1.0)
    beyond, _ = _depth_errors(kinect, 1.25 * kinect.preset.z_max_m)
    assert beyond.valid.float().mean() < 0.1 < 0.9 < near.valid.float().mean()


def test_ir_signal_falls_with_square_distance_and_cosine():
    sensor = DepthSensor(small_kinect())

    def mean_signal(z, tilt=0.0):
        """Mean projector signal over the image centre, and the mean of cos(incidence)/d_mm^2 there."""
        g = plane_geometry(sensor.intr, z, tilt)
        from ddsgen.sensor.ir import render_ir

        with torch.no_grad():
            _, signal = render_ir(g.points, g.normals, g.albedo, g.hit.float(), sensor.pattern_field(),
                                  sensor.intr.fx, sensor.intr.fy, sensor.intr.cx, sensor.intr.cy,
                                  sensor.preset.baseline_m, sensor.preset.emitted_intensity, 0.0, 1.0, 0.0, 0.0,
                                  None)  # fmt: skip
        to_projector = torch.tensor([sensor.preset.baseline_m, 0.0, 0.0]) - g.points
        distance = to_projector.norm(dim=-1)
        falloff = (g.normals * to_projector).sum(-1) / distance / (1000.0 * distance) ** 2
        centre = (slice(40, 80), slice(60, 100))
        return float(signal[centre].mean()), float(falloff[centre].mean())

    near, far = mean_signal(1.0), mean_signal(2.0)
    assert near[0] / far[0] == pytest.approx(4.0, rel=0.05)  # inverse square law
    flat, tilted = mean_signal(1.0), mean_signal(1.0, 60.0)
    # Tilting by 60 degrees scales the irradiance by cos(incidence) seen from the projector at +b
    # (0.56 at the centre, not cos 60 = 0.5, because the projector is off axis).
    assert tilted[0] / flat[0] == pytest.approx(tilted[1] / flat[1], rel=0.05)
    assert tilted[0] / flat[0] < 0.65


def test_shadowed_and_empty_pixels_are_invalid_and_dark():
    """Shadowed pixels are dark and pixels without a surface have no depth. With the paper's shadow map every
    shadowed pixel is invalid; without it (kinect_v1: a real device has no such map) the matcher keeps the lit
    surface at most half a 9-px window into a 30-px shadow from each side and loses its core. Likewise the empty
    space right of column 120: the paper's masks leave it all invalid; kinect_v1 (no mask of empty space either)
    carries the surface into it by at most half a window (measured per column: 120-123 0.95 0.81 0.57 0.12)."""
    g = plane_geometry(small_kinect().intrinsics, 1.0)
    g.shadow[:, 60:90] = True
    g.hit[:, 120:] = False
    for shadow_map in (True, False):
        with torch.no_grad():
            out = DepthSensor(small_kinect(shadow_always_invalid=shadow_map))(g, seed=0)
        if shadow_map:
            assert not out.valid[:, 120:].any()
        else:
            assert not out.valid[:, 124:].any() and out.valid[:, 120:122].float().mean() > 0.5
        assert out.ir[:, 65:85].mean() < 0.2 * out.ir[:, 20:50].mean()
        assert out.valid[:, 20:50].float().mean() > 0.8
        if shadow_map:
            assert not out.valid[:, 60:90].any()
        else:  # measured per column: 60-63 0.97 0.70 0.41 0.08 | 64-85 none | 86-89 0.26 0.56 0.82 0.97
            assert not out.valid[:, 64:86].any()
            assert out.valid[:, 60:62].float().mean() > 0.5 and out.valid[:, 88:90].float().mean() > 0.5


# ---- gradients ---------------------------------------------------------------------------------
PARAMETERS = ["log_emitted_intensity", "log_speckle_scale", "log_read_noise_std", "log_beta", "log_baseline",
              "log_focal_scale"]  # fmt: skip


@pytest.fixture(scope="module")
def gradient_setup():
    # The paper's flat detector noise: with the device's high SNR the depth hardly depends on eta_c and
    # its differences sink into float32 round-off (tests/test_device_model.py checks the device's gradients).
    sensor = DepthSensor(small_kinect(128, 96, electrons_per_count=0.0, read_noise_std_counts=10.4))
    geometry = plane_geometry(sensor.intr, 0.9, tilt_deg=20.0)
    noise = sensor.draw_noise(3)
    with torch.no_grad():
        mask = sensor(geometry, noise=noise, quantise=False).valid
    return sensor, geometry, noise, mask


@pytest.mark.parametrize("name", PARAMETERS)
def test_depth_gradient_matches_central_finite_difference(gradient_setup, name):
    """d(mean valid depth)/d(log parameter): autograd vs central differences.

    quantise=False removes the ADC and disparity rounding (their straight-through gradients
    are by design not derivatives of the rounded forward value); the noise draws are fixed.
    The step eps = 3e-3 in log space moves disparities by < 0.05 px (small against the
    soft-argmax spread); the mean is taken in float64 (a float32 sum of ~10k depths rounds the
    difference to ~1e-5 steps, more than eta_c's whole derivative). Measured agreement: 0.03-0.5 %
    (focal 0.5 %); 3 % relative tolerance. beta's derivative is the smallest (~7e-6 m): over 3e-3 its difference sits
    at the float32 matcher's round-off (autograd / difference 0.99, 0.96, 0.98 with the row smoothing's w at 0,
    0.16, 0.25), over 1e-2 it is clear of it (1.003, 0.995, 1.004), so beta takes 1e-2.
    """
    sensor, geometry, noise, mask = gradient_setup

    def loss():
        return sensor(geometry, noise=noise, quantise=False).raw_depth[mask].double().mean()

    autograd, finite_difference = autograd_and_difference(loss, getattr(sensor, name),
                                                          eps=1e-2 if name == "log_beta" else 3e-3)  # fmt: skip
    assert math.isfinite(autograd)
    assert autograd == pytest.approx(finite_difference, rel=0.03, abs=1e-8), (autograd, finite_difference)


def test_gradients_are_finite_everywhere_including_invalid_pixels():
    sensor = DepthSensor(small_kinect(128, 96))
    g = plane_geometry(sensor.intr, 1.0)
    g.shadow[:, 40:60] = True
    g.hit[:10] = False
    out = sensor(g, seed=0)
    (out.depth.sum() + out.raw_depth.sum() + out.valid_soft.sum()).backward()
    for name, p in sensor.named_parameters():
        assert p.grad is None or torch.isfinite(p.grad).all(), name


def test_dot_jitter_moves_dots_off_the_lattice_and_zero_is_the_lattice():
    """``pattern_dot_jitter_px``: 0 (and a vanishing jitter) gives the lattice raster bit for bit; 1 px moves
    each dot by a fixed offset (the same in every build: a property of the projector) without changing the
    light it carries (touching dots overlap a little: within 0.5 %), and the dots' sub-pixel positions along
    the rows then spread over the whole pixel instead of sitting at one phase."""
    from ddsgen.sensor.pattern import PatternField, fit_pattern

    pattern = np.zeros((40, 60), np.float32)
    pattern[20, 2:-2:4] = 255.0  # one row of isolated dots on the lattice
    geometry = fit_pattern(pattern.shape, 50, 30, pad_left=0, margin=2)
    lattice = PatternField(pattern, geometry, psf_px=0.4)
    assert torch.equal(PatternField(pattern, geometry, psf_px=0.4, dot_jitter_px=1e-9).raster, lattice.raster)
    moved = PatternField(pattern, geometry, psf_px=0.4, dot_jitter_px=1.0)
    assert torch.equal(PatternField(pattern, geometry, psf_px=0.4, dot_jitter_px=1.0).raster, moved.raster)
    assert float(moved.raster.sum()) == pytest.approx(float(lattice.raster.sum()), rel=5e-3)

    def column_phases(field):
        """Sub-pixel phase (projector px) of each dot's intensity centroid along x."""
        u = torch.arange(-1.0, 51.0, 1.0 / 16)
        v = torch.arange(-5.0, 35.0, 0.5)
        values = field.sample(u[None, :].expand(len(v), -1), v[:, None].expand(-1, len(u))).sum(0).numpy()
        phases, start = [], None
        for i, lit in enumerate(values > 0.05 * values.max()):
            if lit and start is None:
                start = i
            elif not lit and start is not None:
                seg = slice(start, i)
                phases.append(float((u.numpy()[seg] * values[seg]).sum() / values[seg].sum()) % 1.0)
                start = None
        return np.array(phases)

    assert np.ptp(column_phases(lattice)) < 0.05  # every dot column at one phase
    jittered = column_phases(moved)
    assert np.ptp(jittered) > 0.5, jittered  # spread over the pixel


# ---- depth edges: the device keeps its edges and loses depth only in the projector's shadow -----------------------
def _board_before_wall(intr, baseline, z_board=1.0, z_wall=1.6, half=(0.15, 0.12)):
    """A fronto-parallel board (|x| < half[0], |y| < half[1] m, at z_board) before a wall at z_wall,
    with the wall's projector shadow: a wall point is dark when the segment to the projector at
    (+baseline, 0, 0) crosses the board (the shadow falls on the board's left, away from +x)."""
    u, v = np.meshgrid(np.arange(intr.width, dtype=np.float64), np.arange(intr.height, dtype=np.float64))
    rays = np.stack([(u - intr.cx) / intr.fx, (v - intr.cy) / intr.fy, np.ones_like(u)], axis=-1)
    on_board = (np.abs(rays[..., 0] * z_board) < half[0]) & (np.abs(rays[..., 1] * z_board) < half[1])
    z = np.where(on_board, z_board, z_wall)
    points = rays * z[..., None]
    s = (z_wall - z_board) / z_wall  # where the wall-to-projector segment crosses the board's plane
    cross_x = points[..., 0] + s * (baseline - points[..., 0])
    cross_y = points[..., 1] * (1 - s)
    shadow = ~on_board & (np.abs(cross_x) < half[0]) & (np.abs(cross_y) < half[1])
    shape = z.shape
    geometry = SensorGeometry(
        points=torch.tensor(points, dtype=torch.float32),
        normals=torch.tensor(np.broadcast_to([0.0, 0.0, -1.0], points.shape).copy(), dtype=torch.float32),
        albedo=torch.full(shape, 0.8), hit=torch.ones(shape, dtype=torch.bool),
        shadow=torch.tensor(shadow), clean_depth=torch.tensor(z, dtype=torch.float32),
    )  # fmt: skip
    return geometry, on_board, shadow


@pytest.fixture(scope="module")
def board_frames():
    """The board scene at 320x240 through kinect_v1 and through kinect_v1 with the confirmed-match rule off (both
    without the narrow fill of the clean-up, which would close the uniqueness test's ring: the matcher's rule is
    what these tests look at)."""
    device = small_kinect(320, 240).replace(cleanup_fill_width_px=0)
    geometry, on_board, shadow = _board_before_wall(device.intrinsics, device.baseline_m)
    outputs = {}
    for name, preset in (("device", device), ("uniqueness only", device.replace(confirmed_match_zncc=1.0))):
        with torch.no_grad():
            outputs[name] = DepthSensor(preset)(geometry, seed=3)
    return outputs, on_board, shadow, device.focal_px * device.baseline_m


def _edge_bands(on_board, shadow, width=4):
    """Wall pixels within ``width`` px of the board on the sides away from the shadow (right, top, bottom),
    and the board's first and last rows and columns."""
    rows, cols = np.nonzero(on_board)
    top, bottom, left, right = rows.min(), rows.max(), cols.min(), cols.max()
    away = np.zeros_like(on_board)
    away[top + 2 : bottom - 1, right + 1 : right + 1 + width] = True
    away[top - width : top, left + 2 : right - 1] = True
    away[bottom + 1 : bottom + 1 + width, left + 2 : right - 1] = True
    return away & ~shadow, (top, bottom, left, right)


def _shadow_band(on_board, shadow):
    """``(rows, columns)``: the board's rows but its first and last two, and the columns of the shadow left of it."""
    rows = np.nonzero(on_board.any(1))[0][2:-2]
    return rows, np.nonzero(shadow[rows].any(0))[0]


@pytest.mark.parametrize("z_wall, width", [(1.25, 4), (2.2, 12)])
def test_without_the_shadow_mask_the_matcher_alone_decides_how_much_of_a_shadow_is_lost(z_wall, width):
    """``shadow_always_invalid: false`` (kinect_v1): no ray-cast oracle, the matcher decides. A window at a shadow's
    edge still sees its lit neighbour's dots and keeps that surface, so a projector shadow loses its core only: a
    4-px shadow keeps most of its pixels, a 12-px one its outer columns on both sides -- as real PrimeSense frames do
    (no hole below ~7 px of shadow at 640 px, about half the width beyond: docs/validation.md). With the paper's mask
    every shadow pixel is invalid; elsewhere the two agree. (Both without the device's narrow fill, which closes the
    4-px shadow whichever decides: checked with it too, at half the 9-px window, 4 px; kinect_v1 fills 3.)"""
    with_fill = small_kinect(320, 240, cleanup_fill_width_px=4)
    assert not with_fill.shadow_always_invalid
    device = with_fill.replace(cleanup_fill_width_px=0)
    fb = device.focal_px * device.baseline_m
    geometry, on_board, shadow = _board_before_wall(device.intrinsics, device.baseline_m, z_board=1.0, z_wall=z_wall)
    with torch.no_grad():
        masked = DepthSensor(device.replace(shadow_always_invalid=True))(geometry, seed=3)
        matcher_only = DepthSensor(device)(geometry, seed=3)
        filled = DepthSensor(with_fill)(geometry, seed=3)
        masked_filled = DepthSensor(with_fill.replace(shadow_always_invalid=True))(geometry, seed=3)
    rows, columns = _shadow_band(on_board, shadow)
    assert len(columns) == width  # f b (1/z_board - 1/z_wall) at 320 px
    assert not masked.valid.numpy()[shadow].any()
    # The narrow fill (4 px): the 4-px shadow takes the wall's depth on its left and the board's on its right, with
    # or without the mask; the 12-px one keeps its hole (with the mask all of it but for its last rows at each end,
    # where the 9 x 9 window sees the lit rows beyond the shadow; without, its core).
    for output in (filled, masked_filled):
        kept = output.valid.numpy()[rows][:, columns]
        if width <= with_fill.cleanup_fill_width_px:
            assert kept.mean() >= 0.85, kept.mean()  # measured 1.0 (a few rows have a matcher hole beside the shadow)
            filled_disparity = output.disparity.numpy()[rows][:, columns]
            assert np.median(filled_disparity[:, 0]) == pytest.approx(fb / z_wall, abs=1.0)
            assert np.median(filled_disparity[:, -1]) == pytest.approx(fb, abs=1.0)
        elif output is masked_filled:
            assert not kept[2:-2].any()
        else:  # measured 0.98 0.73 0.42 | 0.11 0.05 0.03 0.03 0.02 0.08 | 0.45 0.80 0.98
            core, wall_side, board_side = kept[:, 3:-3], kept[:, :2], kept[:, -2:]
            assert core.mean() <= 0.15 and min(wall_side.mean(), board_side.mean()) >= 0.6, kept.mean(0)
    valid = matcher_only.valid.numpy()[rows][:, columns]
    disparity = matcher_only.disparity.numpy()[rows][:, columns]
    on_a_surface = (np.abs(disparity - fb / z_wall) <= 1) | (np.abs(disparity - fb) <= 1)
    assert on_a_surface[valid].mean() >= 0.98  # measured 0.996-1.0: what it keeps is the wall or the board
    per_column = valid.mean(axis=0)
    if width == 4:
        assert per_column.mean() >= 0.5, per_column  # measured 0.68
    else:
        # measured 0.95 0.67 | 0.06 0.02 0 0 0 0.06 | 0.67 0.83 (wall side | core | board side)
        assert per_column[:2].min() >= 0.4 and per_column[-2:].min() >= 0.4, per_column
        assert per_column[4:-4].max() <= 0.15, per_column
    differ = (matcher_only.valid.numpy() != masked.valid.numpy()) & ~shadow
    assert differ.mean() <= 0.001  # measured 0-0.0001


def test_depth_edges_keep_their_depth_and_only_the_projector_shadow_is_lost(board_frames):
    """A window across a depth edge sees two surfaces; the device keeps the stronger (foreground
    fattening) where the uniqueness test alone leaves a ring of holes around every object."""
    outputs, on_board, shadow, fb = board_frames
    away, (top, bottom, left, right) = _edge_bands(on_board, shadow)
    assert 6 <= shadow[(top + bottom) // 2].sum() <= 10  # the shadow band: f b (1/z_board - 1/z_wall) = 8 px
    device = outputs["device"]
    ring = {name: float(out.valid.numpy()[away].mean()) for name, out in outputs.items()}
    # Measured: 0.91 kept with the device's rule (0.79 at 0.4), 0.37 with uniqueness alone (the ring). What stays lost are
    # windows whose best peak is a wrong disparity (the pattern's self-similarity), not either surface.
    assert ring["device"] > 0.7 and ring["uniqueness only"] < 0.5, ring
    # The one-sided projector shadow (8 px) loses its core: kinect_v1 has no shadow map, and a window there sees
    # too little of either lit surface (measured per column, device 0.80 0.36 | 0.19 0.08 0.06 0.30 | 0.73 0.94,
    # uniqueness only 0.31 0.08 | 0.08 0 0.03 0.05 | 0.28 0.67).
    rows, columns = _shadow_band(on_board, shadow)
    for out in outputs.values():
        band = out.valid.numpy()[rows][:, columns]
        assert band[:, 2:-2].mean() <= 0.3, band.mean(0)
    # Fattening: the board's depth reaches over the wall by a pixel or two (measured 1.7-1.9 px on average at the
    # preset's 0.35; 1.3-1.7 at 0.4, 2.0-2.1 at 0.3),
    # never by a window (9 px): at most half a window, where the board still fills half the window.
    depth = device.depth.numpy()
    on_board_depth = np.abs(depth - 1.0) < 0.05
    for beyond in (on_board_depth[top + 2 : bottom - 1, right + 1 : right + 9],  # right of the board, per row
                   on_board_depth[top - 8 : top, left + 2 : right - 1].T,  # above, per column
                   on_board_depth[bottom + 1 : bottom + 9, left + 2 : right - 1].T):  # below, per column
        fattened = beyond.sum(axis=1)
        assert fattened.mean() <= 2 and fattened.max() <= 4, fattened
    # Where the device keeps an edge pixel, its disparity is the board's or the wall's (within 1 px), not a blend.
    disparity = fb / depth[device.valid.numpy() & away]
    off_both = np.minimum(np.abs(disparity - fb / 1.0), np.abs(disparity - fb / 1.6)) > 1.0
    assert off_both.mean() < 0.02, (off_both.mean(), disparity[off_both])


def test_edge_windows_whose_best_peak_is_neither_surface_keep_the_confirmed_second():
    """Board 1.0 m before a wall at 1.6 m: some windows across its edges score best at a disparity of
    neither surface (another alignment of the dot pattern beats both half-window peaks) and have one
    of the surfaces as their second peak. Where a unique neighbour on that surface confirms the second
    peak, the pixel is kept with that surface's depth, as the best peak is kept elsewhere."""
    results = []
    device = small_kinect(320, 240)
    # A matcher stage whose matching function keeps each result: handed to both sensors, each with its own settings.
    recording = dataclasses.replace(BlockMatcher.from_preset(device),
                                    function=lambda *a, **k: results.append(match(*a, **k)) or results[-1])
    geometry, _, _ = _board_before_wall(device.intrinsics, device.baseline_m)
    fb = device.focal_px * device.baseline_m
    with torch.no_grad():
        DepthSensor(device.replace(confirmed_match_zncc=1.0), stages={"matcher": recording})(geometry, seed=3)
        output = DepthSensor(device, stages={"matcher": recording})(geometry, seed=3)  # the rule at 0.35
    alone, rule = results
    surfaces = torch.tensor([fb / 1.0, fb / 1.6])

    def on_a_surface(disparity):
        return (disparity[..., None].double() - surfaces).abs().min(dim=-1).values <= 1

    # Failing the uniqueness test, best peak on neither surface, second peak (ZNCC > the rule's threshold) on one.
    wrong_best = ~alone.valid & ~on_a_surface(alone.peak_px) & (alone.best_zncc > device.confirmed_match_zncc)
    cases = wrong_best & on_a_surface(rule.second_peak_px) & (rule.second_zncc > device.confirmed_match_zncc)
    took_second = cases & rule.valid & (rule.peak_px == rule.second_peak_px.long())
    assert cases.sum() >= 40, int(cases.sum())  # measured 145 at the preset's 0.35 (67 at 0.4)
    # Measured 94 of 145 (48 of 67 at 0.4): the rest have no unique neighbour on that surface in their window.
    assert took_second.sum() >= 0.5 * cases.sum(), (int(took_second.sum()), int(cases.sum()))
    # Every one of them within 1 px of the surface (measured 94 of 94); the clean-up then removes those left in
    # valid specks under 100 px, as it does any speck (measured: keeps 84 of 94; 48 of 48 at 0.4).
    right = took_second & on_a_surface(rule.disparity.detach())
    assert right.sum() == took_second.sum(), (int(right.sum()), int(took_second.sum()))
    assert (right & output.valid).sum() >= 0.8 * took_second.sum(), (int((right & output.valid).sum()), int(took_second.sum()))
