"""Fitting that transfers (issue 14): held-out splits by scene, bounds and prior, uncertainties,
reverting what did not help, and the synthetic "hidden device" fitted on one scene list and
judged on another.
"""

from __future__ import annotations

import dataclasses
import math
import textwrap
from pathlib import Path

import numpy as np
import pytest
import torch
from test_compare import SMALL_PRESET, render

from torch_threads import torch_threads
from ddsgen.errors import InputError
from ddsgen.realscan.gap import gap
from ddsgen.fit.device_keys import search_grid, set_key
from ddsgen.realscan.losses import FIT_WEIGHTS, LossWeights, without_plane_pose
from ddsgen.realscan.plane_depth import plane_depth_for, undo_disparity_effects
from ddsgen.sensor.effects.context import EffectContext
from ddsgen.fit.fit_report import at_bound
from ddsgen.fit.fitting import fit_sensor
from ddsgen.fit.parameters import SENSOR_PARAMS, resolve_params
from ddsgen.fit.priors import Priors
from ddsgen.fit.revert import revert_unhelpful, snapshot
from ddsgen.realscan.simulate import prepare_frames, simulate
from ddsgen.fit.tiles import step_tiles
from ddsgen.fit.split import scene_of, split_fit_held_out
from ddsgen.fit.uncertainty import estimate_uncertainty, sandwich_sigma
from ddsgen.io.scanfolder import read_scan_folder
import yaml

from ddsgen.preset import load_preset, preset_from_dict
from ddsgen.sensor.depth_sensor import DepthSensor
from ddsgen.sensor.effects.distortion import GRID_KEYS


@dataclasses.dataclass
class _Frame:  # the fields of FrameData a split reads
    name: str
    region: torch.Tensor
    object_region: torch.Tensor


def _frame(name, region):
    return _Frame(name, region, region.clone())


def test_split_holds_out_whole_scenes_then_frames_then_blocks_of_a_frame():
    region = torch.ones(6, 10, dtype=torch.bool)
    frames = [_frame(f"{s:06d}/{i:06d}", region) for s in (1, 2, 3, 4) for i in range(3)]
    fit, held, kind = split_fit_held_out(frames, 0.25, seed=3)
    assert kind == "scene" and len(held) == 3 and len(fit) == 9
    assert len({scene_of(f.name) for f in held}) == 1
    assert not {scene_of(f.name) for f in held} & {scene_of(f.name) for f in fit}
    fit, held, kind = split_fit_held_out(frames[:3], 0.34, seed=3)
    assert kind == "frame" and len(held) == 1 and len(fit) == 2
    # One frame, an object at its left edge (as the real cat): interleaved blocks, the object's pixels shared.
    region = torch.zeros(120, 160, dtype=torch.bool)
    region[10:110, 5:155] = True
    objects = torch.zeros_like(region)
    objects[40:80, 5:35] = True
    one = _Frame("a/000000", region, objects)
    (fit,), (held,), kind = split_fit_held_out([one], 0.25)
    assert kind == "spatial"
    assert not bool((fit.region & held.region).any()) and torch.equal(fit.region | held.region, region)
    block = 8 * 8  # the most one block can tip the balance
    assert abs(int(fit.object_region.sum()) - int(held.object_region.sum())) <= block
    assert abs(int(fit.region.sum()) - int(held.region.sum())) <= block
    for half in (fit, held):  # each half spans the view: both sides of the image and the object's rows
        columns = half.region.nonzero()[:, 1]
        assert int(columns.min()) < 40 and int(columns.max()) > 120
    assert torch.equal(split_fit_held_out([one], 0.25, seed=0)[0][0].region, fit.region)  # seeded
    assert split_fit_held_out(frames, 0.0)[2] == "none"
    with pytest.raises(InputError, match="--holdout"):
        split_fit_held_out(frames, 1.0)


def test_bounds_and_prior_keep_parameters_physical():
    sensor = DepthSensor(preset_from_dict(yaml.safe_load(SMALL_PRESET)))
    table = {n: SENSOR_PARAMS[n] for n in ("beta", "baseline", "emitted_intensity")}
    priors = Priors(sensor, table, prior_mm=1.0)
    for t in (sensor.log_beta, sensor.log_baseline, sensor.log_emitted_intensity):
        t.requires_grad_(True)
    assert float(priors.penalty().detach()) == 0.0
    with torch.no_grad():
        sensor.log_beta.fill_(math.log(2.0))  # below beta's 5..40
        sensor.log_baseline.fill_(math.log(0.075 * 1.2))  # beyond +-5 %
        sensor.log_emitted_intensity.fill_(math.log(1.5e6 * 2.0))  # within x0.25..x4: untouched
    penalty = float(priors.penalty().detach())
    width = SENSOR_PARAMS["beta"].width
    assert penalty > (math.log(15.0 / 2.0) / width) ** 2  # at least beta's own term
    assert sorted(priors.project()) == ["baseline", "beta"]
    values = sensor.physical_parameters()
    assert values["softargmax_beta"] == pytest.approx(5.0, rel=1e-5)
    assert values["baseline_m"] == pytest.approx(0.075 * 1.05, rel=1e-5)
    assert values["emitted_intensity"] == pytest.approx(3.0e6, rel=1e-5)
    assert sorted(priors.at_bound()) == ["baseline", "beta"]
    # The report flags a value on a bound (the real cat frame's SNR search ends at x4 of kinect_v1's eta_c).
    assert at_bound(["factor", 0.25, 4.0], 1.5e6, 6.0e6) and not at_bound(["factor", 0.25, 4.0], 1.5e6, 5.9e6)
    assert at_bound(["range", 5.0, 40.0], 15.0, 5.0) and not at_bound(["range", 5.0, 40.0], 15.0, 25.9)


def test_revert_returns_the_input_when_the_groups_it_kept_do_not_beat_it(monkeypatch):
    """The first pass keeps beta because, beside the fitted baseline, removing it hurts; then the baseline is
    reverted and beta, judged again beside it, goes too (backward elimination). The output must be the input (as the
    summary says), not a preset that keeps beta. Seen on the real cat with `fit --steps 20`: held-out 9.48 mm in,
    beta 15 -> 14.2 kept, and the line "the output keeps the input's values". Then: a group kept in the first pass
    that hurts beside what was reverted after it goes out, and the rest stays."""
    from types import SimpleNamespace

    from ddsgen.fit import revert

    sensor = DepthSensor(preset_from_dict(yaml.safe_load(SMALL_PRESET)))
    names = ["emitted_intensity", "beta", "baseline"]
    resolved = resolve_params(sensor, [*names, "speckle_scale"])  # the fit leaves the speckle scale where it was
    start = snapshot(resolved)
    with torch.no_grad():
        sensor.log_emitted_intensity.add_(0.1)
        sensor.log_beta.add_(-0.05)
        sensor.log_baseline.add_(-0.004)
    fitted = snapshot(resolved)
    # The held-out gap (mm) by which of the three groups keep their fitted values (snr, beta, baseline).
    gaps = {(1, 1, 1): 9.50, (0, 1, 1): 9.50, (0, 0, 1): 9.51, (0, 1, 0): 9.49, (0, 0, 0): 9.48}

    def stand_in_gap(sensor_, frames, **kwargs):
        changed = tuple(int(not torch.equal(resolved[n][0], start[n][0])) for n in names)
        return SimpleNamespace(gap=gaps[changed])

    monkeypatch.setattr(revert, "gap", stand_in_gap)
    outcome = revert_unhelpful(sensor, resolved, start, [], SENSOR_PARAMS)
    assert not outcome["better"] and outcome["gap_fitted"] == 9.50 and outcome["gap_kept"] == 9.48
    assert not any(info["kept"] for info in outcome["groups"].values())
    assert not any(revert.output_holds_fit(outcome, SENSOR_PARAMS[n].group) for n in names)
    assert revert.output_holds_fit(outcome, SENSOR_PARAMS["speckle_scale"].group)  # unchanged: not "reverted"
    for name in names:
        assert torch.equal(resolved[name][0], start[name][0]) and not torch.equal(fitted[name][0], start[name][0])
    lines = revert.revert_summary(outcome)
    assert lines[-1] == "nothing the fit changed lowers the held-out gap: the output keeps the input's values"
    assert not any(line.startswith("kept") for line in lines)
    assert ("reverted matching (beta) to the input's values: the change did not lower the held-out gap (9.48 mm "
            "without it)") in lines  # judged again once the baseline it compensated was reverted

    # When the kept group does beat the input, it stays.
    gaps[(0, 1, 0)] = 9.40
    with torch.no_grad():
        for name in names:
            resolved[name][0].copy_(fitted[name][0])
    outcome = revert_unhelpful(sensor, resolved, start, [], SENSOR_PARAMS)
    assert outcome["better"] and outcome["gap_kept"] == 9.40
    assert [g for g, info in outcome["groups"].items() if info["kept"]] == [SENSOR_PARAMS["beta"].group]
    assert torch.equal(resolved["beta"][0], fitted["beta"][0])

    # The signal-to-noise change helps beside the fitted baseline only: the first pass keeps it and reverts the
    # baseline (9.30 mm); judged again it goes (9.20 mm), and beta, which helps beside either, stays.
    gaps.update({(1, 1, 1): 9.40, (0, 1, 1): 9.45, (1, 0, 1): 9.50, (1, 1, 0): 9.30, (0, 1, 0): 9.20,
                 (1, 0, 0): 9.60})  # fmt: skip
    with torch.no_grad():
        for name in names:
            resolved[name][0].copy_(fitted[name][0])
    outcome = revert_unhelpful(sensor, resolved, start, [], SENSOR_PARAMS)
    assert outcome["better"] and outcome["gap_kept"] == 9.20
    assert [g for g, info in outcome["groups"].items() if info["kept"]] == [SENSOR_PARAMS["beta"].group]
    assert torch.equal(resolved["emitted_intensity"][0], start["emitted_intensity"][0])


def test_report_says_when_the_frames_do_not_determine_a_parameter():
    """A log-fitted parameter whose 1 s.d. exceeds its value (eta_c on the real cat with the beam fall-off fitted
    beside it: 1.25e6 +- 5.6e7), or any infinite s.d., is flagged in the command's line and parameters.txt; a
    well-determined one, a held one and a linear one near zero are not."""
    from ddsgen.fit.fit_report import fitted_line, parameter_table

    def row(fitted, sigma, bound, method="curvature"):
        return {"param": "p", "key": "k", "before": 1.0, "fitted": fitted, "after": fitted, "sigma": sigma,
                "method": method, "bound": bound, "kept": True, "at_bound": False}  # fmt: skip

    flat = row(1.25e6, 5.6e7, ["factor", 0.25, 4.0])
    assert fitted_line(flat) == "1.25e+06 +- 5.6e+07 (not identified by these frames)"
    assert parameter_table([flat]).endswith("curvature; NOT IDENTIFIED")
    assert fitted_line(row(3.0, math.inf, ["range", 0.0, 12.0])).endswith("+- inf (not identified by these frames)")
    for fine in (row(1.25e6, 7.1e4, ["factor", 0.25, 4.0]), row(0.001, 0.01, ["range", -1.0, 1.0]),
                 row(1.0, math.nan, None, method="held: off")):  # fmt: skip
        assert "not identified" not in fitted_line(fine) and "NOT IDENTIFIED" not in parameter_table([fine])


def test_sandwich_sigma_matches_the_spread_of_independent_minima():
    """Quadratic tile losses a_u (x - m_u)^2 with random centres m_u: the minimiser of the sum is the
    weighted mean of m_u, whose standard error the sandwich must reproduce; a loss that is not
    curved up (a maximum) is 'not identified'."""
    rng = np.random.default_rng(0)
    a = rng.uniform(0.5, 2.0, 400)
    m = rng.normal(0.0, 1.0, 400)
    x0 = float(np.sum(a * m) / np.sum(a))
    h = 0.1

    def losses(x):
        return list(a * (x - m) ** 2)

    sigma = sandwich_sigma(losses(x0 - h), losses(x0), losses(x0 + h), h)
    exact = math.sqrt(np.sum(a**2) * 1.0) / np.sum(a)  # sd of sum(a m) / sum(a)
    assert sigma == pytest.approx(exact, rel=0.15)
    assert math.isinf(sandwich_sigma([-v for v in losses(x0 - h)], [-v for v in losses(x0)],
                                     [-v for v in losses(x0 + h)], h))  # fmt: skip


# ------------------------------------------------------------------------------------------ hidden device

SCENES_A = textwrap.dedent(
    """\
    scenes:
      - name: boxes
        frames: 3
        objects:
          - {shape: box, size: [0.3, 0.2, 0.15], albedo: 0.6}
          - {shape: box, size: [0.2, 0.2, 0.25], albedo: 0.6}
        clutter: {count: [2, 3], area: [0.6, 0.5]}
        ground: {size: [6, 6], albedo: 0.6}
        camera: {distance: [0.9, 1.8], elevation_deg: [30, 60], azimuth_deg: [-180, 180]}
    """
)
SCENES_B = textwrap.dedent(
    """\
    scenes:
      - name: round
        frames: 2
        objects:
          - {shape: cylinder, radius: 0.08, height: 0.25, albedo: 0.6}
          - {shape: sphere, radius: 0.1, albedo: 0.6}
        clutter: {count: [1, 2], area: [0.5, 0.4]}
        ground: {size: [6, 6], albedo: 0.6}
        camera: {distance: [1.0, 2.0], elevation_deg: [40, 70], azimuth_deg: [-180, 180]}
    """
)


def hidden_device(rng) -> tuple[str, dict]:
    """A random device within the fit's bounds: its SNR (eta_c) and a smooth disparity distortion field.

    beta stays the stock value and is not fitted: against a distortion field the depth loss does not
    identify it (measured on these frames: a device with beta 23.6 came out 15.0 +- 1.9, and a device with
    beta 15 came out 21.3 +- 1.3 -- the sandwich sigma of a confounded parameter is optimistic).
    """
    eta = 1.5e6 * float(np.exp(rng.uniform(math.log(2.5), math.log(3.5))))  # within x0.25..x4
    grid = rng.uniform(-0.6, 0.6, len(GRID_KEYS)).round(3).tolist()  # a few Kinect disparity units
    text = (SMALL_PRESET.replace("emitted_intensity: 1.5e6", f"emitted_intensity: {eta:.6g}")
            + f"effects:\n  - {{name: disparity_distortion, alpha0: 0.0, alpha1: 0.02, grid: {grid}}}\n")  # fmt: skip
    return text, {"emitted_intensity": eta}


@pytest.mark.slow
def test_hidden_device_fitted_on_one_scene_list_transfers_to_another(tmp_path, set_torch_threads):
    """Fit on scene list A, judge on scene list B (other shapes, other views).

    The design is not noise-dominated: each sensor is judged on held-out frames whose support planes are
    fitted where *its* disparity errors put them (ddsgen.realscan.plane_depth; with planes fitted to the raw
    real depth the true device scored 21.4 mm and the stock one 18.6 -- the planes had absorbed the
    distortion) and the gap is averaged over two simulation noise seeds. Fit on 8 views of one layout of
    list A, 80 steps (1 thread): true device 10.55 mm, stock 18.55, fitted and kept 14.31 (0.77x);
    eta_c 4.33e6 +- 0.26e6 vs true 4.96e6. With 3 views and 30 steps (before): 0.83x. The noise texture is
    judged on the objects (``plane_nuisance``): on all pixels eta_c came out 4.24e6 in every variant (the
    plane's disparity staircase depends on where the plane was placed). Spread over 3 layouts (3+3+2 views)
    the same fit gives 0.78x but eta_c 4.24e6 +- 0.20e6 (3.6 s.d.: the sandwich s.d. of a searched
    parameter is optimistic where eta_c trades against the distortion field).
    """
    set_torch_threads(2)
    text, truth = hidden_device(np.random.default_rng(14))
    stock_text = SMALL_PRESET + "effects:\n  - {name: disparity_distortion, alpha0: 0.0, alpha1: 0.02}\n"
    for name, content in (("hidden.yaml", text), ("stock.yaml", stock_text), ("a.yaml", SCENES_A.replace("frames: 3", "frames: 8")),
                          ("b.yaml", SCENES_B)):  # fmt: skip
        (tmp_path / name).write_text(content)
    render(tmp_path / "hidden.yaml", tmp_path / "a.yaml", tmp_path / "A", 8, seed=5)
    render(tmp_path / "hidden.yaml", tmp_path / "b.yaml", tmp_path / "B", 2, seed=6)
    stock = load_preset(tmp_path / "stock.yaml")
    scans_b = read_scan_folder(tmp_path / "B")

    def held_for(sensor):
        return prepare_frames(stock, scans_b, plane_depth=plane_depth_for(sensor))

    def held_gap(sensor):
        frames = held_for(sensor)
        return float(np.mean([gap(sensor, frames, seed=s, noise_floor=False).gap for s in (1, 2)]))

    fit_frames = prepare_frames(stock, read_scan_folder(tmp_path / "A"))
    sensor = DepthSensor(stock)
    names = ["emitted_intensity", "read_noise_std", *[f"effect:disparity_distortion.{k}" for k in GRID_KEYS]]
    start = snapshot(resolve_params(sensor, names))
    stock_gap = held_gap(sensor)
    true_gap = held_gap(DepthSensor(load_preset(tmp_path / "hidden.yaml")))
    result = fit_sensor(sensor, fit_frames, names, steps=80, progress=False, start_effects=True, weights=FIT_WEIGHTS)
    sigma = estimate_uncertainty(sensor, fit_frames, result, SENSOR_PARAMS, names={"emitted_intensity"},
                                 weights=FIT_WEIGHTS)  # fmt: skip
    outcome = revert_unhelpful(sensor, resolve_params(sensor, names), start, held_for, SENSOR_PARAMS, seed=1)
    fitted_gap = held_gap(sensor)
    report = {k: (round(v["value"], 4), round(v["sigma"], 4), truth[v["key"]]) for k, v in sigma.items()}
    print(f"\nheld-out gap (2 seeds): stock {stock_gap:.2f} -> kept {fitted_gap:.2f} mm (true device {true_gap:.2f}); "
          f"fitted (value, sigma, truth): {report}; {result.seconds:.1f} s; "
          f"groups {[(g, i['kept']) for g, i in outcome['groups'].items()]}")  # fmt: skip
    assert true_gap <= 0.7 * stock_gap  # the measure sees the device, not the noise
    for name, info in sigma.items():  # recovered within three reported standard deviations (see the docstring)
        assert math.isfinite(info["sigma"]) and info["sigma"] < 0.5 * info["value"], name
        assert abs(info["value"] - truth[info["key"]]) <= 3.0 * info["sigma"], name
    assert fitted_gap <= 0.8 * stock_gap  # issue 14's target


# ------------------------------------------------------------------------------------------ device keys


@pytest.fixture(scope="module")
def steep_beam(tmp_path_factory):
    """Two 160 x 120 frames of a device whose projector beam falls off as cos^6 off its axis (stock: flat),
    prepared with the stock preset."""
    with torch_threads(2):
        tmp_path = tmp_path_factory.mktemp("device_keys")
        (tmp_path / "device.yaml").write_text(SMALL_PRESET + "projector_falloff_exponent: 6.0\nvignetting_exponent: 0.0\n")
        (tmp_path / "stock.yaml").write_text(SMALL_PRESET)
        (tmp_path / "a.yaml").write_text(SCENES_A)
        render(tmp_path / "device.yaml", tmp_path / "a.yaml", tmp_path / "A", 2, seed=5)
        stock = load_preset(tmp_path / "stock.yaml")
        yield stock, prepare_frames(stock, read_scan_folder(tmp_path / "A"))


def test_device_keys_are_fitted_by_a_search_reported_and_reverted(steep_beam):
    """A steep projector beam on a dim IR image loses the image corners; fitted from the flat stock preset,
    the 1-D search over the fall-off exponent must find a steep beam from the validity alone, carry it into
    the fitted preset, give it a finite uncertainty, and put the input's value back when reverted."""
    stock, frames = steep_beam
    sensor = DepthSensor(stock)
    names = ["projector_falloff", "vignetting"]
    resolved = resolve_params(sensor, names)
    start = snapshot(resolved)
    result = fit_sensor(sensor, frames, names, steps=0, progress=False)
    search = result.searches["projector_falloff"]
    print(f"\nfall-off profile {search['profile']}")
    # The projector and the lens fall-off shape the same radial profile: only one is searched.
    assert result.searches["vignetting"]["held"] and sensor.preset.vignetting_exponent == 0.0
    assert 4.0 <= sensor.preset.projector_falloff_exponent <= 8.0
    profile = dict(search["profile"])
    assert profile[0.0] > profile[sensor.preset.projector_falloff_exponent]  # the flat beam fits worse
    assert result.after["projector_falloff_exponent"] == sensor.preset.projector_falloff_exponent
    assert sensor.to_preset().projector_falloff_exponent == sensor.preset.projector_falloff_exponent
    hole_grid = search_grid(sensor, SENSOR_PARAMS["cleanup_hole"])  # a discrete key is searched over integers
    assert np.array_equal(hole_grid, np.round(hole_grid)) and hole_grid.min() == 0 and hole_grid.max() == 32
    set_key(sensor, "cleanup_hole_px", 7.0)
    assert sensor.preset.cleanup_hole_px == 7 and isinstance(sensor.preset.cleanup_hole_px, int)
    assert {b["param"] for b in result.bounds} >= set(names)
    sigma = estimate_uncertainty(sensor, frames, result, SENSOR_PARAMS, names={"projector_falloff"})
    assert 0.0 < sigma["projector_falloff"]["sigma"] < 4.0
    outcome = revert_unhelpful(sensor, resolved, start, frames, SENSOR_PARAMS, seed=1)
    assert outcome["groups"]["falloff"]["kept"] == (sensor.preset.projector_falloff_exponent != 0.0)
    if not outcome["groups"]["falloff"]["kept"]:
        assert sensor.preset.projector_falloff_exponent == 0.0


def test_step_tiles_are_seeded_windows_simulated_like_crops(steep_beam):
    """A tile is a window of the frame with a shifted principal point and no matching border in its region,
    chosen by (seed, step, frame); simulated, it sees the same surfaces at the same depths as the frame."""
    stock, frames = steep_beam
    frame = frames[0]
    sensor = DepthSensor(stock)
    tiles = step_tiles(frames, 64, step=3, seed=0, sensor=sensor)
    again = step_tiles(frames, 64, step=3, seed=0, sensor=sensor)
    other = step_tiles(frames, 64, step=4, seed=0, sensor=sensor)
    tile = tiles[0]
    assert tile.shape == (64, 64) and again[0].crop == tile.crop and [t.crop for t in other] != [t.crop for t in tiles]
    x0, y0, _, _ = tile.crop
    assert tile.intrinsics.cx == pytest.approx(frame.intrinsics.cx - x0)
    assert torch.equal(tile.real_depth, frame.real_depth[y0 : y0 + 64, x0 : x0 + 64])
    border = stock.block_size_px // 2 + 1
    assert not bool(tile.region[:border].any()) and not bool(tile.region[:, -border:].any())
    assert bool(tile.region.any())
    assert step_tiles(frames, None, 0, 0, sensor) == frames and step_tiles(frames, 1000, 0, 0, sensor)[0] is frame
    with torch.no_grad():
        sim_tile = simulate(sensor, tile)
        sim_full = simulate(sensor, frame)
    both = tile.region & sim_tile.valid & tile.real_valid
    full = sim_full.depth[y0 : y0 + 64, x0 : x0 + 64]
    both &= full > 0
    assert int(both.sum()) > 500
    # Same surfaces, same depth law: the tile's and the frame's simulations agree to the depth noise.
    assert float((sim_tile.depth - full)[both].abs().median()) < 0.01 * float(full[both].median())


# ------------------------------------------------------------------------------------------ the support plane


def test_plane_depth_undoes_the_sensors_disparity_errors_and_the_fit_loss_ignores_the_plane_pose():
    """A device whose disparity is off by 0.3 px (+ a distortion field) sees a table at z' = f b / (f b / z + e):
    undoing the sensor's own effects gives z back (neutral effects: the input itself). On the plane's pixels
    the fit loss drops an error affine in disparity (a plane shift or tilt explains it) and keeps the rest."""
    preset = preset_from_dict(yaml.safe_load(SMALL_PRESET)).replace(effects=[
        {"name": "disparity_offset", "offset_px": 0.3},
        {"name": "disparity_distortion", "alpha0": 0.0, "alpha1": 0.02, "grid": [0.2] * 5 + [0.0] * 5 + [-0.2] * 5}])
    sensor = DepthSensor(preset)
    intr = preset.intrinsics
    fb = intr.fx * preset.baseline_m
    z = np.fromfunction(lambda v, u: 1.0 + 0.004 * v + 0.001 * u, (intr.height, intr.width)).astype(np.float32)
    d = torch.from_numpy(fb / z)
    ctx = EffectContext(fx=intr.fx, fy=intr.fy, cx=intr.cx, cy=intr.cy, baseline=sensor.baseline)
    with torch.no_grad():
        seen = sensor.disparity_effects(d, ctx)
    observed = (fb / seen).numpy().astype(np.float32)
    observed[:5, :5] = 0.0  # invalid pixels stay invalid
    assert float(np.abs(observed[5:, 5:] - z[5:, 5:]).max()) > 0.02  # the errors are tens of mm
    undone = undo_disparity_effects(sensor, observed, intr)
    assert float(np.abs(undone[5:, 5:] - z[5:, 5:]).max()) < 2e-4 and not undone[:5, :5].any()
    neutral = DepthSensor(preset.replace(effects=[{"name": "disparity_offset", "offset_px": 0.0}]))
    assert undo_disparity_effects(neutral, observed, intr) is observed

    # The loss: plane pixels (instance 0) with an affine disparity error lose it; an object pixel keeps its error.
    h, w = 40, 60
    real = torch.full((h, w), 1.5)
    instance = torch.zeros(h, w, dtype=torch.int32)
    instance[10:20, 10:20] = 1
    v, u = torch.meshgrid(torch.arange(h, dtype=torch.float32), torch.arange(w, dtype=torch.float32), indexing="ij")
    err = (0.5 + 0.01 * u - 0.02 * v) * real**2  # mm, affine in disparity units err / z^2
    err = err + 3.0 * (instance > 0)  # and the object is 3 mm off on top
    frame = _Frame("a/000000", torch.ones(h, w, dtype=torch.bool), instance > 0)
    frame.instance, frame.real_depth = instance, real
    out = without_plane_pose(err, frame, torch.ones(h, w, dtype=torch.bool))
    plane = instance == 0
    assert float(out[plane].abs().max()) < 1e-3
    assert torch.allclose(out[~plane], err[~plane])


def test_tile_losses_on_crops_equal_the_whole_frame_masked(steep_beam):
    """The uncertainty's per-tile losses, computed on each tile's own window, are those of the whole frame masked
    to the tile (the cheap way is the same number)."""
    from ddsgen.fit.uncertainty import _tile_losses, tile_masks

    stock, frames = steep_beam
    sensor = DepthSensor(stock)
    tiles = [tile_masks(f) for f in frames]
    assert sum(len(t) for t in tiles) >= 4
    for weights in (FIT_WEIGHTS, LossWeights()):
        cropped = _tile_losses(sensor, frames, tiles, 0, weights)
        whole = _tile_losses(sensor, frames, tiles, 0, weights, crop=False)
        # float32 rounding of the plane-pose solve on a differently sized window: measured <= 1.6e-4 relative
        assert np.allclose(cropped, whole, rtol=1e-3, atol=1e-6)


def test_a_small_region_gets_smaller_uncertainty_tiles_instead_of_none():
    """A frame's objects alone (``--region objects``: on the real cat 1,148 px) hold no 90-px tile at a quarter full,
    so every sigma used to read "+- inf (not identified)". Such a region is tiled with fewer loss windows per tile
    until it has MIN_TILES; a whole-frame region keeps the 90-px tiles; weights sum to 1 either way."""
    from types import SimpleNamespace

    from ddsgen.fit.uncertainty import MIN_TILES, TILE_WINDOWS, tile_masks
    from ddsgen.realscan.losses import local_window

    intrinsics = SimpleNamespace(fx=572.41)
    window = local_window(intrinsics.fx)
    blob = torch.zeros(480, 640, dtype=torch.bool)
    blob[200:245, 300:350] = True  # 2,250 px, about the cat
    whole = torch.ones(480, 640, dtype=torch.bool)
    for region, size in ((whole, TILE_WINDOWS * window), (blob, None)):
        tiles = tile_masks(SimpleNamespace(region=region, intrinsics=intrinsics))
        assert len(tiles) >= MIN_TILES and sum(w for _, w in tiles) == pytest.approx(1.0)
        if size is not None:  # the whole frame: the evidence's own scale
            assert max(int(mask.sum()) for mask, _ in tiles) == size * size
        else:
            assert max(int(mask.sum()) for mask, _ in tiles) < (TILE_WINDOWS * window) ** 2 * 0.25


def test_edge_keeping_is_found_from_a_model_without_it(tmp_path, set_torch_threads):
    """Scans of the device model (windows across depth edges kept at ZNCC 0.35), fitted from a model with it off
    (the paper's sensor): the 1-D search switches it on near the device's value (measured: 0.3; fit loss 0.66 mm at
    1.0, 0.44 at 0.3). (The narrow fill, cleanup_fill_width, is searched the same way, but on these scenes the fit
    loss barely sees it: 0.246 -> 0.237 mm of data loss from 0 to 4 px, less than its prior.)"""
    from effects_geometry import small_preset

    from ddsgen.preset import save_preset

    set_torch_threads(2)
    device = small_preset(640, 480)
    save_preset(device, tmp_path / "device.yaml")
    render(tmp_path / "device.yaml", Path(__file__).with_name("diagnose_scenes.yaml"), tmp_path / "scans", 2, seed=4)
    model = device.replace(confirmed_match_zncc=1.0)
    frames = prepare_frames(model, read_scan_folder(tmp_path / "scans"), progress=False)
    sensor = DepthSensor(model)
    result = fit_sensor(sensor, frames, ["confirmed_match"], steps=0, progress=False)
    search = result.searches["confirmed_match"]
    print("found", search["estimate"], "(device 0.35); profile", search["profile"])
    assert 0.25 <= search["estimate"] <= 0.45  # on, near the device's 0.35: a window across an edge keeps a surface
    assert sensor.preset.confirmed_match_zncc == search["estimate"]
