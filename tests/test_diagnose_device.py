"""Device behaviours as diagnosis candidates (ddsgen.diagnose.device_candidates): what a PrimeSense-family device
does to its own matches (keeps windows across depth edges, fills small holes and narrow gaps, removes specks) and
how its signal fades towards the corners (beam and lens fall-off), tried when the preset has it switched off, and
named from real data."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch
import yaml

from ddsgen.diagnose import DiagnoseConfig
from ddsgen.diagnose.evaluation import evaluate
from ddsgen.diagnose.device_candidates import BEHAVIOURS, device_candidates, fit_behaviour, with_behaviour
from ddsgen.preset import load_preset

LINEMOD = Path(__file__).resolve().parents[2] / "shared" / "data" / "linemod_bop"


def test_behaviours_are_candidates_only_where_the_preset_switches_them_off():
    paper, device = load_preset("kinect_v1_paper"), load_preset("kinect_v1")
    assert set(device_candidates(paper)) == set(BEHAVIOURS)  # the paper's sensor has none of them
    assert device_candidates(device) == []  # the device model has them all (measured values)
    assert device_candidates(paper.replace(cleanup_hole_px=8)) == [n for n in BEHAVIOURS if n != "hole_fill"]
    from ddsgen.sensor.depth_sensor import DepthSensor

    switched = with_behaviour(DepthSensor(paper), "edge_keeping_matches", {"confirmed_match_zncc": 0.35})
    assert switched.preset.confirmed_match_zncc == 0.35 and switched.preset.subpixel_level == paper.subpixel_level
    assert not any(p.requires_grad for p in switched.parameters())


def test_edge_keeping_is_found_on_scans_of_a_device_that_keeps_its_edges(tmp_path, set_torch_threads):
    """Scans of a device that keeps windows straddling depth edges (confirmed_match_zncc 0.35), judged from a model
    without it: switching the behaviour on at a value near the device's removes most of the gap the ring of holes
    around every object left, and the search tells the device's value from a wrong one."""
    from effects_geometry import small_preset

    from ddsgen.realscan.simulate import prepare_frames
    from ddsgen.io.scanfolder import read_scan_folder
    from ddsgen.preset import save_preset
    from ddsgen.runner import render_dataset

    set_torch_threads(1)
    device = small_preset(640, 480)
    save_preset(device, tmp_path / "device.yaml")
    scenes = Path(__file__).with_name("diagnose_scenes.yaml")
    render_dataset(str(tmp_path / "device.yaml"), str(scenes), 2, str(tmp_path / "scans"), workers=1, seed=4,
                   progress=False)  # fmt: skip
    model = device.replace(confirmed_match_zncc=1.0)  # no edge keeping: a ring of holes at every depth edge
    frames = prepare_frames(model, read_scan_folder(tmp_path / "scans"), progress=False)
    from ddsgen.sensor.depth_sensor import DepthSensor

    sensor = DepthSensor(model)
    config = DiagnoseConfig(seed=0)
    with torch.no_grad():
        base = evaluate(sensor, frames, config.seed)
    found, values, score = fit_behaviour(sensor, "edge_keeping_matches", frames, config, base)
    with torch.no_grad():
        after = evaluate(found, frames, config.seed)
    print(f"gap beyond the floor {base.excess:.2f} -> {after.excess:.2f} mm at {values}")
    assert values["confirmed_match_zncc"] <= 0.4  # the device's 0.35 or its neighbour
    # measured (forward registration): credited fall 46 % of the gap, its part beyond the noise floor
    # 0.27 -> -0.03 mm (all of it)
    assert -score >= 0.4 and after.excess <= 0.2 * base.excess


def test_corner_falloff_is_found_on_scans_of_a_device_whose_corners_are_dark(tmp_path, set_torch_threads):
    """Scans of a device whose beam and lens both fade towards the corners (cos^4 each) at a low signal, so that its
    corners lose depth, judged from a model with neither: each fall-off candidate, searched on two frames, takes
    a strong exponent (one key stands in for both) and on two other frames the gap beyond the floor is gone and the
    holes are where the device's are. Measured: held-out 3.60 -> -2.49 mm (beam, 6), -2.71 (lens, 6)."""
    from effects_geometry import small_preset

    from ddsgen.realscan.simulate import prepare_frames
    from ddsgen.io.scanfolder import read_scan_folder
    from ddsgen.preset import save_preset
    from ddsgen.runner import render_dataset
    from ddsgen.sensor.depth_sensor import DepthSensor

    set_torch_threads(1)
    device = small_preset(320, 240)
    device = device.replace(emitted_intensity=0.2 * device.emitted_intensity)  # a weak signal: corners go first
    assert device.projector_falloff_exponent == 4.0 and device.vignetting_exponent == 4.0
    save_preset(device, tmp_path / "device.yaml")
    scenes = Path(__file__).with_name("diagnose_scenes.yaml")
    render_dataset(str(tmp_path / "device.yaml"), str(scenes), 4, str(tmp_path / "scans"), workers=1, seed=4,
                   progress=False)  # fmt: skip
    model = device.replace(projector_falloff_exponent=0.0, vignetting_exponent=0.0)
    assert {"beam_falloff", "lens_vignetting"} <= set(device_candidates(model))
    frames = prepare_frames(model, read_scan_folder(tmp_path / "scans"), progress=False)
    fit_frames, held = frames[:2], frames[2:]
    sensor = DepthSensor(model)
    config = DiagnoseConfig(seed=0)
    with torch.no_grad():
        base_fit, base_held = evaluate(sensor, fit_frames, config.seed), evaluate(sensor, held, config.seed)
    assert base_held.excess > 0.5, "the model without fall-off keeps depth in the corners the device loses"
    for name in ("beam_falloff", "lens_vignetting"):
        found, values, score = fit_behaviour(sensor, name, fit_frames, config, base_fit)
        with torch.no_grad():
            after = evaluate(found, held, config.seed)
        print(f"{name}: {values}, held-out gap beyond the floor {base_held.excess:.2f} -> {after.excess:.2f} mm")
        assert next(iter(values.values())) >= 4.0
        assert after.excess <= 0.2 * base_held.excess and after.validity_ll > base_held.validity_ll


@pytest.mark.slow
@pytest.mark.skipif(not (LINEMOD / "test" / "000006" / "scene_gt.json").is_file(), reason="real LineMOD data absent")
def test_real_kinect_cat_from_the_paper_sensor_names_what_the_device_does_at_edges(tmp_path, capsys):
    """The real LineMOD cat (one frame, split spatially), diagnosed from the paper's sensor on the annotated object:
    the model loses depth in a ring around the cat where the real Kinect keeps it. The diagnosis names a device
    behaviour for it first and the held-out gap beyond the noise floor falls by more than issue 15's 30 % (measured:
    edge_keeping_matches at 0.35, the value kinect_v1.yaml measured on other statistics, 1.38 -> 0.09 mm; the
    narrow-gap fill at 4 px, kinect_v1's value again, came second at +69 %). The extended preset carries the key.
    The loop then stops by itself: the gap is below its noise floor (1.49 -> -0.48 mm beyond the floor averaged
    over 4 units), nothing is left to explain (it used to add a 0.02 px offset next)."""
    from ddsgen.cli import main

    report, extended = tmp_path / "report", tmp_path / "extended.yaml"
    code = main(["diagnose", "kinect_v1_paper", str(LINEMOD), "--region", "objects",
                 "--report", str(report), "--apply", str(extended), "--quiet"])  # fmt: skip
    out = capsys.readouterr().out
    print(out)
    assert code == 0
    data = json.loads((report / "diagnosis.json").read_text())
    (step,) = data["steps"]  # one effect, then below the floor: stop
    assert step["effect"] in ("edge_keeping_matches", "narrow_gap_fill")
    assert step["gap_after"] <= 0.7 * step["gap_before"]
    assert step["gap_after"] <= 0.0 and "is below its noise floor now" in (report / "report.html").read_text()
    key = BEHAVIOURS[step["effect"]].key
    assert yaml.safe_load(extended.read_text())[key] == pytest.approx(step["params"][key])
    assert load_preset(extended).confirmed_match_zncc < 1.0 or load_preset(extended).cleanup_fill_width_px > 0
