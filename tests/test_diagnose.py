"""ddsgen diagnose: names the effect hidden in rendered scans, stays silent on clean ones, and says which axis
an unknown distortion follows.

Scans are rendered by ddsgen itself with the Kinect V1 sensor at its full 640 x 480 (1/8 px sub-pixel steps like
the device), 8 frames of ``diagnose_scenes.yaml`` (large objects on a floor, camera 0.8-2.4 m), one library effect
switched on at a realistic strength and the base parameters perturbed a little (eta_c x 1.15, soft-argmax beta x
1.1), then diagnosed from the stock preset (5 fit frames, 3 held out). Each case asserts what the issue asks:
that effect is named first and the held-out gap falls by at least half.

The cases are marked slow (about 3-7 minutes each on one core); the rendered scans are shared by the module. A case
with one hidden effect stops after the first accepted effect (:data:`ONE_EFFECT`): the test judges that one.

The blind cases (end of the module) diagnose scans that ddsgen's sensor did not make: an independent numpy
measurement model (``independent_sensor.py``) turns the ray-cast clean depth into depth with its own noise,
quantisation and the hidden effect written from its textbook formula.
"""

from __future__ import annotations

import dataclasses
import json
import math
import re

import numpy as np
import pytest
import torch

from torch_threads import torch_threads
from ddsgen.diagnose import (
    BOOTSTRAP_QUANTILE,
    DiagnoseConfig,
    Evaluation,
    bootstrap_fall,
    diagnose,
    relative_fall,
    replane,
)
from ddsgen.preset import save_preset
from effects_geometry import small_preset

SCENES = __import__("pathlib").Path(__file__).with_name("diagnose_scenes.yaml")
FRAMES = 8
#: Settings of the test runs: few Adam steps (the 1-D searches of the base fit still run), two frames for the
#: candidates' searches.
CONFIG = DiagnoseConfig(base_steps=2, refit_steps=0, grid_frames=2, refine_rounds=2)
#: Cases with one hidden library effect assert only the first named effect and the gap it leaves: the loop stops
#: after one accepted effect (a second round costs as much as the first and is judged by the null and axis cases).
ONE_EFFECT = dataclasses.replace(CONFIG, max_steps=1)
#: Target of the library cases: the held-out gap beyond the noise floor at most halves.
HALF = 0.5

#: The hidden effect of each case, at a realistic strength for the Kinect V1.
CASES = {
    "disparity_offset": {"name": "disparity_offset", "offset_px": 0.3},
    "depth_scale": {"name": "depth_scale", "scale_error": 0.015},
    "lens_distortion": {"name": "lens_distortion", "k1": -0.01},
    "grazing_dropout": {"name": "grazing_dropout", "angle_deg": 65.0},
    "edge_dropout": {"name": "edge_dropout", "width_px": 4.0},
    "low_signal_dropout": {"name": "low_signal_dropout", "threshold_counts": 10.0},
}
#: Filled by the tests, printed at the end of the test session.
TABLE: list[str] = []


@pytest.fixture(scope="module", autouse=True)
def one_thread():
    """Many small simulations: one torch thread is much faster on a shared machine."""
    with torch_threads(1):
        yield
    if TABLE:
        print("\n" + "\n".join(["case                 named                     held-out gap before -> after"] + TABLE))


@pytest.fixture(scope="module")
def scans(tmp_path_factory):
    """Scan folders rendered on demand, once per module: ``scans(name, effects, perturb, seed)``."""
    root = tmp_path_factory.mktemp("diagnose_scans")
    done: dict[str, object] = {}

    def get(name: str, effects: list[dict], perturb: bool = True, seed: int = 11):
        if name not in done:
            done[name] = render_scans(root, name, effects, perturb, seed)
        return done[name]

    return get


def stock():
    """The Kinect V1 preset with the device's 1/8 px sub-pixel steps, measuring to the driver's 10 m. Two rules make
    the far floor harmless: its depth beyond 4.14 m, where one 1/8-px step is more than the depth term's 50 mm clip,
    is not compared (:func:`ddsgen.realscan.losses.resolved_depth_m`), and candidates are judged against the floor over
    the reported units (:func:`ddsgen.diagnose.acceptance.judged_floors`). With neither, the disparity_offset case
    tied with depth_scale (credited falls 43.0 % each, depth_scale named first)."""
    return small_preset(640, 480, subpixel_level=3)


def render_scans(root, name: str, effects: list[dict], perturb: bool = True, seed: int = 11, n: int = FRAMES):
    """Render ``n`` frames with ``effects`` (and perturbed base parameters) into a scan folder."""
    from ddsgen.runner import render_dataset

    base = stock()
    truth = base.replace(effects=effects)
    if perturb:
        truth = truth.replace(emitted_intensity=base.emitted_intensity * 1.15, softargmax_beta=base.softargmax_beta * 1.1)
    preset_path = root / f"{name}.yaml"
    save_preset(truth, preset_path)
    out = root / name
    render_dataset(str(preset_path), str(SCENES), n, str(out), workers=1, seed=seed, progress=False)
    return out


def prepared(folder):
    from ddsgen.realscan.simulate import prepare_frames
    from ddsgen.io.scanfolder import read_scan_folder

    return prepare_frames(stock(), read_scan_folder(folder))


def run(folder, log=None, config: DiagnoseConfig = CONFIG):
    return diagnose(stock(), prepared(folder), config, echo=(log.append if log is not None else (lambda line: None)))


def fall_or_known_shortfall(result, text: str, floor: float | None, why: str) -> None:
    """Assert the target (the gap at least halves); a case with a measured shortfall must still reach ``floor``
    (its measured fall, rounded down) and is then reported as an expected failure naming ``why``. Improving past
    the target turns it into a pass, never into a strict-xfail error."""
    fall = 1.0 - result.final_gap / result.baseline_gap
    if floor is None:
        assert fall >= HALF, text
        return
    assert fall >= floor, f"fall {100 * fall:.0f} % is below even the measured {100 * floor:.0f} %\n{text}"
    if fall < HALF:
        pytest.xfail(f"gap falls {100 * fall:.0f} % (target {100 * HALF:.0f} %): {why}")


def record(case: str, result) -> None:
    named = ", ".join(s.effect for s in result.steps) or "(none)"
    fall = 100.0 * (1.0 - result.final_gap / result.baseline_gap)
    extra = "; unexplained: " + ", ".join(f"{u['axis']} {u['strength']:.1f} mm" for u in result.unexplained)
    TABLE.append(f"{case:20s} {named:25s} {result.baseline_gap:6.2f} -> {result.final_gap:6.2f} mm ({fall:+.0f} %)"
                 + (extra if result.unexplained else ""))  # fmt: skip


# --------------------------------------------------------------------------------------------------------------
# The acceptance rule and the support plane (fast)


def test_credited_fall_counts_only_what_the_noise_floor_does_not_explain():
    before = Evaluation([10.0, 12.0, 11.0], [8.0, 8.0, 8.0])
    hiding = Evaluation([8.0, 10.0, 9.0], [6.0, 6.0, 6.0])  # gap and floor fall together: noise hidden
    fixing = Evaluation([8.0, 9.0, 8.5], [8.0, 8.0, 8.0])  # gap falls to the floor
    noisier = Evaluation([10.0, 12.0, 11.0], [9.0, 9.5, 9.0])  # own draws disagree more: no credit
    assert relative_fall(before, hiding) == pytest.approx(0.0)
    assert relative_fall(before, fixing) == pytest.approx((2 + 3 + 2.5) / 33.0)
    assert relative_fall(before, noisier) == pytest.approx(0.0)
    rng = np.random.default_rng(0)
    assert bootstrap_fall(before, fixing, rng) > 0.0
    one_frame = Evaluation([8.0, 12.5, 11.5], [8.0, 8.0, 8.0])  # one frame better, two worse
    assert relative_fall(before, one_frame) > 0.0
    assert bootstrap_fall(before, one_frame, rng) < 0.0
    assert 0.0 < BOOTSTRAP_QUANTILE < 0.5


@dataclasses.dataclass
class _Frame:
    """The fields of a FrameData that :func:`replane` reads."""

    geometry: object
    instance: torch.Tensor
    region: torch.Tensor
    real_depth: torch.Tensor
    real_valid: torch.Tensor
    intrinsics: object
    incidence_deg: torch.Tensor
    plane: object
    name: str = "scan/000000"
    object_region: torch.Tensor | None = None
    clean_depth: torch.Tensor | None = None
    hit: torch.Tensor | None = None
    index: int = 0
    resolved_depth_m: float = math.inf

    def noise_seed(self, seed: int = 0) -> list[int]:  # as FrameData's
        from ddsgen.realscan.simulate import SIM_STREAM

        return [int(seed), int(self.index), SIM_STREAM]

    def __post_init__(self):  # the image is the geometry's (not registered), as in FrameData
        self.clean_depth = self.geometry.clean_depth if self.clean_depth is None else self.clean_depth
        self.hit = self.geometry.hit if self.hit is None else self.hit

    @property
    def shape(self):
        return tuple(self.real_depth.shape)


def test_replane_recovers_the_plane_a_disparity_offset_was_added_to():
    """A plane seen with a disparity offset is still a plane (1/z shifts by offset / (f b)); prepare_frames fits
    that biased plane to the real depth, and a model with the offset would bias it twice. One re-planing step
    under that model recovers the true plane."""
    from ddsgen.realscan.support_plane import Plane
    from ddsgen.sensor.depth_sensor import SensorOutput
    from effects_geometry import plane_geometry, tilted_normal

    preset = stock()
    intr = preset.intrinsics
    fb, offset = intr.fx * preset.baseline_m, 0.4
    n, d = np.array(tilted_normal(40)), 1.5  # true plane n.X + d = 0
    truth = plane_geometry(intr, normal=n, distance=d).clean_depth
    abc = -n / d + np.array([0.0, 0.0, offset / fb])  # 1/z = abc . (x_n, y_n, 1) of the biased plane
    n_b, d_b = -abc / np.linalg.norm(abc), 1.0 / np.linalg.norm(abc)
    biased = plane_geometry(intr, normal=n_b, distance=d_b)
    real = fb / (fb / truth + offset)
    assert torch.allclose(biased.clean_depth, real, rtol=1e-4)
    everywhere = torch.ones_like(truth, dtype=torch.bool)
    frame = _Frame(biased, torch.zeros_like(truth, dtype=torch.int32), everywhere, real, everywhere, intr,
                   torch.zeros_like(truth), Plane(normal=n_b, offset=d_b, inliers=0, candidates=0))  # fmt: skip
    twice = fb / (fb / biased.clean_depth + offset)  # the offset model simulated on the biased plane
    sim = SensorOutput(depth=twice, valid=everywhere, valid_soft=everywhere.float(), ir=truth, disparity=truth,
                       confidence=truth, raw_depth=twice)  # fmt: skip
    new = replane(frame, sim)
    assert torch.allclose(new.geometry.clean_depth, truth, rtol=1e-4)
    assert np.allclose(new.plane.normal, n, atol=1e-4) and new.plane.offset == pytest.approx(d, rel=1e-4)
    assert torch.allclose(new.geometry.normals[60, 80], torch.tensor(n, dtype=torch.float32), atol=1e-4)
    # The same real surface: the re-estimated geometry shows the scene's speckle (drawn once, for the scene), not a
    # new field per estimate of the plane's pose; so does a re-estimate of the re-estimate.
    from ddsgen.sensor.speckle import scene_speckle

    assert new.geometry.speckle_scene is biased and replane(new, sim).geometry.speckle_scene is biased
    field = scene_speckle(biased, [], 12, 16, 4.5, 1.0)
    assert scene_speckle(new.geometry, [], 12, 16, 4.5, 1.0) is field
    moved = dataclasses.replace(biased, points=new.geometry.points.clone())  # another scene: its own field
    assert not np.array_equal(scene_speckle(moved, [], 12, 16, 4.5, 1.0), field)


def test_one_frame_is_split_into_disjoint_pieces_that_each_cover_the_whole_image():
    from ddsgen.diagnose.split import block_labels, split_single_frame

    labels = block_labels(480, 640, 8, seed=3)
    counts = np.bincount(labels.ravel(), minlength=8)
    assert counts.min() >= 0.8 * counts.max(), counts  # blocks dealt evenly
    for k in range(8):  # every piece reaches every quadrant of the image (centre and corners alike)
        rows, cols = np.nonzero(labels == k)
        assert rows.min() < 120 and rows.max() > 360 and cols.min() < 160 and cols.max() > 480
    frame = _plane_frame()
    frame.region[:, :10] = False  # a part outside the comparison stays outside every piece
    fit, held = split_single_frame(frame, 1.0 / 3.0, seed=3)
    assert len(fit) == 1 and len(held) == 3
    masks = [f.region for f in fit + held]
    assert int(sum(m.int() for m in masks).max()) == 1, "pieces are disjoint"
    assert torch.equal(torch.stack(masks).any(0), frame.region), "together they are the frame's region"
    assert all(f.real_depth is frame.real_depth for f in held), "same scan, same geometry: only the region differs"
    assert len({f.name for f in fit + held}) == 4


def test_the_real_frames_output_window_is_measured_and_used_before_the_base_fit():
    """Border columns with depth in the real frames, where the preset declares a band without (the stock Kinect's
    8 left columns): the diagnosis uses the measured window (the band is not an effect and no effect adds pixels)
    and says so; a preset that agrees, one frame, or a crop (its border is not the device's) leave it alone."""
    from types import SimpleNamespace

    from ddsgen.diagnose.window import with_measured_window
    from ddsgen.sensor.output_window import OutputWindow

    registered = small_preset(160, 120)
    preset = registered.replace(registration_ir_offset_m=0.0, registration_shift_px=0.0)
    assert OutputWindow.of(preset).left == 8
    intr = preset.intrinsics
    rng = np.random.default_rng(0)

    def frame(valid, crop=(0, 0, 160, 120)):  # depth 1.2 m where valid
        return SimpleNamespace(real_depth=torch.from_numpy(np.where(valid, 1.2, 0.0).astype(np.float32)), crop=crop,
                               full_intrinsics=intr)  # fmt: skip

    device = [rng.random((120, 160)) < 0.9 for _ in range(3)]  # depth up to every border
    for valid in device:
        valid[:, -12:] = False  # and a registered device's right band
    adopted, window, note = with_measured_window(preset, [frame(v) for v in device])
    assert window == OutputWindow(left=0, right=12) and OutputWindow.of(adopted) == window
    assert "left 0, right 12" in note and "left 8" in note
    stock = [v.copy() for v in device]
    for valid in stock:
        valid[:, :8] = False
        valid[:, -12:] = True
    assert with_measured_window(preset, [frame(v) for v in stock])[1] is None  # agrees with the preset
    assert with_measured_window(preset, [frame(device[0])])[1] is None  # one frame: its border may be the scene's
    crops = [frame(v, crop=(20, 10, 160, 120)) for v in device]
    assert with_measured_window(preset, crops)[1] is None
    # --apply writes it in the preset's own pixels
    assert window.rescaled(160, 120, 640, 480) == OutputWindow(left=0, right=48)
    # A preset registered to an RGB camera declares its IR frame's bands, which the registration moves by
    # f b_r / Z - s: the output's band at 1.2 m is that much narrower on the right, and the IR frame shows depth
    # from column 0 (+1: the dense splat fills the band's last column).
    adopted, window, _ = with_measured_window(registered, [frame(v) for v in device])
    moved = registered.focal_px * registered.registration_ir_offset_m / 1.2 - registered.registration_shift_px
    assert window == OutputWindow(left=1, right=12 - round(moved)) and OutputWindow.of(adopted) == window


def _plane_frame(width: int = 160, height: int = 120):
    """A tilted support plane seen by the small Kinect preset, real depth = clean depth (a _Frame)."""
    from ddsgen.realscan.support_plane import Plane
    from effects_geometry import plane_geometry, tilted_normal

    intr = small_preset(width, height).intrinsics
    geometry = plane_geometry(intr, normal=tilted_normal(20), distance=1.4)
    z = geometry.clean_depth.clone()
    everywhere = torch.ones_like(z, dtype=torch.bool)
    return _Frame(geometry, torch.zeros_like(z, dtype=torch.int32), everywhere.clone(), z, everywhere.clone(), intr,
                  torch.full_like(z, 20.0), Plane(normal=np.array(tilted_normal(20)), offset=1.4, inliers=0,
                                                    candidates=0), object_region=~everywhere)  # fmt: skip


def test_axis_term_shapes_are_read_off_the_residual():
    """The real scan carries a disparity bias that is a known Legendre series along the image column, and drops
    pixels with a keep-probability that falls towards the right of the image: the generic terms' starting shapes
    recover both (the depth-free support plane part is absorbed by its nuisance terms)."""
    from types import SimpleNamespace

    from ddsgen.diagnose.axis_candidates import disparity_guess, validity_guess
    from ddsgen.sensor.depth_sensor import DepthSensor
    from ddsgen.sensor.effects.axis_terms import axis_coordinate, keep_probability, legendre_basis

    sensor = DepthSensor(small_preset())
    frame = _plane_frame()
    intr = frame.intrinsics
    fb = intr.fx * float(sensor.baseline.detach())
    xn = ((torch.arange(intr.width, dtype=torch.float64) - intr.cx) / intr.fx)[None, :].expand(intr.height, -1)
    basis = legendre_basis(axis_coordinate("column", xn))
    truth = np.array([0.0, 0.0, 0.3, 0.0, -0.2])  # even, no affine part: the plane's nuisance cannot absorb it
    bias = torch.tensordot(torch.as_tensor(truth), basis, dims=1)
    sim_depth = frame.geometry.clean_depth
    frame.real_depth = (fb / (fb / sim_depth.double() + bias)).float()
    frame.instance[:, : intr.width // 2] = 1  # half of it an object: no nuisance term there
    sim = SimpleNamespace(depth=sim_depth, valid=torch.ones_like(frame.region), ir=torch.ones_like(sim_depth))
    coef = np.array(disparity_guess("column", sensor, [frame], [sim]))
    assert np.allclose(coef[2:], truth[2:], atol=0.01), coef
    frame.real_depth = sim_depth
    keep_truth = keep_probability(torch.tensordot(torch.tensor([-1.0, -2.0, 0.0, 0.0, 0.0], dtype=torch.float64),
                                                  basis, dims=1))  # fmt: skip
    frame.real_valid = torch.rand(keep_truth.shape, generator=torch.Generator().manual_seed(0)) < keep_truth
    s = torch.tensordot(torch.tensor(validity_guess("column", [frame], [sim]), dtype=torch.float64), basis, dims=1)
    assert torch.allclose(keep_probability(s), keep_truth, atol=0.08)


def test_validity_likelihood_prefers_holes_where_the_real_ones_are():
    """Two models with the same valid rate: the one that puts its holes where the real scan has them makes the
    real valid map more likely; the rate difference of compare cannot tell them apart."""
    from types import SimpleNamespace

    from ddsgen.diagnose.evaluation import validity_log_likelihood

    frame = _plane_frame()
    frame.real_valid[:, :40] = False  # the real scan lost the left quarter
    right_place = torch.ones_like(frame.region, dtype=torch.float32)
    right_place[:, :40] = 0.0
    wrong_place = torch.ones_like(right_place)
    wrong_place[:, -40:] = 0.0
    ll = {name: validity_log_likelihood(SimpleNamespace(valid_soft=soft), frame)
          for name, soft in (("right", right_place), ("wrong", wrong_place), ("none", torch.ones_like(right_place)))}
    assert ll["right"] > ll["none"] > ll["wrong"], ll
    assert ll["right"] > -0.05  # only the window at the boundary is uncertain


# --------------------------------------------------------------------------------------------------------------
# The cases (rendered scans, full diagnosis)




#: Rendered cases whose blind counterpart (below) passes are not rendered again (CI time).
BLIND_COVERS = ("lens_distortion",)


#: Measured shortfalls (fall of the gap beyond the floor, rounded down; why). edge_dropout
#: (640 x 480): named first with width 4.0 px (true 4), gap beyond the floor 1.24 -> 0.67 mm (-46 %);
#: since the matcher keeps windows across depth edges (confirmed_match_zncc) it passes, so it keeps
#: only a floor here against a return of the ring.
RENDERED_SHORT = {"edge_dropout": (0.40, "named first with the true width; the sensor's own holes at depth "
                                         "edges stay in the gap")}


@pytest.mark.slow
@pytest.mark.parametrize("name", [n for n in CASES if n not in BLIND_COVERS])
def test_diagnose_names_the_hidden_effect_first_and_halves_the_gap(scans, name):
    entry = CASES[name]
    log: list[str] = []
    result = run(scans(name, [entry]), log, ONE_EFFECT)
    record(name, result)
    text = "\n".join(log)
    assert result.steps, text
    assert result.steps[0].effect == name, text
    # the fitted strength is of the right sign and size (checked before the gap: a shortfall ends the test there)
    check_strength(name, entry, result.steps[0].params, text)
    fall_or_known_shortfall(result, text, *RENDERED_SHORT.get(name, (None, "")))


#: low_signal_dropout's threshold is not checked: it trades off with the base fit's emitted intensity (the dropout
#: compares the dot signal with the threshold, and a fainter model also matches fewer dots). Measured
#: (on the test's scans): named first, gap beyond the floor 10.22 -> 0.50 mm (-95 %),
#: threshold 4 counts (true 10) with eta_c fitted to 3.75e5 (true 1.725e6), i.e. 18 counts at the true intensity.
#: Before the floor was measured against another unit the same run fell ~22 % and the case was left out of CI.
STRENGTH_TRADES_OFF = ("low_signal_dropout",)


def check_strength(name: str, entry: dict, fitted: dict, text: str) -> None:
    if name in STRENGTH_TRADES_OFF:
        return
    if name == "lens_distortion":  # k1 and k2 trade off inside the image: compare the radial displacement
        r2 = np.linspace(0.0, 0.47, 48)  # r^2 up to the corners of the Kinect image
        true_radial = entry["k1"] * r2
        fit_radial = fitted["k1"] * r2 + fitted["k2"] * r2 * r2
        assert np.abs(fit_radial - true_radial).max() <= 0.3 * np.abs(true_radial).max(), (fitted, text)
        return
    for key, value in entry.items():
        if key != "name":
            assert fitted[key] == pytest.approx(value, rel=0.3), (key, fitted[key], text)


def add_column_ripple(folder, amplitude: float = 0.01, periods: float = 3.0) -> None:
    """Out-of-library distortion: depth x (1 + a cos(2 pi periods (u - cx) / W)), written into the scans' files.

    A periodic error along image columns (like a banding of the depth sensor's reference), even about the image
    centre and with zero mean across the image: no library effect produces it.
    """
    from ddsgen.io.exr import read_exr, write_exr
    from ddsgen.io.png import read_depth_png, write_depth_png

    for line in (folder / "manifest.jsonl").read_text().splitlines():
        record_ = json.loads(line)
        intr = record_["intrinsics"]
        u = np.arange(intr["width"], dtype=np.float64)
        factor = 1.0 + amplitude * np.cos(2.0 * math.pi * periods * (u - intr["cx"]) / intr["width"])
        png = folder / record_["depth"]
        depth = read_depth_png(png, record_["depth_scale"]) * factor[None, :]
        write_depth_png(png, depth.astype(np.float32), record_["depth_scale"])
        if record_.get("depth_exr"):
            exr = folder / record_["depth_exr"]
            write_exr(exr, (read_exr(exr) * factor[None, :]).astype(np.float32))


@pytest.mark.slow
def test_out_of_library_distortion_is_reported_by_axis_not_named(scans):
    folder = scans("ripple", [], perturb=True, seed=31)  # its own folder: the ripple is written into its files
    add_column_ripple(folder)
    log: list[str] = []
    result = run(folder, log, dataclasses.replace(CONFIG, max_steps=2))  # a small library claim, then the axis term
    record("column ripple (none)", result)
    for step in result.steps:  # no library effect may claim a large gain
        if ":" not in step.effect:
            assert step.gap_after > 0.8 * step.gap_before, "\n".join(log)
    # the column is named as the axis: by an unnamed effect along it, or as the strongest unexplained structure
    generic_axes = [s.effect.partition(":")[2] for s in result.steps if ":" in s.effect]
    assert "column" in generic_axes or (result.unexplained and result.unexplained[0]["axis"] == "column"), \
        "\n".join(log)


@pytest.mark.slow
def test_screening_keeps_the_answer_and_skips_searches(tmp_path):
    """The screening rule (loop.SCREEN_FRACTION): the same effect is named with the same value and gap as without
    screening, the candidates that explain nothing are judged at their one-frame values, and fewer simulations run
    (validity stages actually computed, i.e. not served by the caches; front ends at most 5 % more)."""
    from ddsgen.diagnose.loop import SCREEN_FRACTION
    from ddsgen.diagnose.stage_cache import StageCache
    from ddsgen.realscan.simulate import prepare_frames
    from ddsgen.io.scanfolder import read_scan_folder
    from ddsgen.runner import render_dataset

    base = small_preset(320, 240, subpixel_level=3)
    truth = base.replace(effects=[CASES["disparity_offset"]], emitted_intensity=base.emitted_intensity * 1.15)
    save_preset(truth, tmp_path / "truth.yaml")
    render_dataset(str(tmp_path / "truth.yaml"), str(SCENES), 6, str(tmp_path / "scans"), workers=1, seed=11,
                   progress=False)  # fmt: skip
    frames = prepare_frames(base, read_scan_folder(tmp_path / "scans"), progress=False)
    # Not depth_scale: at 320 x 240 with 2 held-out frames it beats the offset with or without screening (measured:
    # 5.68 -> 2.58 mm both ways); the 640 x 480 cases separate the two.
    # The command's grid_frames (4): each depth candidate's full search runs on 4 fit frames, its screening on 1.
    config = dataclasses.replace(ONE_EFFECT, grid_frames=DiagnoseConfig().grid_frames, candidates=(
        "disparity_offset", "edge_dropout", "grazing_dropout", "lens_distortion", "low_signal_dropout"))  # fmt: skip
    runs = {}
    for screen in (0, 1):
        log: list[str] = []
        # Every simulation runs a validity stage (its front end computed or served from the cache); the cache
        # counts only the stages its sensors computed.
        cache = StageCache()
        result = diagnose(base, frames, dataclasses.replace(config, screen_frames=screen), echo=log.append,
                          stage_cache=cache)  # fmt: skip
        calls = cache.computed
        runs[screen] = (result, calls["validity_stage"], calls["front_end"], "\n".join(log))
    (plain, plain_sims, plain_fronts, plain_log), (screened, sims, fronts, log) = runs[0], runs[1]
    text = f"without screening:\n{plain_log}\nwith screening:\n{log}"
    assert plain.steps and screened.steps, text
    assert screened.steps[0].effect == plain.steps[0].effect == "disparity_offset", text
    assert screened.steps[0].params == pytest.approx(plain.steps[0].params), text
    assert screened.final_gap == pytest.approx(plain.final_gap), text
    skipped = [c for c in screened.rounds[0] if c.screened]
    assert skipped, text  # work was skipped ...
    assert all(c.gain < SCREEN_FRACTION * config.min_relative_gain for c in skipped), text  # ... only far below
    # A candidate whose one-frame screening clears SCREEN_FRACTION is searched in full too, which may cost a few more
    # front ends than no screening (measured: lens_distortion screened at +2.0 %, 460 against 450 front ends, 634
    # against 1128 validity stages); the saving is in the validity stages and must not cost front ends beyond that.
    assert fronts <= 1.05 * plain_fronts and sims < 0.8 * plain_sims, (fronts, plain_fronts, sims, plain_sims, text)
    print(f"screening: front ends {plain_fronts} -> {fronts}, validity stages {plain_sims} -> {sims}; "
          f"screened {[c.effect for c in skipped]}")


# --------------------------------------------------------------------------------------------------------------
# The command


@pytest.mark.slow
def test_diagnose_command_writes_the_report_and_the_extended_preset(tmp_path, scans):
    from ddsgen.cli import main
    from ddsgen.preset import load_preset

    folder = scans("disparity_offset", [CASES["disparity_offset"]])
    preset_path = tmp_path / "stock.yaml"
    save_preset(stock(), preset_path)
    report, extended = tmp_path / "report", tmp_path / "extended.yaml"
    code = main(["diagnose", str(preset_path), str(folder), "--report", str(report), "--apply", str(extended),
                 "--steps", "2", "--refit-steps", "0", "--grid-frames", "2", "--max-effects", "1", "--quiet",
                 "--candidates", "disparity_offset,depth_scale,edge_dropout"])  # fmt: skip
    assert code == 0
    doc = json.loads((report / "diagnosis.json").read_text())
    assert set(doc) == {"baseline_gap", "steps", "final_gap", "unexplained", "local_patches"}
    assert [set(s) for s in doc["steps"]] == [{"effect", "params", "gap_before", "gap_after"}] * len(doc["steps"])
    assert all(set(u) == {"axis", "strength"} for u in doc["unexplained"])
    assert doc["steps"][0]["effect"] == "disparity_offset"
    assert doc["steps"][0]["gap_before"] == doc["baseline_gap"]
    assert doc["final_gap"] == doc["steps"][-1]["gap_after"]
    html = (report / "report.html").read_text()
    figures = re.findall(r"<img alt='[^']*' src='([^']+\.png)'>", html)
    assert len(figures) >= 3 and all((report / f).is_file() for f in figures), figures  # PNG files beside the page
    assert any("residual_map" in f for f in figures) and "Missing effect: disparity_offset" in html
    fitted = load_preset(extended)
    for key in ("speckle_scale", "read_noise_mean_counts", "focal_px"):  # not fitted: the input's own values
        assert getattr(fitted, key) == getattr(stock(), key), key
    # steps name generic terms NAME:AXIS; the preset entry carries the axis as an option
    assert [(e["name"], e.get("axis")) for e in fitted.effects] == \
        [(s["effect"].partition(":")[0], s["effect"].partition(":")[2] or None) for s in doc["steps"]]


def test_diagnose_command_rejects_bad_input_with_one_line(tmp_path, capsys):
    from ddsgen.cli import main

    scans = tmp_path / "scans"
    scans.mkdir()
    assert main(["diagnose", "kinect_v1", str(scans), "--candidates", "edge_dropuot", "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "edge_dropuot" in err[0]
    assert main(["diagnose", "kinect_v1", str(scans), "--apply", str(tmp_path / "x.txt"), "--quiet"]) == 2
    assert not (tmp_path / "x.txt").exists()
    capsys.readouterr()
    assert main(["diagnose", "kinect_v1", str(scans), "--tile", "-1", "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--tile" in err[0]


# --------------------------------------------------------------------------------------------------------------
# Blind cases: scans from an independent measurement model (tests/independent_sensor.py), not from ddsgen's sensor

#: 320 x 240 (half the Kinect's resolution, same field of view), 9 frames: 6 fit, 3 held out.
BLIND_SIZE, BLIND_FRAMES = (320, 240), 9
#: The hidden effect of each blind case, written in the independent model's own terms (see independent_sensor).
BLIND_CASES = {
    "lens_distortion": {"name": "lens_distortion", "k1": -0.02},  # barrel: ~1.5 px at the corners
    # barrel in another model (division, not Brown's), geometry only: ~10 px at the corners, no disparity bias
    "lens_warp": {"name": "lens_warp", "division_lambda": -0.12},
    "disparity_offset": {"name": "disparity_offset", "offset_px": 0.25},
    "grazing_dropout": {"name": "grazing_dropout", "angle_deg": 65.0},
    # the angle at the projector, not the camera's angle the library's effect uses
    "grazing_dropout_projector": {"name": "grazing_dropout_projector", "angle_deg": 60.0},
    "edge_dropout": {"name": "edge_dropout", "width_px": 3.0},
    "null": None,
    "row_bias": {"name": "row_bias", "amplitude_px": 0.4},  # out of the library: vertical misalignment
}


def blind_stock():
    """The stock sensor of the blind cases. Not registered to an RGB camera: the independent model measures the
    clean depth in the camera's own image, as a device that writes its IR-frame depth. Without the narrow fill
    (``cleanup_fill_width_px``): the independent model leaves every projector-shadow pixel empty, however thin the
    shadow (with the fill, the disparity_offset case named depth_scale first: 6.99 against 7.18 mm)."""
    return small_preset(*BLIND_SIZE, subpixel_level=3, registration_ir_offset_m=0.0, registration_shift_px=0.0,
                        cleanup_fill_width_px=0)


@pytest.fixture(scope="module")
def blind_geometry(tmp_path_factory):
    """Scenes rendered once (only their ray-cast geometry is used): ``(folder, prepared frames)``."""
    from ddsgen.runner import render_dataset

    root = tmp_path_factory.mktemp("blind")
    preset_path = root / "stock.yaml"
    save_preset(blind_stock(), preset_path)
    render_dataset(str(preset_path), str(SCENES), BLIND_FRAMES, str(root / "scenes"), workers=1, seed=41, progress=False)
    return root / "scenes", prepared_blind(root / "scenes")


def prepared_blind(folder):
    from ddsgen.realscan.simulate import prepare_frames
    from ddsgen.io.scanfolder import read_scan_folder

    return prepare_frames(blind_stock(), read_scan_folder(folder), progress=False)


def blind_scans(tmp_path, blind_geometry, effect):
    import shutil

    from independent_sensor import remeasure_folder

    source, frames = blind_geometry
    folder = tmp_path / "scans"
    shutil.copytree(source, folder)
    remeasure_folder(folder, frames, blind_stock().baseline_m, effect, seed=5)
    # Scans of another device: only the annotated objects are known, as for real scans (with run.json the render's
    # whole scene would be simulated, :func:`ddsgen.realscan.simulate.rendered_background`).
    (folder / "run.json").unlink()
    return folder


#: Measured (320 x 240, 9 frames, one effect accepted), the floor measured against another unit of the
#: stock sensor (its own speckle and dots, ``simulate_twin``): lens 12.93 -> 1.94 mm (-85 %), offset 2.44 -> 0.28
#: (-88 %), grazing 3.59 -> 0.04 (-99 %), edge 3.15 -> 0.08 (-98 %), null 0.47 mm with nothing named, row bias
#: 10.39 -> 0.18 (-98 %). With a twin that shared the simulation's speckle and dots the null case
#: kept 5.87 mm "beyond the floor" and offset, grazing and edge fell only 14-44 %: the independent model's own noise,
#: which no model of it can know, was counted as structure to explain.
#: The null case's gap beyond the floor, at most this fraction of its floor: a model right in everything but the
#: unit's own noise scores its floor.
NULL_EXCESS_SHARE = 0.25
#: The library effect a blind case written in other terms should be named as.
EFFECT_NAMED = {"grazing_dropout_projector": "grazing_dropout"}


@pytest.mark.slow
@pytest.mark.parametrize("case", list(BLIND_CASES))
def test_blind_case_from_an_independent_measurement_model(tmp_path, blind_geometry, case):
    """Library effects are named first and remove at least half of the gap; nothing is named in the null case;
    the out-of-library row bias gets a generic disparity term along the row, and no confident library name."""
    effect = BLIND_CASES[case]
    log: list[str] = []
    config = CONFIG if case == "row_bias" else ONE_EFFECT  # the row term may come after a small library claim
    result = diagnose(blind_stock(), prepared_blind(blind_scans(tmp_path, blind_geometry, effect)), config,
                      echo=log.append)  # fmt: skip
    record(f"blind {case}", result)
    text = "\n".join(log)
    if case == "null":
        assert result.steps == [], text
        assert result.final_gap <= NULL_EXCESS_SHARE * result.final.floor, text
        return
    assert result.steps, text
    if case == "row_bias":
        for step in result.steps:
            if ":" not in step.effect:  # a library name may only claim a small part
                assert step.gap_after > 0.8 * step.gap_before, text
        assert "axis_disparity_term:row" in [s.effect for s in result.steps], text
        assert result.final_gap <= 0.7 * result.baseline_gap, text
        return
    assert result.steps[0].effect == EFFECT_NAMED.get(case, case), text
    fall_or_known_shortfall(result, text, None, "")


def test_independent_measurement_model_writes_each_effect_by_its_formula():
    """The blind cases' measurement model (tests/independent_sensor.py) against the formulas it claims: the
    offset moves every disparity by delta, Brown's barrel distortion leaves the centre and moves the corners
    by f x k1 r^2, grazing and edge dropout remove exactly the pixels beyond their limits, quantisation is 1/8 px."""
    from independent_sensor import SUBPIXEL, measure
    from effects_geometry import plane_geometry, tilted_normal

    intr = small_preset(320, 240).intrinsics
    cam = {"fx": intr.fx, "fy": intr.fy, "cx": intr.cx, "cy": intr.cy}
    b = 0.075
    fb = intr.fx * b
    geometry = plane_geometry(intr, normal=tilted_normal(50), distance=1.2,
                              rect={"z": 0.9, "x0": -0.1, "x1": 0.1, "y0": -0.1, "y1": 0.1})  # fmt: skip
    clean = geometry.clean_depth.numpy().astype(np.float64)
    lit = (geometry.hit & ~geometry.shadow).numpy()
    front = np.isclose(clean, 0.9)
    incidence = np.where(front, 0.0, 50.0)

    def disparity(effect, seed=0):
        z = measure(clean, lit, incidence, cam, b, effect, np.random.default_rng(seed))
        return np.where(z > 0, fb / np.maximum(z, 1e-9), 0.0)

    base = disparity(None)
    ok = base > 0
    assert np.allclose(base[ok] * SUBPIXEL, np.round(base[ok] * SUBPIXEL), atol=1e-3), "1/8 px levels"
    shifted = disparity({"name": "disparity_offset", "offset_px": 0.25})
    both = ok & (shifted > 0)
    assert np.mean(shifted[both] - base[both]) == pytest.approx(0.25, abs=0.01)
    barrel = disparity({"name": "lens_distortion", "k1": -0.02})
    v, u = int(round(intr.cy)), int(round(intr.cx))
    assert abs(barrel[v, u] - base[v, u]) <= 0.25, "no displacement at the principal point"
    x, y = (np.arange(320) - intr.cx) / intr.fx, (v - intr.cy) / intr.fy
    right = slice(300, 316)  # near the right border, on the plane: x_d - x_u = x k1 r^2 < 0 for barrel
    expected = intr.fx * x[right] * -0.02 * (x[right] ** 2 + y**2)
    shift = barrel[v, right] - base[v, right]
    assert np.mean(shift) == pytest.approx(np.mean(expected), abs=0.2) and np.mean(expected) < -0.3
    # The warp: pixel x_d measures, unbiased, the disparity the ideal camera sees at x_u = x_d / (1 + lambda r_d^2).
    warped = disparity({"name": "lens_warp", "division_lambda": 0.1})
    assert abs(warped[v, u] - base[v, u]) <= 0.25, "no displacement at the principal point"
    xs, ys = np.meshgrid((np.arange(320) - intr.cx) / intr.fx, (np.arange(240) - intr.cy) / intr.fy)
    factor = 1.0 + 0.1 * (xs**2 + ys**2)
    seen_u = np.round(xs / factor * intr.fx + intr.cx).astype(int)
    seen_v = np.round(ys / factor * intr.fy + intr.cy).astype(int)
    assert (239 - seen_v[-1]).min() >= 2, "the bottom row sees the plane farther in"
    both = (warped > 0) & (base[seen_v, seen_u] > 0)
    assert np.mean(warped[both] - base[seen_v, seen_u][both]) == pytest.approx(0.0, abs=0.02)
    bottom = both[-12:] & (base[-12:] > 0)  # the plane tilts about the rows: its disparity changes down the image
    assert abs(np.mean(warped[-12:][bottom] - base[-12:][bottom])) > 0.1, "the plane's disparity moved with the warp"
    grazing = disparity({"name": "grazing_dropout", "angle_deg": 45.0})
    assert not (grazing[~front] > 0).any() and (grazing[front & ok] > 0).mean() > 0.95
    edges = disparity({"name": "edge_dropout", "width_px": 3.0})
    rows = np.nonzero(front.any(1))[0]
    mid = rows[len(rows) // 2]
    left = np.nonzero(front[mid])[0][0]  # first column of the rectangle on that row
    assert not (edges[mid, left - 3 : left + 3] > 0).any(), "within 3 px of the edge: no depth"
    assert (edges[mid, left + 5 : left + 15] > 0).all(), "beyond it: depth"


def test_reported_floor_averages_several_units_and_the_rule_judges_against_the_same_units():
    """Reported gaps beyond the floor average the floor over several units (as compare does), and the acceptance
    rule compares two models' floors over the same units when both have them (else over the one unit both have)."""
    from ddsgen.diagnose.evaluation import evaluate
    from ddsgen.realscan.losses import frame_gap_mm
    from ddsgen.realscan.simulate import simulate, simulate_twin
    from ddsgen.sensor.depth_sensor import DepthSensor

    frame = _plane_frame()
    sensor = DepthSensor(small_preset(160, 120))
    one = evaluate(sensor, [frame], seed=3)
    three = evaluate(sensor, [frame], seed=3, floor_draws=3)
    assert one.reported_floors is None and one.floor == pytest.approx(one.frame_floors[0])
    assert three.frame_gaps == one.frame_gaps and three.frame_floors == one.frame_floors
    assert relative_fall(one, three) == pytest.approx(0.0)  # different unit counts: unit 1 only, no difference
    # A candidate whose gap falls by 1 mm while its floor falls by 0.5 mm on average over three units but not at
    # all against unit 1: credited 0.5 mm (the average), not 1 mm (unit 1's chance draw).
    before = Evaluation([10.0], [8.0], reported_floors=[9.0], floor_draws=3)
    after = Evaluation([9.0], [8.0], reported_floors=[8.5], floor_draws=3)
    assert relative_fall(before, after) == pytest.approx(0.05)
    assert relative_fall(dataclasses.replace(before, reported_floors=None, floor_draws=1), after) == pytest.approx(0.1)
    with torch.no_grad():
        sim = simulate(sensor, frame, 3)
        units = []
        for draw in range(3):
            twin = simulate_twin(sensor, frame, 3, draw)
            units.append(frame_gap_mm(sim, dataclasses.replace(frame, real_depth=twin.depth, real_valid=twin.valid)))
    assert units[0] == pytest.approx(one.frame_floors[0])
    assert len(set(np.round(units, 6))) == 3  # three different units
    assert three.floor == pytest.approx(np.mean(units)) and three.floor_draws == 3
    assert three.excess == pytest.approx(three.gap - np.mean(units))


def test_an_undone_refit_restores_the_candidate_as_judged_including_the_snr_its_search_moved():
    """The loop refits an accepted candidate in place and undoes the refit when it does not help. The undo must give
    back the sensor that was judged: a low-signal dropout's search also moves the SNR, which rebuilding the effect
    on the previous sensor lost (the held-out gap of the 'undone' model was 19.2 mm where the judged one had 1.9)."""
    from ddsgen.diagnose.candidates import copy_of, with_effect
    from ddsgen.sensor.depth_sensor import DepthSensor

    base = DepthSensor(small_preset(160, 120))
    judged = with_effect(base, "low_signal_dropout", {"threshold_counts": 4.0})
    with torch.no_grad():
        judged.log_emitted_intensity.add_(math.log(0.5))  # what the joint SNR x threshold search does
    snapshot = copy_of(judged)
    with torch.no_grad():
        judged.log_emitted_intensity.add_(math.log(3.0))  # the refit moves the live sensor in place
        judged.effects[-1].set_values(threshold_counts=9.0)
    assert float(snapshot.log_emitted_intensity) == pytest.approx(float(base.log_emitted_intensity.detach()) + math.log(0.5))
    assert snapshot.effects[-1].values()["threshold_counts"] == pytest.approx(4.0)
    assert not any(p.requires_grad for p in snapshot.parameters())


def test_a_validity_candidate_is_judged_on_the_current_models_planes_and_front_ends():
    """A validity candidate leaves every depth as it was, so it is judged on the held-out planes re-estimated under
    the current model and reuses that model's front ends (no IR image rendered, nothing matched); a depth
    candidate moves the plane and is judged on planes re-estimated under itself."""
    from ddsgen.diagnose.candidates import with_effect
    from ddsgen.diagnose.evaluation import evaluate
    from ddsgen.diagnose.loop import HELD_REPLANE_STEPS, held_frames_for
    from ddsgen.diagnose.plane import replaned
    from ddsgen.diagnose.stage_cache import StageCache
    from ddsgen.sensor.depth_sensor import DepthSensor

    held = [_plane_frame()]
    cache = StageCache()
    sensor = DepthSensor(small_preset(160, 120), stage_cache=cache)
    sensor.requires_grad_(False)
    with torch.no_grad():  # fitted values: their exp-log round trip through a preset is not exact
        sensor.log_read_noise_std.add_(-0.2)
        sensor.log_emitted_intensity.add_(0.123456)
    counts = cache.computed
    with cache.serving():
        held_now = replaned(sensor, held, 1, HELD_REPLANE_STEPS)
        current = evaluate(sensor, held_now, 1)
        before = dict(counts)
        dropout = with_effect(sensor, "grazing_dropout", {"angle_deg": 30.0})  # plane tilted 20 deg, rays up to 28
        judged = evaluate(dropout, held_frames_for("grazing_dropout", dropout, held, held_now, 1), 1)
        assert counts["front_end"] == before["front_end"]  # sim and twin: both served from the cache
        assert counts["validity_stage"] == before["validity_stage"] + 2
        assert judged.frame_gaps != current.frame_gaps  # it did remove pixels
        offset = with_effect(sensor, "disparity_offset", {"offset_px": 0.5})
        moved = held_frames_for("disparity_offset", offset, held, held_now, 1)
        assert counts["front_end"] > before["front_end"]
    assert held_frames_for("grazing_dropout", dropout, held, held_now, 1)[0] is held_now[0]
    # The offset's plane is its own: the model adds 0.5 px of disparity, so the plane that matches the real depth
    # under it lies farther, by z 0.5 / (d - 0.5) ~ 0.1 m at z = 1.4 m, d = f b / z ~ 7.8 px (f = 145 px at 160 px).
    shift = moved[0].plane.offset - held_now[0].plane.offset
    print(f"plane moved by {shift:.4f} m")
    assert 0.05 < shift < 0.15


def test_a_diagnosis_patches_no_class_or_module_global_its_stage_cache_travels_with_its_sensors(tmp_path):
    """The diagnosis' caches are an object its sensors hold, not a patch: ``DepthSensor``'s class attributes and
    ``ddsgen.sensor.depth_sensor``'s globals are the same objects before, at every line the diagnosis reports (the
    candidate search among them, while the cache serves) and after, as are the stages module's; and the cache did serve (a validity candidate
    runs the validity stage on front ends it did not compute)."""
    import ddsgen.sensor.depth_sensor as depth_sensor
    import ddsgen.sensor.stages as stages
    from ddsgen.diagnose.stage_cache import StageCache
    from ddsgen.realscan.simulate import prepare_frames
    from ddsgen.io.scanfolder import read_scan_folder
    from ddsgen.runner import render_dataset
    from ddsgen.sensor.depth_sensor import DepthSensor

    base = small_preset(160, 120)
    save_preset(base.replace(effects=[CASES["grazing_dropout"]]), tmp_path / "truth.yaml")
    render_dataset(str(tmp_path / "truth.yaml"), str(SCENES), 3, str(tmp_path / "scans"), workers=1, seed=5,
                   progress=False)  # fmt: skip
    frames = prepare_frames(base, read_scan_folder(tmp_path / "scans"), progress=False)

    def snapshot() -> dict:
        return {"class": dict(vars(DepthSensor)), "module": dict(vars(depth_sensor)), "stages": dict(vars(stages))}

    before = snapshot()
    changed: list[str] = []

    def echo(line: str) -> None:
        now = snapshot()
        for part in before:
            if now[part].keys() != before[part].keys() or any(now[part][k] is not v for k, v in before[part].items()):
                changed.append(f"{part} changed at: {line}")

    cache = StageCache()
    config = DiagnoseConfig(base_steps=0, refit_steps=0, grid_frames=1, refine_rounds=1, max_steps=1,
                            axis_terms=False, screen_frames=0, candidates=("grazing_dropout", "disparity_offset"))
    diagnose(base, frames, config, echo=echo, stage_cache=cache)
    echo("after the diagnosis")
    assert not changed, changed
    assert not cache.serve  # serving ends with the loop
    assert cache.front_ends.entries and cache.matches.entries
    assert cache.computed["validity_stage"] > cache.computed["front_end"] > 0
