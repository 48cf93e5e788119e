"""Preset loading: shipped presets carry DESIGN.md's numbers; every bad field is one clear InputError."""

import math

import pytest
import yaml

from ddsgen.errors import InputError
from ddsgen.preset import PRESET_DIR, load_preset, preset_from_dict, save_preset


def _kinect_dict():
    return yaml.safe_load((PRESET_DIR / "kinect_v1.yaml").read_text())


def test_shipped_presets_match_the_paper_supplementary():
    kinect = load_preset("kinect_v1_paper")
    assert (kinect.width_px, kinect.height_px, kinect.focal_px) == (640, 480, 572.41)
    assert (kinect.baseline_m, kinect.z_min_m, kinect.z_max_m, kinect.block_size_px) == (0.075, 0.4, 4.0, 9)
    assert (kinect.emitted_intensity, kinect.shadow_bias_m, kinect.softargmax_beta, kinect.subpixel_level) == (
        1.5e6, 0.005, 15.0, 2)
    mp = load_preset(PRESET_DIR / "matterport_pro2.yaml")
    assert (mp.width_px, mp.height_px, mp.focal_px, mp.z_max_m, mp.block_size_px) == (1280, 1024, 1075.43, 8.0, 11)
    assert (mp.shadow_bias_m, mp.softargmax_beta, mp.subpixel_level) == (0.001, 25.0, 4)
    # The paper's eta_c = 1.5e12 saturates every pixel in our intensity units (see the preset's comment).
    assert mp.emitted_intensity == 1.5e7
    # Disparity range f*b/z: Kinect 10.7 .. 107.3 px
    assert math.isclose(kinect.disparity_max_px, 572.41 * 0.075 / 0.4)
    # The paper's sketch has none of the device's extras (all off by default).
    assert (kinect.speckle_grain_px, kinect.speckle_fixed_to_scene, kinect.electrons_per_count) == (0.0, False, 0.0)
    assert (kinect.projector_falloff_exponent, kinect.vignetting_exponent) == (0.0, 0.0)
    assert (kinect.cleanup_speckle_px, kinect.cleanup_hole_px, kinect.output_left_border_px) == (0, 0, 0)


def test_every_preset_line_is_one_key_and_every_departure_from_the_paper_says_why():
    """A preset is one line per key; kinect_v1 = kinect_v1_paper plus the modelled device causes, each of whose lines
    carries its reason as a comment (a key line with no comment takes the paper's value)."""
    for name in ("kinect_v1", "kinect_v1_paper", "matterport_pro2"):
        lines = [line for line in (PRESET_DIR / f"{name}.yaml").read_text().splitlines() if line.strip()]
        comments = [line for line in lines if line.startswith("#")]
        assert len(comments) <= 3 and all(line == lines[i] for i, line in enumerate(comments)), name  # a header
        keys = [line.split(":")[0] for line in lines if not line.startswith("#")]
        assert len(keys) == len(set(keys)) == len(lines) - len(comments), name
    paper, device = load_preset("kinect_v1_paper").to_dict(), load_preset("kinect_v1").to_dict()
    changed = {key for key in paper if key != "name" and paper[key] != device[key]}
    assert "subpixel_level" in changed and device["subpixel_level"] == 3  # the device's 1/8-px quantum
    lines = {line.split(":")[0]: line for line in (PRESET_DIR / "kinect_v1.yaml").read_text().splitlines()}
    for key in changed:
        assert "#" in lines[key] and len(lines[key].split("#", 1)[1].strip()) > 10, key


def test_save_and_reload_round_trip(tmp_path):
    kinect = load_preset("kinect_v1")
    save_preset(kinect.replace(baseline_m=0.078), tmp_path / "fitted.yaml")
    again = load_preset(tmp_path / "fitted.yaml")
    assert again.baseline_m == 0.078
    assert again.replace(baseline_m=0.075).to_dict() == kinect.to_dict()


@pytest.mark.parametrize(
    "change, message",
    [
        ({"baseline_mm": 75}, "unknown key (did you mean 'baseline_m'?)"),
        ({"focal_lenght_px": 580}, "unknown key (did you mean 'focal_y_px' or 'focal_px'?)"),
        ({"focal_px": -5.0}, "focal_px: must be > 0"),
        ({"baseline_m": 0}, "baseline_m: must be > 0"),
        ({"block_size_px": 8}, "block_size_px: must be odd"),
        ({"block_size_px": 101, "height_px": 96, "width_px": 128}, "block_size_px: must not exceed the image"),
        ({"softargmax_beta": float("nan")}, "softargmax_beta: must be a finite number"),
        ({"emitted_intensity": float("inf")}, "emitted_intensity: must be a finite number"),
        ({"width_px": "wide"}, "width_px: expected a number"),
        ({"subpixel_level": 1.5}, "subpixel_level: expected an integer"),
        ({"z_min_m": 12.0}, "z_min_m: must be smaller than z_max_m"),
        ({"effects": [{"name": "lens_distorsion"}]}, "unknown effect 'lens_distorsion'"),
        ({"speckle_fixed_to_scene": "yes"}, "speckle_fixed_to_scene: expected true or false"),
        ({"speckle_fixed_to_scene": 1}, "speckle_fixed_to_scene: expected true or false"),
        ({"cleanup_hole_px": -1}, "cleanup_hole_px: must be >= 0"),
        ({"cleanup_max_diff_px": 0}, "cleanup_max_diff_px: must be > 0"),
        ({"vignetting_exponent": 40}, "vignetting_exponent: must be <= 32"),
    ],
)
def test_bad_fields_name_file_key_and_problem(change, message):
    data = _kinect_dict()
    data.update(change)
    with pytest.raises(InputError) as error:
        preset_from_dict(data, source="my.yaml")
    text = str(error.value)
    assert text.startswith("my.yaml: ") and message in text and "\n" not in text


def test_missing_required_key_and_malformed_yaml(tmp_path):
    data = _kinect_dict()
    del data["focal_px"]
    with pytest.raises(InputError, match="focal_px: missing required key"):
        preset_from_dict(data, source="p.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("name: x\nwidth_px: [640\n")
    with pytest.raises(InputError, match=r"bad.yaml: malformed YAML at line \d+"):
        load_preset(bad)
    with pytest.raises(InputError, match="preset file not found"):
        load_preset(tmp_path / "absent.yaml")


def test_a_folder_named_like_a_shipped_preset_does_not_hide_it(tmp_path, monkeypatch):
    """``ddsgen render kinect_v1 --out kinect_v1`` makes a folder of that name; later commands run there still find
    the shipped preset, and a folder that is no preset's name is named as a folder."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "kinect_v1").mkdir()
    assert load_preset("kinect_v1").name == "kinect_v1"
    (tmp_path / "renders").mkdir()
    with pytest.raises(InputError, match="renders: is a folder, not a preset file"):
        load_preset("renders")
