"""disparity_distortion and the generic axis terms: validation, neutrality, physics, gradients, recovery by ``fit``.

Full-sensor checks run the real DepthSensor on the analytic scenes of ``effects_geometry`` (160 x 120 px, the
Kinect V1 field of view); an effect acting after the matcher is compared with the same frame (same noise draws)
without it, so the change it makes is exact, not statistical.
"""

from __future__ import annotations

import dataclasses
import hashlib
import math

import numpy as np
import pytest
import torch
from effects_geometry import plane_geometry, small_preset, tilted_normal
from test_effects import RECT, _fd_check, ctx_for, fresh, in_double, run

from torch_threads import torch_threads
from ddsgen.errors import InputError
from ddsgen.fit.fitting import fit_sensor
from ddsgen.realscan.simulate import FrameData
from ddsgen.preset import load_preset, save_preset
from ddsgen.sensor.depth_sensor import DepthSensor
from ddsgen.sensor.effects import REGISTRY, build_effects, library_names, validate_effects
from ddsgen.sensor.effects.axis_terms import (
    AXIS_DOMAINS,
    COEFFICIENTS,
    PHYSICAL_CAUSES,
    AxisDisparityTerm,
    AxisValidityTerm,
    axis_shape,
    fit_axis_coefficients,
    legendre_basis,
)
from ddsgen.sensor.effects.distortion import (
    GRID_COLS,
    GRID_KEYS,
    GRID_ROWS,
    X_EXTENT,
    Y_EXTENT,
    DisparityDistortion,
    fit_distortion_grid,
    sample_field,
)
from ddsgen.sensor.effects.features import edge_distance, normalised_coordinates, pixel_axis
from ddsgen.sensor.matcher import match
from ddsgen.sensor.stages import BlockMatcher

#: A Herrera-like pattern (px at zero disparity): strong at the corners and edges, slightly negative in the middle.
BOWL = [0.5, 0.2, 0.0, 0.2, 0.5,
        0.2, -0.1, -0.2, -0.1, 0.2,
        0.5, 0.2, 0.0, 0.2, 0.5]  # fmt: skip


def legendre_numpy(t: np.ndarray, coefficients) -> np.ndarray:
    """Reference series sum_k c_k P_k(t) from numpy (independent of the effect's recurrence)."""
    return np.polynomial.legendre.legval(t, np.asarray(coefficients, np.float64))


def disparity_of(out, fb: float) -> torch.Tensor:
    """Disparity (px) behind a sensor output's raw depth (0 where there is none)."""
    z = out.raw_depth.double()
    return torch.where(z > 0, fb / z.clamp_min(1e-9), torch.zeros_like(z))


# --------------------------------------------------------------------------------------------
# Metadata and validation


def test_new_effects_are_registered_with_their_metadata():
    assert {"disparity_distortion", "axis_disparity_term", "axis_validity_term"} <= set(REGISTRY)
    assert "disparity_distortion" in library_names()
    assert not {"axis_disparity_term", "axis_validity_term"} & set(library_names())  # generic: not named
    assert set(AXIS_DOMAINS) == set(PHYSICAL_CAUSES) == {
        "radius", "row", "column", "edge_distance", "incidence", "depth", "signal"}  # fmt: skip
    term = AxisValidityTerm(axis="edge_distance")
    info = term.describe()
    assert info["axis"] == "edge_distance" and "edge fattening of the matching window" in info["causes"]
    assert info["description"].endswith("(here: edge distance).")
    assert DisparityDistortion.stage == AxisDisparityTerm.stage == "disparity"
    assert AxisValidityTerm.stage == "validity"


def test_entries_take_an_axis_and_lists_and_round_trip_through_a_preset(tmp_path):
    entries = validate_effects([
        {"name": "axis_disparity_term", "axis": "column", "coefficients": [0.0, 0.1, 0.0, -0.05, 0.0]},
        {"name": "disparity_distortion", "grid": BOWL, "alpha1": 0.02},
        {"name": "axis_validity_term"},
    ], "x.yaml")  # fmt: skip
    assert entries[0] == {"name": "axis_disparity_term", "axis": "column", "c0": 0.0, "c1": 0.1, "c2": 0.0,
                          "c3": -0.05, "c4": 0.0}  # fmt: skip
    assert [entries[1][k] for k in GRID_KEYS] == BOWL and entries[1]["alpha0"] == 0.0
    assert entries[2]["axis"] == "radius" and all(entries[2][k] == 0.0 for k in COEFFICIENTS)  # defaults
    preset = small_preset().replace(effects=entries)
    path = tmp_path / "p.yaml"
    save_preset(preset, path)
    effects = build_effects(load_preset(path).effects)
    assert [e.to_entry()["name"] for e in effects] == ["axis_disparity_term", "disparity_distortion", "axis_validity_term"]
    assert effects[0].axis == "column" and effects[0].values()["c3"] == pytest.approx(-0.05, abs=1e-6)
    assert effects[1].grid().flatten().tolist() == pytest.approx(BOWL, abs=1e-6)


@pytest.mark.parametrize(
    "entry, message",
    [
        ({"name": "axis_disparity_term", "axis": "diagonal"}, r"x\.yaml: effects\[0\]\.axis: unknown axis 'diagonal' of axis_disparity_term \(choices: radius, row"),
        ({"name": "axis_validity_term", "coefficients": [1.0, 2.0]}, r"effects\[0\]\.coefficients: axis_validity_term takes a list of 5 values \(c0, c1, c2, c3, c4\), got 2 values"),
        ({"name": "disparity_distortion", "grid": [0.1] * 12}, r"effects\[0\]\.grid: disparity_distortion takes a list of 15 values .* got 12 values"),
        ({"name": "disparity_distortion", "grid": 0.3}, r"takes a list of 15 values .* got 0\.3"),
        ({"name": "axis_disparity_term", "coefficients": [0.1] * 5, "c1": 0.2}, r"effects\[0\]\.c1: given both alone and in 'coefficients'"),
        ({"name": "axis_disparity_term", "c1": "big"}, r"effects\[0\]\.c1: expected a finite number \(px\), got 'big'"),
        ({"name": "axis_disparity_term", "c7": 0.1}, r"effects\[0\]\.c7: unknown parameter of axis_disparity_term"),
        ({"name": "disparity_distortion", "alpha1": 0.5}, r"effects\[0\]\.alpha1: must be in \[-0\.1, 0\.1\] 1/px"),
    ],
)  # fmt: skip
def test_bad_entries_fail_with_one_line(entry, message):
    with pytest.raises(InputError, match=message) as info:
        validate_effects([entry], "x.yaml")
    assert "\n" not in str(info.value)


def test_bad_entries_in_a_preset_file_fail_with_one_line(tmp_path):
    path = tmp_path / "bad.yaml"
    save_preset(small_preset(), path)
    text = path.read_text()
    assert "\neffects:" in text
    for effects, message in [
        ("[{name: axis_validity_term, axis: colum}]", r"bad\.yaml: effects\[0\]\.axis: unknown axis 'colum'"),
        ("[{name: axis_validity_term, coefficients: [1, .nan, 0, 0, 0]}]",
         r"bad\.yaml: effects\[0\]\.coefficients: expected a finite number"),
    ]:  # fmt: skip
        lines = [f"effects: {effects}" if line.startswith("effects:") else line for line in text.splitlines()]
        path.write_text("\n".join(lines) + "\n")
        with pytest.raises(InputError, match=message) as info:
            load_preset(path)
        assert "\n" not in str(info.value)


# --------------------------------------------------------------------------------------------
# Neutral = bit-identical


def test_neutral_settings_leave_the_sensor_output_bit_identical():
    preset = small_preset()
    geometry = plane_geometry(preset.intrinsics, normal=tilted_normal(40), distance=1.6, rect=RECT)
    base = run(preset, geometry)
    for axis in AXIS_DOMAINS:
        neutral = run(preset, geometry, [
            {"name": "disparity_distortion", "alpha0": 1.5, "alpha1": -0.05},  # the decay alone changes nothing
            {"name": "axis_disparity_term", "axis": axis},
            {"name": "axis_validity_term", "axis": axis},
        ])  # fmt: skip
        for key in ("depth", "valid", "valid_soft", "disparity", "raw_depth"):
            assert torch.equal(getattr(neutral, key), getattr(base, key)), (axis, key)


# --------------------------------------------------------------------------------------------
# Physics: the distortion


def test_distortion_field_interpolates_its_control_values_and_reproduces_a_constant():
    grid = torch.tensor(BOWL, dtype=torch.float64).reshape(GRID_ROWS, GRID_COLS)
    xs = torch.linspace(-X_EXTENT, X_EXTENT, GRID_COLS, dtype=torch.float64)
    ys = torch.linspace(-Y_EXTENT, Y_EXTENT, GRID_ROWS, dtype=torch.float64)
    y, x = torch.meshgrid(ys, xs, indexing="ij")
    assert torch.allclose(sample_field(grid, x, y), grid, atol=1e-12)  # passes through the control points
    anywhere = torch.rand(50, dtype=torch.float64) * 1.6 - 0.8
    assert torch.allclose(sample_field(torch.full_like(grid, 0.3), anywhere, anywhere.flip(0)),
                          torch.full_like(anywhere, 0.3), atol=1e-12)  # fmt: skip
    # Control values symmetric about the centre give a field symmetric about the principal point.
    px = torch.tensor([-0.4, -0.2, 0.2, 0.4], dtype=torch.float64)
    py = torch.full_like(px, 0.1)
    field = sample_field(grid, px, py)
    assert torch.allclose(field, field.flip(0), atol=1e-12)
    assert torch.allclose(sample_field(grid, px, -py), field, atol=1e-12)


def test_distortion_shift_is_the_pattern_times_the_disparity_decay():
    """d' - d = D(u, v) exp(alpha0 - alpha1 d) at every matched pixel, on walls at 0.8 and 2.5 m.

    The device's clean-up is off: its hole fill copies a neighbour's (distorted) disparity into a
    filled pixel, so the law holds at the matcher's own pixels, before the clean-up.
    """
    preset = small_preset(cleanup_speckle_px=0, cleanup_hole_px=0)
    intr = preset.intrinsics
    fb = preset.focal_px * preset.baseline_m
    alpha0, alpha1 = 0.2, 0.08
    entry = {"name": "disparity_distortion", "grid": BOWL, "alpha0": alpha0, "alpha1": alpha1}
    effect = build_effects(validate_effects([entry]))[0]
    x, y = normalised_coordinates(intr.height, intr.width, intr.fx, intr.fy, intr.cx, intr.cy)
    pattern = sample_field(effect.grid().detach().double(), x.double(), y.double())
    mean_shift = {}
    for z in (0.8, 2.5):
        geometry = plane_geometry(intr, distance=z)
        base, warped = run(preset, geometry), run(preset, geometry, [entry])
        d0, d1 = disparity_of(base, fb), disparity_of(warped, fb)
        matched = (d0 > 0) & base.valid
        assert matched.float().mean() > 0.8
        expected = pattern * torch.exp(alpha0 - alpha1 * d0)
        assert torch.allclose((d1 - d0)[matched], expected[matched], atol=2e-4), z
        mean_shift[z] = float((d1 - d0)[matched].abs().mean())
    # The pattern fades as disparity grows: the near wall (larger d) is shifted less, by the model's ratio.
    ratio = math.exp(-alpha1 * (fb / 0.8 - fb / 2.5))
    assert mean_shift[0.8] / mean_shift[2.5] == pytest.approx(ratio, rel=0.05)
    assert mean_shift[0.8] < 0.5 * mean_shift[2.5]


# --------------------------------------------------------------------------------------------
# Physics: the axis terms


@pytest.mark.parametrize("axis", ["column", "row", "radius"])
def test_axis_disparity_term_follows_its_coefficients_along_its_axis_only(axis):
    preset = small_preset()
    intr = preset.intrinsics
    geometry = plane_geometry(intr, distance=1.5)
    ctx = ctx_for(preset, geometry)
    coefficients = [0.05, 0.3, -0.2, 0.1, 0.05]
    effect = AxisDisparityTerm(axis=axis, **dict(zip(COEFFICIENTS, coefficients)))
    disparity = torch.full(geometry.shape, 7.0)
    with torch.no_grad():
        shift = (effect(disparity, fresh(ctx)) - disparity).double()
    x, y = normalised_coordinates(intr.height, intr.width, intr.fx, intr.fy, intr.cx, intr.cy)
    value = {"column": x, "row": y, "radius": torch.sqrt(x * x + y * y)}[axis].double().numpy()
    low, high = AXIS_DOMAINS[axis]
    expected = legendre_numpy(np.clip(2 * (value - low) / (high - low) - 1, -1, 1), coefficients)
    assert np.allclose(shift.numpy(), expected, atol=1e-5)
    assert float(shift.max() - shift.min()) > 0.3  # it does vary along its axis ...
    if axis == "column":  # ... and not along the other one
        assert float(shift.std(0).max()) < 1e-6
    elif axis == "row":
        assert float(shift.std(1).max()) < 1e-6
    else:  # constant on rings about the principal point: mirror images agree
        assert torch.allclose(shift, shift.flip(0).flip(1), atol=1e-5)  # cx, cy are the image centre
    # No match, no shift.
    assert torch.equal(effect(torch.zeros(geometry.shape), fresh(ctx)), torch.zeros(geometry.shape))


def test_axis_disparity_term_along_depth_changes_depth_by_its_profile():
    preset = small_preset()
    fb = preset.focal_px * preset.baseline_m
    coefficients = [0.1, 0.3, 0.0, 0.0, 0.0]  # grows linearly with depth over 0.3 .. 5 m
    entry = {"name": "axis_disparity_term", "axis": "depth", "coefficients": coefficients}
    for z in (0.9, 2.6):
        geometry = plane_geometry(preset.intrinsics, distance=z)
        base, shifted = run(preset, geometry), run(preset, geometry, [entry])
        d0, d1 = disparity_of(base, fb), disparity_of(shifted, fb)
        ok = base.valid
        z0 = (fb / d0[ok]).numpy()
        expected = legendre_numpy(2 * (z0 - 0.3) / 4.7 - 1, coefficients)
        assert np.allclose((d1 - d0)[ok].numpy(), expected, atol=2e-4), z
        # constant along the image for a fronto-parallel wall (up to its measured-depth noise)
        assert float((d1 - d0)[ok].std()) < 0.02


def test_axis_validity_term_drops_exactly_where_its_keep_logit_falls_below_minus_ln3():
    preset = small_preset()
    intr = preset.intrinsics
    geometry = plane_geometry(intr, distance=1.4)
    entry = {"name": "axis_validity_term", "axis": "column", "coefficients": [0.0, -5.0, 0.0, 0.0, 0.0]}
    base, cut = run(preset, geometry), run(preset, geometry, [entry])
    # s = -5 t with t = x / 0.6: dropped where s < -ln 3, i.e. right of x = 0.6 ln 3 / 5.
    x, _ = normalised_coordinates(intr.height, intr.width, intr.fx, intr.fy, intr.cx, intr.cy)
    edge = 0.6 * math.log(3.0) / 5.0
    assert base.valid[x > edge + 0.01].float().mean() > 0.8
    assert not cut.valid[x > edge + 0.01].any()
    assert torch.equal(cut.valid[x < edge - 0.01], base.valid[x < edge - 0.01])
    # Validity only: depth untouched, but for the device's hole fill, whose source (a hole's nearest valid
    # pixel) may change when the cut empties a region near it (one pixel of 9,000, 11 px from the cut, with
    # the noise drawn for the IR margin's wider image).
    assert float((cut.depth[cut.valid] == base.depth[cut.valid]).float().mean()) > 0.999


def test_axis_validity_term_along_edge_distance_removes_a_band_at_depth_edges():
    # The device's clean-up off: its speckle filter would also drop the valid islands the cut leaves.
    preset = small_preset(cleanup_speckle_px=0, cleanup_hole_px=0)
    geometry = plane_geometry(preset.intrinsics, distance=1.8, rect=RECT)
    dist = edge_distance(geometry.clean_depth)
    # keep logit rising from -6 at an edge to +6 at 30 px: the band ends where s = -ln 3
    entry = {"name": "axis_validity_term", "axis": "edge_distance", "coefficients": [0.0, 6.0, 0.0, 0.0, 0.0]}
    base, cut = run(preset, geometry), run(preset, geometry, [entry])
    band = 30.0 * (1.0 - math.log(3.0) / 6.0) / 2.0  # t = -ln3 / 6 -> dist = 15 (1 - ln3 / 6) = 12.25 px
    assert not cut.valid[dist < band - 0.5].any()
    assert torch.equal(cut.valid[dist > band + 0.5], base.valid[dist > band + 0.5])
    assert base.valid[(dist < band - 0.5) & ~geometry.shadow].float().mean() > 0.5


def test_pixel_axes_read_the_context_like_the_named_effects():
    preset = small_preset()
    geometry = plane_geometry(preset.intrinsics, normal=tilted_normal(50), distance=1.5, rect=RECT)
    ctx = ctx_for(preset, geometry)
    depth = geometry.clean_depth
    fb = float(ctx.fx * ctx.baseline)
    disparity = torch.where(depth > 0, fb / depth.clamp_min(1e-6), torch.zeros_like(depth))
    hit = geometry.hit
    assert torch.allclose(pixel_axis("depth", ctx, disparity, "disparity")[hit], depth[hit], rtol=1e-5)
    assert torch.equal(pixel_axis("depth", ctx, depth, "validity"), depth)
    assert torch.equal(pixel_axis("edge_distance", ctx, depth, "validity"), edge_distance(depth))
    theta = pixel_axis("incidence", ctx, depth, "validity")
    assert float(theta[hit & (depth > 1.2)].median()) == pytest.approx(50.0, abs=12.0)  # the tilted wall
    with pytest.raises(KeyError, match="unknown pixel axis"):
        pixel_axis("diagonal", ctx, depth, "validity")


def test_axis_shape_and_the_least_squares_helpers_return_what_was_put_in():
    coefficients = [0.05, -0.2, 0.1, 0.0, 0.03]
    term = AxisDisparityTerm(axis="incidence", **dict(zip(COEFFICIENTS, coefficients)))
    values, shape = axis_shape(term, points=46)
    assert values[0] == 0.0 and values[-1] == 90.0 and shape.shape == (46,)
    assert np.allclose(shape, legendre_numpy(values / 45.0 - 1.0, coefficients), atol=1e-6)
    fitted = fit_axis_coefficients("incidence", values, shape)
    assert np.allclose(fitted, coefficients, atol=1e-5)
    plane = (np.arange(46) % 2 == 0).astype(float)  # half the pixels carry an extra offset (a plane fitted to them)
    fitted = fit_axis_coefficients("incidence", values, shape + 0.3 * plane, nuisance=plane[:, None])
    assert np.allclose(fitted, coefficients, atol=1e-5)
    # Pixels on a few rows only (one object's): the degree-4 fit of noisy data there has coefficients far beyond
    # +-1 px (clipped, its shape would be unrelated to the data); a lower degree that stays in range is used.
    rng = np.random.default_rng(3)
    rows = rng.uniform(0.05, 0.12, 2000)
    bias = 0.1 + 1.5 * (rows - 0.05) + rng.normal(0.0, 0.05, rows.size)
    fitted = np.array(fit_axis_coefficients("row", rows, bias))
    assert np.all(np.abs(fitted) <= 1.0)
    on_data = legendre_numpy(rows / 0.48, fitted)
    assert np.sqrt(np.mean((on_data - bias) ** 2)) < 0.06  # within the noise on the rows the data cover
    keep_values, keep = axis_shape(AxisValidityTerm(axis="signal", c0=-3.0, c1=4.0))
    assert keep_values[0] == pytest.approx(0.1) and keep_values[-1] == pytest.approx(1000.0)  # log-spaced counts
    assert keep[0] < 0.01 and keep[-1] == 1.0 and np.all(np.diff(keep) >= 0)  # more signal, more kept
    # The distortion grid from a synthetic residual (disparities 4 .. 14 px, alpha1 known).
    rng = np.random.default_rng(0)
    x, y = rng.uniform(-0.55, 0.55, 3000), rng.uniform(-0.42, 0.42, 3000)
    d = rng.uniform(4.0, 14.0, 3000)
    grid = torch.tensor(BOWL, dtype=torch.float64).reshape(GRID_ROWS, GRID_COLS)
    target = sample_field(grid, torch.as_tensor(x), torch.as_tensor(y)).numpy() * np.exp(-0.05 * d)
    target[::10] += rng.normal(0.0, 3.0, 300)  # a tenth of the pixels mismatched: the trimmed fit ignores them
    recovered = np.array(fit_distortion_grid(x, y, d, target, alpha1=0.05, keep_quantile=0.8)).reshape(GRID_ROWS, GRID_COLS)
    inside = np.abs(np.linspace(-X_EXTENT, X_EXTENT, GRID_COLS)) < 0.56  # control columns within the pixels
    assert np.allclose(recovered[:, inside], np.array(BOWL).reshape(GRID_ROWS, GRID_COLS)[:, inside], atol=0.02)


# --------------------------------------------------------------------------------------------
# Gradients


@pytest.mark.parametrize(
    "name, key, values",
    [
        ("disparity_distortion", "d_r0c1", {"grid": BOWL, "alpha0": 0.1, "alpha1": 0.05}),
        ("disparity_distortion", "d_r1c2", {"grid": BOWL, "alpha0": 0.1, "alpha1": 0.05}),
        ("disparity_distortion", "alpha0", {"grid": BOWL, "alpha0": 0.1, "alpha1": 0.05}),
        ("disparity_distortion", "alpha1", {"grid": BOWL, "alpha0": 0.1, "alpha1": 0.05}),
        ("axis_disparity_term", "c3", {"axis": "radius", "coefficients": [0.1, 0.2, -0.1, 0.05, 0.0]}),
        ("axis_disparity_term", "c1", {"axis": "signal", "coefficients": [0.1, 0.2, -0.1, 0.05, 0.0]}),
        ("axis_validity_term", "c2", {"axis": "incidence", "coefficients": [-2.0, 0.5, 0.3, 0.0, 0.0]}),
        ("axis_validity_term", "c0", {"axis": "column", "coefficients": [-2.0, 0.5, 0.3, 0.0, 0.0]}),
    ],
)
def test_gradient_matches_finite_differences(name, key, values):
    torch.manual_seed(0)
    preset = small_preset()
    geometry = plane_geometry(preset.intrinsics, normal=tilted_normal(55), distance=1.3, rect=RECT)
    ctx = ctx_for(preset, geometry, signal=geometry.albedo * 20.0 * (1 + torch.rand(geometry.shape)))
    ctx = in_double(ctx)
    effect = build_effects(validate_effects([{"name": name, **values}]))[0].double()
    depth = geometry.clean_depth.double()
    x = 10.0 / depth.clamp_min(0.1) if effect.stage == "disparity" else depth
    weights = torch.rand(geometry.shape, dtype=torch.float64)
    _fd_check(effect, key, lambda: (effect(x, fresh(ctx)) * weights).sum())


def test_gradients_reach_every_new_parameter_through_the_full_sensor():
    preset = small_preset()
    entries = [{"name": "disparity_distortion", "grid": BOWL, "alpha1": 0.05},
               {"name": "axis_disparity_term", "axis": "column", "coefficients": [0.1, 0.2, 0.0, 0.0, 0.1]},
               {"name": "axis_validity_term", "axis": "depth", "coefficients": [-0.5, -1.0, 0.5, 0.0, 0.0]}]  # fmt: skip
    sensor = DepthSensor(preset.replace(effects=entries))
    geometry = plane_geometry(preset.intrinsics, normal=tilted_normal(45), distance=1.4, rect=RECT)
    out = sensor(geometry, seed=1)
    ((out.depth * out.valid).sum() + out.valid_soft.sum()).backward()
    for effect in sensor.effects:
        for key, raw in effect.raw.items():
            assert raw.grad is not None and torch.isfinite(raw.grad), (effect.name, key)
            assert float(raw.grad) != 0.0, (effect.name, key)


# --------------------------------------------------------------------------------------------
# Recovery by ``fit`` (effect:NAME parameters)


class MatchOnce:
    """A block-matching function memoised per IR image (``len``: the images matched): the fitted parameters all act
    after the matcher, so its result for a frame is the same at every step (the fit itself runs unchanged)."""

    def __init__(self):
        self.results = {}

    def __len__(self) -> int:
        return len(self.results)

    def __call__(self, observed, *args, **kwargs):
        assert not observed.requires_grad
        key = (hashlib.blake2b(observed.contiguous().numpy().tobytes(), digest_size=16).hexdigest(), tuple(observed.shape),
               tuple(float(a) if isinstance(a, (int, float)) or torch.is_tensor(a) and a.numel() == 1 else id(a) for a in args))  # fmt: skip
        if key not in self.results:
            self.results[key] = match(observed, *args, **kwargs)
        return self.results[key]

    def sensor(self, preset) -> DepthSensor:
        """A sensor of ``preset`` whose matcher stage uses this function."""
        return DepthSensor(preset, stages={"matcher": dataclasses.replace(BlockMatcher.from_preset(preset),
                                                                           function=self)})  # fmt: skip


@pytest.fixture
def matcher_once():
    with torch_threads(1):  # many small steps: one thread is faster on a shared machine
        yield MatchOnce()


def frames_with(truth, geometries, seed: int = 7) -> list[FrameData]:
    """FrameData of analytic geometries whose 'real' depth comes from the sensor preset ``truth``."""
    sensor = DepthSensor(truth)
    intr = truth.intrinsics
    x, y = normalised_coordinates(intr.height, intr.width, intr.fx, intr.fy, intr.cx, intr.cy)
    frames = []
    for index, geometry in enumerate(geometries):
        with torch.no_grad():
            real = sensor(geometry, seed=[seed, index])
        region = geometry.hit & ~geometry.shadow
        frames.append(FrameData(
            name=f"f{index}", index=index, intrinsics=intr, crop=(0, 0, intr.width, intr.height), geometry=geometry,
            instance=torch.zeros(geometry.shape, dtype=torch.int32), real_depth=real.depth, real_valid=real.valid,
            region=region, object_region=region & False, incidence_deg=torch.zeros(geometry.shape),
            radius=torch.sqrt(x * x + y * y)))  # fmt: skip
    return frames


def fitted_shift(sensor, frames) -> tuple[torch.Tensor, torch.Tensor]:
    """The disparity change (px) the sensor's effects make on each frame's matched pixels (concatenated)."""
    base = DepthSensor(sensor.preset.replace(effects=[]))
    out = []
    for f in frames:
        noise = sensor.draw_noise(f.noise_seed(0))
        with torch.no_grad():
            a, b = base(f.geometry, noise=noise), sensor(f.geometry, noise=noise)
        fb = float((sensor.baseline * sensor.focal_scale).detach()) * f.intrinsics.fx
        ok = a.valid
        out.append((disparity_of(b, fb) - disparity_of(a, fb))[ok])
    return torch.cat(out)


def walls(intr):
    return [plane_geometry(intr, distance=1.0), plane_geometry(intr, normal=tilted_normal(30, "y"), distance=1.6),
            plane_geometry(intr, normal=tilted_normal(25), distance=2.4)]  # fmt: skip


def test_fit_recovers_a_disparity_distortion_field(matcher_once):
    torch.manual_seed(0)
    preset = small_preset(96, 72)
    truth = preset.replace(effects=[{"name": "disparity_distortion", "grid": BOWL, "alpha1": 0.05}])
    start = preset.replace(effects=[{"name": "disparity_distortion"}])  # neutral start
    frames = frames_with(truth, walls(preset.intrinsics))
    sensor = matcher_once.sensor(start)
    matched_before = len(matcher_once)
    result = fit_sensor(sensor, frames, ["effect:disparity_distortion"], steps=40, lr=3e-3, progress=False,
                        search=False)  # fmt: skip
    assert result.trainable == len(GRID_KEYS) + 2
    assert len(matcher_once) == matched_before + len(frames)  # the matcher ran once per frame: only post-matching parameters moved
    # The shift field D(u, v) exp(alpha0 - alpha1 d) on the fit frames and on a wall at a depth not fitted.
    held = frames_with(truth, [plane_geometry(preset.intrinsics, normal=tilted_normal(20, "y"), distance=1.3)], seed=8)
    for name, check in (("fit frames", frames), ("held-out wall", held)):
        true_shift = fitted_shift(DepthSensor(truth), check)
        shift = fitted_shift(sensor, check)
        rms_true = float(true_shift.pow(2).mean().sqrt())
        rms_error = float((shift - true_shift).pow(2).mean().sqrt())
        print(f"\ndistortion recovery, {name}: rms shift {rms_true:.3f} px, rms error {rms_error:.3f} px")
        assert rms_error < 0.2 * rms_true, name  # within 20 % (rms) of the true field
    assert result.history[-1]["total"] < result.history[0]["total"]


def test_fit_recovers_an_axis_disparity_term_along_columns(matcher_once):
    torch.manual_seed(0)
    preset = small_preset(96, 72)
    true_c = [0.0, 0.4, 0.0, -0.2, 0.0]  # an odd profile: +0.6 px at the right edge, -0.6 px at the left
    truth = preset.replace(effects=[{"name": "axis_disparity_term", "axis": "column", "coefficients": true_c}])
    start = preset.replace(effects=[{"name": "axis_disparity_term", "axis": "column"}])
    frames = frames_with(truth, walls(preset.intrinsics))
    sensor = matcher_once.sensor(start)
    fit_sensor(sensor, frames, ["effect:axis_disparity_term"], steps=30, lr=3e-3, progress=False, search=False)
    effect = sensor.effects[0]
    values, fitted = axis_shape(effect, 25)
    _, truth_shape = axis_shape(build_effects(truth.effects)[0], 25)
    inside = np.abs(values) <= 0.5  # the image spans |x| <= 0.56
    error = np.abs(fitted - truth_shape)[inside].max()
    print(f"\naxis term recovery: max profile error {error:.3f} px of {np.abs(truth_shape[inside]).max():.3f} px, "
          f"coefficients {[round(v, 3) for v in effect.values().values()]}")  # fmt: skip
    assert error < 0.25 * np.abs(truth_shape[inside]).max()
    assert effect.values()["c1"] == pytest.approx(true_c[1], abs=0.12)


def test_legendre_basis_is_the_numpy_series():
    t = torch.linspace(-1, 1, 21, dtype=torch.float64)
    basis = legendre_basis(t)
    for k in range(len(COEFFICIENTS)):
        unit = np.zeros(k + 1)
        unit[k] = 1.0
        assert np.allclose(basis[k].numpy(), legendre_numpy(t.numpy(), unit), atol=1e-12)


def test_fit_recovers_an_axis_validity_term_along_columns(matcher_once):
    preset = small_preset(96, 72)
    true_c = [0.0, -5.0, 0.0, 0.0, 0.0]  # no depth right of x = 0.6 ln 3 / 5 = 0.13
    truth = preset.replace(effects=[{"name": "axis_validity_term", "axis": "column", "coefficients": true_c}])
    start = preset.replace(effects=[{"name": "axis_validity_term", "axis": "column"}])
    frames = frames_with(truth, walls(preset.intrinsics))
    sensor = matcher_once.sensor(start)
    fit_sensor(sensor, frames, ["effect:axis_validity_term"], steps=30, progress=False, search=False)
    true_sensor = DepthSensor(truth)
    disagree, dropped = [], []
    for f in frames:  # the fitted and the true sensor on the same noise draws
        noise = sensor.draw_noise(f.noise_seed(0))
        with torch.no_grad():
            a, b = sensor(f.geometry, noise=noise), true_sensor(f.geometry, noise=noise)
        disagree.append((a.valid != b.valid)[f.region].float().mean())
        dropped.append((~b.valid)[f.region].float().mean())
    values, keep = axis_shape(sensor.effects[0], 61)
    edge = values[np.argmax(keep < 0.5)]  # the fitted term's first dropped column
    print(f"\nvalidity term recovery: {100 * float(max(disagree)):.1f} % of pixels disagree with the true sensor, "
          f"drop edge at x = {edge:.3f} (true 0.132), coefficients {[round(v, 2) for v in sensor.effects[0].values().values()]}")  # fmt: skip
    assert min(dropped) > 0.3  # the truth drops a large part of every frame
    assert float(max(disagree)) < 0.05
    assert edge == pytest.approx(0.6 * math.log(3.0) / 5.0, abs=0.05)


def test_set_values_takes_the_current_option_and_refuses_another():
    term = AxisDisparityTerm(axis="depth")
    term.set_values(axis="depth", c2=0.3)  # a search point may carry its axis
    assert term.values()["c2"] == pytest.approx(0.3, abs=1e-6)
    with pytest.raises(ValueError, match="axis of axis_disparity_term is 'depth'"):
        term.set_values(axis="row")
    with pytest.raises(KeyError):
        AxisDisparityTerm(axis="diagonal")
