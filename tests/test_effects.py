"""Effect library: neutral settings are no-ops, each effect produces its physical signature, gradients are right.

Full-sensor tests run the real DepthSensor (matcher included) on small analytic scenes
(160 x 120 px, the Kinect V1 field of view): a wall, a tilted plane, a rectangle in front
of a wall. Effects are compared against the same frame (same noise draws) without them.
"""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch

from ddsgen.errors import InputError
from ddsgen.sensor.depth_sensor import DepthSensor
from ddsgen.sensor.effects import REGISTRY, build_effects, validate_effects
from ddsgen.sensor.effects.context import EffectContext
from ddsgen.sensor.effects.features import edge_distance, image_radius, incidence_angle_deg, local_signal
from ddsgen.sensor.effects.library import LensDistortion
from effects_geometry import plane_geometry, small_preset, tilted_normal
from gradient_check import autograd_and_difference
from tiny_inputs import tiny_preset_yaml

REQUIRED = {"lens_distortion", "disparity_offset", "grazing_dropout", "edge_dropout"}
RECT = dict(z=1.0, x0=-0.12, x1=0.12, y0=-0.10, y1=0.10, albedo=0.5)


def run(preset, geometry, effects=(), seed=3):
    """One frame through the full sensor with the given ``effects:`` entries."""
    sensor = DepthSensor(preset.replace(effects=list(effects)))
    with torch.no_grad():
        return sensor(geometry, seed=seed)


def ctx_for(preset, geometry, signal=None) -> EffectContext:
    intr = preset.intrinsics
    return EffectContext(fx=torch.tensor(intr.fx), fy=torch.tensor(intr.fy), cx=intr.cx, cy=intr.cy,
                         baseline=torch.tensor(preset.baseline_m), geometry=geometry,
                         signal=signal if signal is not None else geometry.albedo * 40.0, ir_max=1023.0,
                         raw_depth=geometry.clean_depth)  # fmt: skip


def fresh(ctx: EffectContext) -> EffectContext:
    """The same frame with no feature computed yet (each call of an effect as the sensor makes it)."""
    return dataclasses.replace(ctx)


def in_double(ctx: EffectContext) -> EffectContext:
    """``ctx`` with every floating-point tensor in float64 (finite-difference checks)."""
    values = {f.name: getattr(ctx, f.name) for f in dataclasses.fields(ctx) if f.init}
    return EffectContext(**{k: (v.double() if torch.is_tensor(v) and v.is_floating_point() else v)
                            for k, v in values.items()})  # fmt: skip


# --------------------------------------------------------------------------------------------
# The library itself


def test_library_has_the_required_effects_and_two_more_with_complete_metadata():
    assert REQUIRED <= set(REGISTRY)
    assert len(REGISTRY) >= len(REQUIRED) + 2
    axes = {"depth", "incidence", "radius", "row", "column", "edge_distance", "signal"}
    for name, cls in REGISTRY.items():
        assert cls.name == name
        assert cls.stage in {"ir", "disparity", "depth", "validity", "image"}
        assert cls.description.strip().endswith(".") and cls.description.count(". ") == 0, name  # one sentence
        assert cls.signature and cls.axis in axes, name
        for key, spec in cls.params.items():
            assert spec.low <= spec.neutral <= spec.high, (name, key)
            assert spec.typical is not None and spec.low < spec.typical < spec.high, (name, key)


def test_validate_effects_rejects_unknown_names_and_out_of_range_values():
    with pytest.raises(InputError, match="did you mean 'edge_dropout'"):
        validate_effects([{"name": "edge_dropuot"}], "x.yaml")
    with pytest.raises(InputError, match="must be in"):
        validate_effects([{"name": "grazing_dropout", "angle_deg": 120}], "x.yaml")
    entry = validate_effects([{"name": "lens_distortion", "k1": -0.01}])[0]
    assert entry == {"name": "lens_distortion", "k1": -0.01, "k2": 0.0}


def test_typical_values_round_trip_through_the_reparameterisation():
    for cls in REGISTRY.values():
        typical = {k: p.typical for k, p in cls.params.items()}
        effect = cls(**typical)
        for key, value in effect.values().items():
            assert value == pytest.approx(typical[key], abs=1e-5 * (cls.params[key].high - cls.params[key].low))


# --------------------------------------------------------------------------------------------
# Neutral = no-op


def test_each_neutral_effect_is_an_identity_on_its_stage():
    preset = small_preset()
    geometry = plane_geometry(preset.intrinsics, normal=tilted_normal(50), distance=1.5, rect=RECT)
    ctx = ctx_for(preset, geometry)
    x = torch.rand(geometry.shape) * 100 + 1
    for cls in REGISTRY.values():
        effect = cls()  # all parameters neutral
        with torch.no_grad():
            y = effect((x, x, x > 50, x, x), fresh(ctx))[0] if cls.stage == "image" else effect(x, fresh(ctx))
        if cls.stage == "validity":
            lit = geometry.hit & ~geometry.shadow
            # exact up to the reparameterisation: a boundary neutral sits 1e-6 of the range inside it
            assert torch.all(y[lit] > 1 - 1e-4), cls.name
        else:
            assert torch.equal(y, x), cls.name


def test_all_library_effects_at_neutral_leave_the_sensor_output_unchanged():
    preset = small_preset()
    geometry = plane_geometry(preset.intrinsics, normal=tilted_normal(40), distance=1.6, rect=RECT)
    base = run(preset, geometry)
    neutral = run(preset, geometry, [{"name": name} for name in REGISTRY])
    assert base.valid.float().mean() > 0.5
    assert torch.equal(neutral.depth, base.depth)
    assert torch.equal(neutral.valid, base.valid)
    assert torch.allclose(neutral.valid_soft, base.valid_soft, atol=1e-4)  # boundary neutrals: 1e-6 of the range


# --------------------------------------------------------------------------------------------
# Physics


def test_disparity_offset_depth_bias_grows_with_z_squared():
    preset = small_preset()
    fb = preset.focal_px * preset.baseline_m
    offset = 0.3
    biases = {}
    for z in (0.8, 1.6, 2.8):
        geometry = plane_geometry(preset.intrinsics, distance=z)
        base = run(preset, geometry)
        shifted = run(preset, geometry, [{"name": "disparity_offset", "offset_px": offset}])
        both = base.valid & shifted.valid
        assert both.float().mean() > 0.5
        biases[z] = float((shifted.depth - base.depth)[both].median())
        expected = fb / (fb / z + offset) - z  # ~ -z^2 offset / (f b)
        assert biases[z] == pytest.approx(expected, rel=0.15), z
    assert biases[2.8] < biases[1.6] < biases[0.8] < 0
    # z^2 law: (2.8 / 0.8)^2 = 12.25, times the small correction of the exact formula
    assert biases[2.8] / biases[0.8] == pytest.approx(12.25 * (1 + 0.8 * offset / fb) / (1 + 2.8 * offset / fb), rel=0.15)


def test_lens_distortion_warp_moves_pixels_radially_by_the_brown_model():
    preset = small_preset()
    intr = preset.intrinsics
    geometry = plane_geometry(intr, distance=1.5)
    ctx = ctx_for(preset, geometry)
    h, w = geometry.shape
    ramp_u = torch.arange(w, dtype=torch.float32).expand(h, w).contiguous()
    ramp_v = torch.arange(h, dtype=torch.float32)[:, None].expand(h, w).contiguous()
    k1, k2 = -0.05, 0.02
    effect = LensDistortion(k1=k1, k2=k2)
    with torch.no_grad():
        du = effect(ramp_u, ctx) - ramp_u
        dv = effect(ramp_v, ctx) - ramp_v
    x = (ramp_u - intr.cx) / intr.fx
    y = (ramp_v - intr.cy) / intr.fy
    r2 = x * x + y * y
    inner = slice(2, -2)
    assert torch.allclose(du[inner, inner], (x * intr.fx * (k1 * r2 + k2 * r2 * r2))[inner, inner], atol=1e-3)
    assert torch.allclose(dv[inner, inner], (y * intr.fy * (k1 * r2 + k2 * r2 * r2))[inner, inner], atol=1e-3)
    assert float(du[h // 2, w // 2].abs()) < 1e-3


def test_lens_warp_moves_an_off_centre_edge_by_the_brown_model_and_leaves_the_border_bands_in_place():
    """Pixel u of the warped grid shows the ideal image at u + f x (k1 r^2) (row through the principal point, y = 0):
    a depth edge at ideal column e appears at the u solving u + f x^3 k1 = e; the matcher's invalid band at the
    left border stays as wide as it was, and pixels looking into it see the scene beside it."""
    preset = small_preset(320, 240)
    intr = preset.intrinsics
    h, w = 240, 320
    depth = torch.full((h, w), 1.5)
    depth[:, 300:] = 1.0  # a nearer object right of column 300
    valid = torch.ones(h, w, dtype=torch.bool)
    valid[:, :8] = False  # the device grid's band
    depth[:, :8] = 0.0
    ctx = EffectContext(fx=intr.fx, fy=intr.fy, cx=intr.cx, cy=intr.cy, baseline=preset.baseline_m)
    k1 = 0.1  # barrel: pixels look farther out, the image shrinks towards the centre
    disparity = torch.where(valid, intr.fx * preset.baseline_m / depth.clamp_min(1e-6), 0.0)
    warped, _, warped_valid = REGISTRY["lens_warp"](k1=k1)((depth, disparity, valid), ctx)
    row = int(round(intr.cy))
    u = torch.arange(w, dtype=torch.float64)
    x = (u - intr.cx) / intr.fx
    predicted = int(torch.nonzero(u + intr.fx * x**3 * k1 >= 300 - 0.5)[0])
    edge = int(torch.nonzero(warped[row] == 1.0)[0])
    assert abs(edge - predicted) <= 1 and edge <= 297, (edge, predicted)  # 3.4 px nearer the centre
    assert not warped_valid[:, :8].any() and warped_valid[:, 8:].all(), "the band neither moves nor grows"
    assert torch.equal(warped[row, 150:170], depth[row, 150:170]), "the centre is not displaced"


def test_lens_distortion_depth_error_grows_with_image_radius():
    preset = small_preset()
    intr = preset.intrinsics
    geometry = plane_geometry(intr, distance=1.5)
    base = run(preset, geometry)
    warped = run(preset, geometry, [{"name": "lens_distortion", "k1": -0.03}])
    both = base.valid & warped.valid
    err = warped.depth - base.depth
    r = image_radius(intr.height, intr.width, intr.fx, intr.fy, intr.cx, intr.cy)
    u = torch.arange(intr.width).expand(intr.height, -1)
    rings = [(0.0, 0.15), (0.25, 0.4), (0.45, 0.8)]
    spread = [float(err[both & (r >= a) & (r < b)].abs().mean()) for a, b in rings]
    assert spread[0] < 0.004  # centre: unchanged (< half a quantisation step of depth)
    assert spread[2] > 3 * spread[1] / 2 and spread[2] > 5 * spread[0] and spread[2] > 0.02
    outer = both & (r >= 0.45)
    # k1 < 0 pulls content towards the centre: the right half reads larger disparity (nearer), the left farther.
    assert float(err[outer & (u > intr.cx)].median()) < 0 < float(err[outer & (u < intr.cx)].median())
    # More dropout in the corners than in the centre.
    lost = base.valid & ~warped.valid
    assert lost[r >= 0.45].float().mean() >= lost[r < 0.25].float().mean()


def test_grazing_dropout_removes_tilted_planes_and_spares_facing_ones():
    preset = small_preset()
    effect = [{"name": "grazing_dropout", "angle_deg": 50.0}]
    tilted = plane_geometry(preset.intrinsics, normal=tilted_normal(65), distance=1.0)
    facing = plane_geometry(preset.intrinsics, distance=1.5)
    theta = incidence_angle_deg(tilted.points, tilted.normals)
    base, dropped = run(preset, tilted), run(preset, tilted, effect)
    steep = tilted.hit & (theta > 53.0)
    assert base.valid[steep].float().mean() > 0.3
    assert dropped.valid[steep].float().mean() == 0.0
    gentle = tilted.hit & (theta < 49.0)
    assert torch.equal(dropped.valid[gentle], base.valid[gentle])
    assert torch.equal(run(preset, facing, effect).valid, run(preset, facing).valid)  # facing wall: < 40 deg everywhere


def test_edge_dropout_removes_a_band_of_the_given_width_along_depth_edges():
    # Without the device's narrow fill, which runs after the validity effects and refills the band where its 9 x 9
    # window sees mostly valid pixels (the rectangle's corners at 160 x 120): the effect alone is under test.
    preset = small_preset().replace(cleanup_fill_width_px=0)
    geometry = plane_geometry(preset.intrinsics, distance=1.8, rect=RECT)
    dist = edge_distance(geometry.clean_depth)
    assert (dist == 0).sum() > 100  # the rectangle outline
    base, dropped = run(preset, geometry), run(preset, geometry, [{"name": "edge_dropout", "width_px": 3.0}])
    assert not dropped.valid[dist < 2.5].any()
    far = dist > 3.0
    assert torch.equal(dropped.valid[far], base.valid[far])
    assert base.valid[(dist < 2.5) & ~geometry.shadow].float().mean() > 0.3


def test_low_signal_dropout_removes_dark_surfaces_first():
    preset = small_preset()
    dark = dict(RECT, albedo=0.04)
    geometry = plane_geometry(preset.intrinsics, distance=1.2, albedo=0.8, rect=dark)
    # Mean dot signal (counts) of the dark rectangle and of the bright wall; threshold half-way (log scale).
    mean_pattern = float(DepthSensor(preset).pattern_field().raster.mean())
    level_rect = 0.04 * preset.emitted_intensity * mean_pattern / 1000.0**2
    level_wall = 0.8 * preset.emitted_intensity * mean_pattern / 1200.0**2
    threshold = math.sqrt(level_rect * level_wall)
    base = run(preset, geometry)
    dropped = run(preset, geometry, [{"name": "low_signal_dropout", "threshold_counts": threshold}])
    # The matching window near the rectangle's outline still sees bright wall dots: look inside.
    front = (geometry.clean_depth < 1.1) & (edge_distance(geometry.clean_depth) > 5)
    wall = (geometry.clean_depth > 1.1) & ~geometry.shadow
    assert base.valid[front].float().mean() > 0.3  # the base sensor still sees the dark rectangle
    assert dropped.valid[front].float().mean() < 0.1 * base.valid[front].float().mean()
    assert dropped.valid[wall].float().mean() > 0.95 * base.valid[wall].float().mean()


def test_depth_scale_error_is_proportional_to_depth():
    preset = small_preset()
    for z in (0.9, 2.7):
        geometry = plane_geometry(preset.intrinsics, distance=z)
        base = run(preset, geometry)
        scaled = run(preset, geometry, [{"name": "depth_scale", "scale_error": 0.01}])
        both = base.valid & scaled.valid
        ratio = (scaled.depth[both] / base.depth[both]).median()
        assert float(ratio) == pytest.approx(1.01, abs=1e-5)


# --------------------------------------------------------------------------------------------
# Gradients


def _fd_check(effect: torch.nn.Module, key: str, loss_fn, eps: float = 1e-4, rel: float = 1e-3):
    """Compare the autograd derivative of loss_fn() w.r.t. the raw parameter with central differences."""
    analytic, numeric = autograd_and_difference(loss_fn, effect.raw[key], eps)
    assert math.isfinite(analytic)
    assert abs(numeric) > 1e-8, "the loss must depend on the parameter"
    assert analytic == pytest.approx(numeric, rel=rel, abs=1e-9)


@pytest.mark.parametrize(
    "name, key, values",
    [
        ("lens_distortion", "k1", {"k1": -0.02, "k2": 0.01}),
        ("lens_distortion", "k2", {"k1": -0.02, "k2": 0.01}),
        ("disparity_offset", "offset_px", {"offset_px": 0.3}),
        ("depth_scale", "scale_error", {"scale_error": 0.01}),
        ("grazing_dropout", "angle_deg", {"angle_deg": 55.0}),
        ("edge_dropout", "width_px", {"width_px": 2.6}),
        ("low_signal_dropout", "threshold_counts", {"threshold_counts": 8.0}),
    ],
)
def test_effect_gradient_matches_finite_differences(name, key, values):
    torch.manual_seed(0)
    preset = small_preset()
    geometry = plane_geometry(preset.intrinsics, normal=tilted_normal(55), distance=1.3, rect=RECT)
    ctx = ctx_for(preset, geometry, signal=geometry.albedo * 20.0 * (1 + torch.rand(geometry.shape)))
    ctx = in_double(ctx)
    effect = REGISTRY[name](**values).double()
    h, w = geometry.shape
    if name == "lens_distortion":  # a smooth image, so that bilinear sampling is differentiable enough for FD
        u = torch.arange(w, dtype=torch.float64)
        v = torch.arange(h, dtype=torch.float64)[:, None]
        x = torch.sin(u / 7.0) * torch.cos(v / 5.0) * 100 + 200
    else:
        x = geometry.clean_depth.double() if effect.stage != "disparity" else 10.0 / geometry.clean_depth.double()
    weights = torch.rand(h, w, dtype=torch.float64)
    _fd_check(effect, key, lambda: (effect(x, fresh(ctx)) * weights).sum())


def test_gradients_through_the_full_sensor_are_finite_for_every_effect():
    preset = small_preset()
    entries = [{"name": n, **{k: p.typical for k, p in cls.params.items()}} for n, cls in REGISTRY.items()]
    sensor = DepthSensor(preset.replace(effects=entries))
    geometry = plane_geometry(preset.intrinsics, normal=tilted_normal(45), distance=1.4, rect=RECT)
    out = sensor(geometry, seed=1)
    loss = (out.depth * out.valid).sum() + out.valid_soft.sum()
    loss.backward()
    for effect in sensor.effects:
        for key, raw in effect.raw.items():
            if effect.differentiable:
                assert raw.grad is not None and torch.isfinite(raw.grad), (effect.name, key)
            else:  # a resampling: no gradient, and none leaks into the others
                assert raw.grad is None or float(raw.grad) == 0.0, (effect.name, key)
    assert any(float(effect.raw[k].grad) != 0 for effect in sensor.effects for k in effect.raw)


def test_disparity_offset_gradient_through_the_sensor_matches_finite_differences():
    preset = small_preset()
    geometry = plane_geometry(preset.intrinsics, distance=1.5)
    sensor = DepthSensor(preset.replace(effects=[{"name": "disparity_offset", "offset_px": 0.2}]))
    noise = sensor.draw_noise(4)
    mask = run(preset, geometry).valid

    def loss():
        return sensor(geometry, noise=noise).raw_depth[mask].sum()

    _fd_check(sensor.effects[0], "offset_px", loss, eps=1e-3, rel=2e-2)


def test_build_effects_follows_the_entries():
    effects = build_effects(validate_effects([{"name": "depth_scale", "scale_error": 0.02}, {"name": "edge_dropout"}]))
    assert [e.name for e in effects] == ["depth_scale", "edge_dropout"]
    assert effects[0].values()["scale_error"] == pytest.approx(0.02, abs=1e-6)
    assert local_signal(torch.ones(5, 7), 3).shape == (5, 7)


def test_every_effect_class_takes_its_declaration_from_the_one_table():
    """The library's classes and the table presets are checked against (ddsgen.effect_params) cannot drift apart."""
    from ddsgen.effect_params import EFFECTS

    assert set(REGISTRY) == set(EFFECTS)
    for name, cls in REGISTRY.items():
        spec = EFFECTS[name]
        assert (cls.stage, cls.params, cls.options, cls.groups, cls.generic) == (
            spec.stage, spec.params, spec.options, spec.groups, spec.generic), name


def test_a_preset_and_its_effects_are_checked_without_the_sensor(tmp_path):
    """Loading a preset checks its effects from the declarations alone: the preset layer does not import the sensor
    (torch is blocked in the child process; the one-line error names the entry)."""
    import subprocess
    import sys

    bad = tmp_path / "bad.yaml"
    bad.write_text(tiny_preset_yaml(96, 72) + "effects: [{name: edge_dropout, width_px: 99}]\n")
    code = ("import sys; sys.modules['torch'] = None\n"
            "from ddsgen.errors import InputError\nfrom ddsgen.preset import load_preset\n"
            "assert load_preset('kinect_v1').name == 'kinect_v1'\n"
            f"try:\n    load_preset({str(bad)!r})\nexcept InputError as error:\n    print(error)\n")  # fmt: skip
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
    assert "effects[0].width_px: must be in [0, 20] px, got 99" in result.stdout


def test_a_render_with_a_lens_warp_writes_masks_and_clean_depth_on_its_warped_depth(tmp_path):
    """The masks of a warped render follow its depth: on an object's mask pixels the depth is the clean depth
    (within the sensor's noise) as often as in a render without the warp, and the masks differ from the ideal
    camera's towards the corners."""
    import json
    from pathlib import Path

    import cv2
    import numpy as np

    from ddsgen.io.exr import read_exr
    from ddsgen.preset import save_preset
    from ddsgen.runner import render_dataset

    scenes = Path(__file__).with_name("diagnose_scenes.yaml")
    shares, masks = {}, {}
    for name, effects in (("ideal", []), ("warped", [{"name": "lens_warp", "k1": 0.15, "k2": 0.0}])):
        save_preset(small_preset(320, 240).replace(effects=effects), tmp_path / f"{name}.yaml")
        out = tmp_path / name
        render_dataset(str(tmp_path / f"{name}.yaml"), str(scenes), 2, str(out), workers=1, seed=3, progress=False)
        off = []
        for line in (out / "manifest.jsonl").read_text().splitlines():
            record = json.loads(line)
            depth = cv2.imread(str(out / record["depth"]), cv2.IMREAD_UNCHANGED) / 1000.0
            clean = read_exr(out / record["clean"])
            mask = cv2.imread(str(out / record["mask"]), cv2.IMREAD_UNCHANGED)
            on = (mask > 0) & (depth > 0)
            off.append(np.abs(depth[on] - clean[on]) > 0.03)
            masks.setdefault(name, []).append(mask)
            assert all(o["bbox"][2] > 0 for o in record["objects"] if o["visible_fraction"] > 0)
        shares[name] = float(np.concatenate(off).mean())
    # measured: 0.0679 ideal, 0.0687 warped; 0.0796 when the masks were the ideal camera's
    assert shares["warped"] <= shares["ideal"] + 0.005, shares
    assert any((a != b).any() for a, b in zip(masks["ideal"], masks["warped"])), "the warp moved the masks"
