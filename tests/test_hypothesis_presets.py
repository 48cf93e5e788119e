"""Property-based tests over preset values (hypothesis).

* any valid combination of values loads, keeps its values, and survives save -> load unchanged;
* any value of any key (numbers out of range, NaN/inf, text, booleans, lists, mappings, null)
  either loads into a preset that satisfies every documented invariant, or raises InputError
  with one line naming the key -- never another exception;
* arbitrary YAML text and bytes given as a preset file: a preset or InputError, never a crash.
"""

from __future__ import annotations

import math

import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from ddsgen.errors import InputError
from ddsgen.preset import FIELDS, load_preset, preset_from_dict, save_preset

SETTINGS = settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])


@st.composite
def valid_presets(draw) -> dict:
    width = draw(st.integers(16, 2048))
    height = draw(st.integers(16, 2048))
    block = draw(st.integers(1, (min(width, height, 255) - 1) // 2)) * 2 + 1
    z_min = draw(st.floats(0.05, 10.0))
    z_max = draw(st.floats(z_min * 1.01 + 1e-6, 1000.0))
    baseline = draw(st.floats(0.001, 2.0))
    # focal such that the largest disparity f*b/z_min stays below the image width
    focal = draw(st.floats(1.0, 1e5).filter(lambda f: f * baseline / z_min < width - 1))
    data = {
        "name": draw(st.text(st.characters(categories=["L", "N"]), min_size=1, max_size=12)),
        "width_px": width,
        "height_px": height,
        "focal_px": focal,
        "baseline_m": baseline,
        "z_min_m": z_min,
        "z_max_m": z_max,
        "block_size_px": block,
        "emitted_intensity": draw(st.floats(1e-3, 1e20)),
        "shadow_bias_m": draw(st.floats(0.0, 1.0)),
        "softargmax_beta": draw(st.floats(1e-3, 1e4)),
        "subpixel_level": draw(st.integers(0, 6)),
    }
    optional = {
        "speckle_shape": st.floats(1e-3, 1e4),
        "read_noise_std_counts": st.floats(0.0, 1e4),
        "read_noise_mean_counts": st.floats(-1e4, 1e4),
        "ambient_counts": st.floats(0.0, 1e6),
        "ir_bits": st.integers(4, 16),
        "min_confidence": st.floats(0.0, 1.0),
        "band_rows": st.integers(1, 16384),
        "pattern_psf_px": st.floats(1e-3, 10.0),
        "cx_px": st.floats(0.0, float(width)),
        "focal_y_px": st.floats(1.0, 1e5),
        "speckle_grain_px": st.floats(0.0, 50.0),
        "speckle_fixed_to_scene": st.booleans(),
        "electrons_per_count": st.floats(0.0, 1e6),
        "projector_falloff_exponent": st.floats(0.0, 32.0),
        "vignetting_exponent": st.floats(0.0, 32.0),
        "cleanup_speckle_px": st.integers(0, 1_000_000),
        "cleanup_max_diff_px": st.floats(1e-3, 1000.0),
        "cleanup_hole_px": st.integers(0, 1_000_000),
    }
    for key in draw(st.lists(st.sampled_from(sorted(optional)), unique=True)):
        data[key] = draw(optional[key])
    return data


def _check_invariants(preset) -> None:
    for key, field in FIELDS.items():
        value = getattr(preset, key)
        if field.kind in (int, float) and value is not None:
            assert isinstance(value, field.kind) and not isinstance(value, bool), (key, value)
            assert math.isfinite(value), (key, value)
            if field.low is not None:
                assert value > field.low if field.low_open else value >= field.low, (key, value)
            if field.high is not None:
                assert value <= field.high, (key, value)
    assert preset.block_size_px % 2 == 1
    assert preset.block_size_px <= min(preset.width_px, preset.height_px)
    assert preset.z_min_m < preset.z_max_m
    assert preset.disparity_max_px < preset.width_px


@SETTINGS
@given(valid_presets())
def test_valid_values_load_and_round_trip(tmp_path, data):
    preset = preset_from_dict(data, source="hyp.yaml")
    for key, value in data.items():
        assert getattr(preset, key) == pytest.approx(value) if isinstance(value, float) else getattr(preset, key) == value
    _check_invariants(preset)
    path = tmp_path / "p.yaml"
    save_preset(preset, path)
    again = load_preset(path)
    assert again.to_dict() == preset.to_dict()


ANY_VALUE = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(-(2**70), 2**70),
    st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=20),
    st.sampled_from(["nan", "inf", "-inf", "1e400", "0x10", "1_000", "9.0", " 5 ", "", "yes"]),
    st.lists(st.integers(), max_size=3),
    st.dictionaries(st.text(max_size=5), st.integers(), max_size=2),
)


@SETTINGS
@given(valid_presets(), st.sampled_from(sorted(FIELDS)), ANY_VALUE)
def test_any_value_of_any_key_loads_or_is_an_input_error(data, key, value):
    data = dict(data, **{key: value})
    try:
        preset = preset_from_dict(data, source="hyp.yaml")
    except InputError as error:
        message = str(error)
        assert "\n" not in message and message.startswith("hyp.yaml: "), message
        return
    _check_invariants(preset)


NUMERIC = sorted(k for k, f in FIELDS.items() if f.kind in (int, float))


@SETTINGS
@given(valid_presets(), st.sampled_from(NUMERIC), st.data())
def test_out_of_range_or_non_finite_is_an_input_error_naming_the_key(data, key, draw):
    field = FIELDS[key]
    bad = [st.sampled_from([math.nan, math.inf, -math.inf])]
    if field.low is not None:
        below = st.floats(max_value=field.low, allow_nan=False, allow_infinity=False)
        bad.append(below if field.low_open else below.filter(lambda v: v < field.low))
    if field.high is not None:
        bad.append(st.floats(min_value=field.high, allow_nan=False, allow_infinity=False).filter(lambda v: v > field.high))
    value = draw.draw(st.one_of(bad))
    if field.kind is int and math.isfinite(value):
        value = math.floor(value) if field.low is not None and value < field.low else math.ceil(value)
        assume((field.low is not None and value < field.low) or (field.high is not None and value > field.high)
               or (field.low_open and value <= field.low))  # fmt: skip
    with pytest.raises(InputError) as error:
        preset_from_dict(dict(data, **{key: value}), source="hyp.yaml")
    assert f"hyp.yaml: {key}: " in str(error.value) and "\n" not in str(error.value)


@SETTINGS
@given(valid_presets(), st.text(st.characters(categories=["Ll"]), min_size=1, max_size=15))
def test_unknown_key_is_an_input_error(data, key):
    assume(key not in FIELDS)
    with pytest.raises(InputError, match=f"{key}: unknown key"):
        preset_from_dict(dict(data, **{key: 1}), source="hyp.yaml")


@SETTINGS
@given(st.one_of(st.text(max_size=200), st.binary(max_size=200).map(lambda b: b.decode("latin-1"))))
def test_arbitrary_yaml_text_is_a_preset_or_an_input_error(tmp_path, text):
    path = tmp_path / "arbitrary.yaml"
    path.write_bytes(text.encode("utf-8", "surrogatepass"))
    try:
        preset = load_preset(path)
    except InputError as error:
        assert "\n" not in str(error) and str(path) in str(error)
        return
    _check_invariants(preset)


@SETTINGS
@given(st.binary(min_size=1, max_size=64))
def test_arbitrary_bytes_are_an_input_error(tmp_path, blob):
    path = tmp_path / "blob.yaml"
    path.write_bytes(blob)
    try:
        load_preset(path)
    except InputError as error:
        assert "\n" not in str(error) and str(path) in str(error)
