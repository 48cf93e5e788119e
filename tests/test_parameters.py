"""The parameter registry (ddsgen/parameters.py): every preset key is declared there once, and every table the
commands use is derived from it with the values these tables held when they were written out by hand."""

from __future__ import annotations

import ast
import dataclasses
from pathlib import Path

import pytest

from ddsgen.diagnose.device_candidates import BEHAVIOURS
from ddsgen.diagnose.stage_cache import PARAMETER_KEYS, VALIDITY_STAGE_KEYS
from ddsgen.fit.parameters import SENSOR_PARAMS
from ddsgen.fit.unpaired.parameters import UNPAIRED_PARAMETERS
from ddsgen.parameters import PARAMETERS, REQUIRED, STAGES, stage_keys
from ddsgen.preset import FIELDS, PRESET_DIR, SensorPreset, shipped_preset_names
from ddsgen.yamlfile import read_yaml

PACKAGE = Path(__file__).resolve().parents[1] / "ddsgen"
REGISTRY_MODULE = PACKAGE / "parameters.py"

# ---- the tables as they were written out by hand (kind, low, high, low_open, default) ------------------------------
EXPECTED_FIELDS = {
    "name": (str, None, None, False, REQUIRED),
    "width_px": (int, 8, 16384, False, REQUIRED),
    "height_px": (int, 8, 16384, False, REQUIRED),
    "focal_px": (float, 0, 100000.0, True, REQUIRED),
    "focal_y_px": (float, 0, 100000.0, True, None),
    "cx_px": (float, None, None, False, None),
    "cy_px": (float, None, None, False, None),
    "baseline_m": (float, 0, 2.0, True, REQUIRED),
    "z_min_m": (float, 0, 1000.0, True, REQUIRED),
    "z_max_m": (float, 0, 1000.0, True, REQUIRED),
    "block_size_px": (int, 3, 255, False, REQUIRED),
    "emitted_intensity": (float, 0, 1e20, True, REQUIRED),
    "shadow_bias_m": (float, 0, 1.0, False, REQUIRED),
    "softargmax_beta": (float, 0, 10000.0, True, REQUIRED),
    "subpixel_level": (int, 0, 6, False, REQUIRED),
    "speckle_shape": (float, 0, 10000.0, True, 4.54),
    "speckle_scale": (float, 0, 1000.0, True, 0.196),
    "speckle_grain_px": (float, 0, 50, False, 0.0),
    "speckle_fixed_to_scene": (bool, None, None, False, False),
    "read_noise_mean_counts": (float, -10000.0, 10000.0, False, -0.126),
    "read_noise_std_counts": (float, 0, 10000.0, False, 10.4),
    "electrons_per_count": (float, 0, 1000000.0, False, 0.0),
    "ambient_counts": (float, 0, 1000000.0, False, 0.0),
    "projector_falloff_exponent": (float, 0, 32, False, 0.0),
    "vignetting_exponent": (float, 0, 32, False, 0.0),
    "ir_bits": (int, 4, 16, False, 10),
    "min_confidence": (float, 0, 1, False, 0.15),
    "shadow_always_invalid": (bool, None, None, False, True),
    "no_hit_always_invalid": (bool, None, None, False, True),
    "row_smoothing_weight": (float, 0, 0.5, False, 0.0),
    "confirmed_match_zncc": (float, 0, 1, False, 1.0),
    "cleanup_speckle_px": (int, 0, 1000000, False, 0),
    "cleanup_max_diff_px": (float, 0, 1000, True, 1.0),
    "cleanup_hole_px": (int, 0, 1000000, False, 0),
    "cleanup_fill_width_px": (int, 0, 1000, False, 0),
    "output_left_border_px": (int, 0, 16384, False, 0),
    "output_right_border_px": (int, 0, 16384, False, 0),
    "ir_margin_right_px": (int, 0, 64, False, 0),
    "registration_ir_offset_m": (float, 0, 1, False, 0.0),
    "registration_shift_px": (float, -1000, 1000, False, 0.0),
    "registration_dense": (bool, None, None, False, False),
    "registration_forward_gap_px": (int, 0, 64, False, 0),
    "registration_forward_fill_rows": (int, 0, 16, False, 0),
    "output_top_border_px": (int, 0, 16384, False, 0),
    "output_bottom_border_px": (int, 0, 16384, False, 0),
    "band_rows": (int, 1, 16384, False, 64),
    "pattern": (str, None, None, False, "kinect_like_640.png"),
    "pattern_psf_px": (float, 0, 10, True, 0.5),
    "pattern_dot_jitter_px": (float, 0, 2, False, 0.0),
    "ir_lens_k1": (float, -0.5, 0.5, False, 0.0),
    "reference_distance_m": (float, 0.2, 20, False, 1.0),
    "effects": (list, None, None, False, ()),
    "postprocess": (str, None, None, False, None),
}
# --params name: (attr, key, log, bound, width, group, step), in the fit's order
EXPECTED_SENSOR_PARAMS = {
    "emitted_intensity": ("log_emitted_intensity", "emitted_intensity", True, ("factor", 0.25, 4.0), 0.7, "snr", 0.25),
    "read_noise_std": ("log_read_noise_std", "read_noise_std_counts", True, ("factor", 0.25, 4.0), 0.7, "snr", 0.25),
    "beta": ("log_beta", "softargmax_beta", True, ("range", 5.0, 40.0), 1.0, "matching", 0.15),
    "baseline": ("log_baseline", "baseline_m", True, ("factor", 0.95, 1.05), 0.02, "geometry", 0.005),
    "focal": ("log_focal_scale", "focal_px", True, ("factor", 0.97, 1.03), 0.01, "geometry", 0.003),
    "speckle_scale": ("log_speckle_scale", "speckle_scale", True, ("factor", 0.25, 4.0), 0.7, "pattern", 0.2),
    "ambient": ("log_ambient", "ambient_counts", True, ("range", 1e-06, 255.0), 3.0, "ambient", 0.1),
    "read_noise_mean": ("read_noise_mean", "read_noise_mean_counts", False, ("range", -64.0, 64.0), 16.0, "ir_offset",
                        1.0),
    "projector_falloff": (None, "projector_falloff_exponent", False, ("range", 0.0, 8.0), 2.0, "falloff", 0.5),
    "vignetting": (None, "vignetting_exponent", False, ("range", 0.0, 8.0), 1.0, "falloff", 0.5),
    "speckle_grain": (None, "speckle_grain_px", False, ("range", 0.0, 3.0), 0.5, "speckle", 0.25),
    "speckle_shape": (None, "speckle_shape", True, ("factor", 0.25, 4.0), 0.7, "speckle", 0.2),
    "shot_noise_gain": (None, "electrons_per_count", True, ("factor", 0.25, 4.0), 0.7, "snr", 0.25),
    "cleanup_speckle": (None, "cleanup_speckle_px", False, ("range", 0.0, 400.0), 100.0, "cleanup", 25.0),
    "cleanup_hole": (None, "cleanup_hole_px", False, ("range", 0.0, 32.0), 8.0, "cleanup", 2.0),
    "cleanup_max_diff": (None, "cleanup_max_diff_px", False, ("range", 0.25, 4.0), 1.0, "cleanup", 0.25),
    "cleanup_fill_width": (None, "cleanup_fill_width_px", False, ("range", 0.0, 8.0), 4.0, "cleanup", 1.0),
    "confirmed_match": (None, "confirmed_match_zncc", False, ("range", 0.2, 1.0), 0.5, "edges", 0.05),
}  # fmt: skip
# key: (key, low, high, log, integer, grid, choices, terms), in search order
EXPECTED_UNPAIRED = {
    "subpixel_level": ("subpixel_level", 1, 4, False, True, 7, (), ("total",)),
    "emitted_intensity": ("emitted_intensity", 200000.0, 50000000.0, True, False, 8, (), ("total",)),
    "softargmax_beta": ("softargmax_beta", 4.0, 60.0, True, False, 7, (), ("total",)),
    "row_smoothing_weight": ("row_smoothing_weight", 0.0, 0.3, False, False, 7, (), ("grain",)),
    "min_confidence": ("min_confidence", 0.05, 0.35, False, False, 7, (), ("total",)),
    "cleanup_hole_px": ("cleanup_hole_px", 0, 32, False, True, 7, (0, 2, 4, 8, 16, 32), ("holes",)),
    "cleanup_speckle_px": ("cleanup_speckle_px", 0, 400, False, True, 7, (0, 25, 50, 100, 200, 400), ("holes",)),
    "projector_falloff_exponent": ("projector_falloff_exponent", 0.0, 16.0, False, False, 5, (), ("radius",)),
}
# name: (key, off, grid, unit, stage, axis, generic), in candidate order
EXPECTED_BEHAVIOURS = {
    "edge_keeping_matches": ("confirmed_match_zncc", 1.0, (0.3, 0.35, 0.4, 0.5, 0.6), "ZNCC", "disparity",
                             "edge_distance", False),
    "hole_fill": ("cleanup_hole_px", 0, (2, 4, 8, 16, 32), "px", "validity", "signal", False),
    "narrow_gap_fill": ("cleanup_fill_width_px", 0, (1, 2, 3, 4, 6), "px", "validity", "edge_distance", False),
    "speckle_removal": ("cleanup_speckle_px", 0, (25, 50, 100, 200, 400), "px", "validity", "signal", False),
    "beam_falloff": ("projector_falloff_exponent", 0.0, (2.0, 4.0, 6.0, 8.0), "", "disparity", "radius", False),
    "lens_vignetting": ("vignetting_exponent", 0.0, (2.0, 4.0, 6.0, 8.0), "", "disparity", "radius", False),
}  # fmt: skip
EXPECTED_VALIDITY_STAGE_KEYS = {"cleanup_speckle_px": 0, "cleanup_hole_px": 0, "cleanup_fill_width_px": 0,
                                "cleanup_max_diff_px": 1.0}  # fmt: skip
EXPECTED_PARAMETER_KEYS = {"emitted_intensity", "speckle_scale", "read_noise_std_counts", "read_noise_mean_counts",
                           "ambient_counts", "softargmax_beta", "baseline_m"}  # fmt: skip


def _typed(value):
    """A value with the types of its numbers spelled out (0 and 0.0 are different values to a written preset)."""
    if isinstance(value, (tuple, list)):
        return tuple(_typed(v) for v in value)
    return "REQUIRED" if value is REQUIRED else (type(value).__name__, value)


def test_the_preset_schema_holds_its_ranges_and_defaults():
    assert list(FIELDS) == list(EXPECTED_FIELDS)  # the order of keys in a written preset
    for key, field in FIELDS.items():
        assert _typed((field.kind, field.low, field.high, field.low_open, field.default)) == _typed(
            EXPECTED_FIELDS[key]), key


def test_the_fit_tables_hold_their_bounds_priors_and_grids():
    assert list(SENSOR_PARAMS) == list(EXPECTED_SENSOR_PARAMS)  # the --params help and the device-key search order
    for name, spec in SENSOR_PARAMS.items():
        got = (spec.attr, spec.key, spec.log, spec.bound, spec.width, spec.group, spec.step)
        assert _typed(got) == _typed(EXPECTED_SENSOR_PARAMS[name]), name
    assert list(UNPAIRED_PARAMETERS) == list(EXPECTED_UNPAIRED)  # the search order
    for key, p in UNPAIRED_PARAMETERS.items():
        got = (p.key, p.low, p.high, p.log, p.integer, p.grid, p.choices, p.terms)
        assert _typed(got) == _typed(EXPECTED_UNPAIRED[key]), key


def test_the_diagnosis_tables_hold_their_grids_and_keys():
    assert list(BEHAVIOURS) == list(EXPECTED_BEHAVIOURS)  # the candidate order
    for name, b in BEHAVIOURS.items():
        got = (b.key, b.off, b.grid, b.unit, b.stage, b.axis, b.generic)
        assert _typed(got) == _typed(EXPECTED_BEHAVIOURS[name]), name
        assert b.params[b.key].low == min(b.grid) and b.params[b.key].high == max(b.grid)
    assert _typed(sorted(VALIDITY_STAGE_KEYS.items())) == _typed(sorted(EXPECTED_VALIDITY_STAGE_KEYS.items()))
    # (only the set matters: the keys are passed by name to SensorPreset.replace)
    assert set(PARAMETER_KEYS) == EXPECTED_PARAMETER_KEYS and len(PARAMETER_KEYS) == len(EXPECTED_PARAMETER_KEYS)


def test_every_key_of_every_shipped_preset_is_in_the_registry():
    for name in shipped_preset_names():
        data = read_yaml(PRESET_DIR / f"{name}.yaml", "preset")
        assert set(data) <= set(PARAMETERS), (name, sorted(set(data) - set(PARAMETERS)))


def test_the_preset_dataclass_has_one_field_per_registry_key_of_its_kind():
    fields = [f for f in dataclasses.fields(SensorPreset) if f.name != "source"]
    assert [f.name for f in fields] == list(PARAMETERS)
    for f in fields:
        p = PARAMETERS[f.name]
        spelled = {list: "tuple"}.get(p.kind, p.kind.__name__)  # the effects list is held as a tuple
        allowed = {spelled, f"{spelled} | None"} if p.default is None else {spelled}
        assert f.type in allowed, (f.name, f.type, p.kind)


def test_every_key_has_a_stage_a_doc_and_a_default_inside_its_range():
    assert set(STAGES) >= {"camera", "pattern", "ir", "matcher", "row_smoothing", "validity", "cleanup",
                           "output_window", "registration", "effects", "postprocess", "name"}  # fmt: skip
    assert sum(len(stage_keys(s)) for s in STAGES) == len(PARAMETERS)
    assert set(stage_keys("cleanup")) == {"cleanup_speckle_px", "cleanup_max_diff_px", "cleanup_hole_px",
                                          "cleanup_fill_width_px"}  # fmt: skip
    for p in PARAMETERS.values():
        assert p.doc and "\n" not in p.doc, p.name
        if isinstance(p.default, (int, float)) and not isinstance(p.default, bool):
            assert p.low is None or (p.default > p.low if p.low_open else p.default >= p.low), p.name
            assert p.high is None or p.default <= p.high, p.name
    for records in ([p.fit for p in PARAMETERS.values() if p.fit],
                    [p.unpaired for p in PARAMETERS.values() if p.unpaired],
                    [p.diagnose for p in PARAMETERS.values() if p.diagnose]):  # fmt: skip
        orders = sorted(r.order for r in records)
        assert orders == list(range(len(records)))  # one place each, none shared


def test_a_search_stays_within_the_keys_physical_range():
    """What fit, fit --unpaired and diagnose may try is a value a preset may hold."""
    for p in PARAMETERS.values():
        tried = []
        if p.fit and p.fit.bound[0] == "range":
            tried += p.fit.bound[1:]
        if p.unpaired:
            tried += [p.unpaired.low, p.unpaired.high, *p.unpaired.choices]
        if p.diagnose:
            tried += [p.diagnose.off, *p.diagnose.grid]
        for value in tried:
            assert p.low is None or (value > p.low if p.low_open else value >= p.low), (p.name, value)
            assert p.high is None or value <= p.high, (p.name, value)


# ---- no range of a preset key anywhere else -------------------------------------------------------------------------
NUMERIC_KEYS = {name for name, p in PARAMETERS.items() if p.kind in (int, float)}


def _numbers(node: ast.AST) -> int:
    """How many numbers ``node`` writes as literal values: itself, the items of a tuple or list, the arguments of a
    call (a negative number counts once; a number inside arithmetic or a condition is no bound)."""
    if isinstance(node, ast.UnaryOp) and isinstance(node.op, ast.USub):
        node = node.operand
    if isinstance(node, ast.Constant):
        return int(isinstance(node.value, (int, float)) and not isinstance(node.value, bool))
    if isinstance(node, (ast.Tuple, ast.List)):
        return sum(_numbers(item) for item in node.elts)
    if isinstance(node, ast.Call):
        return sum(_numbers(item) for item in (*node.args, *(kw.value for kw in node.keywords)))
    return 0


def _effect_parameter(node: ast.AST) -> bool:
    """An effect's own parameter spec (``EffectParam(...)``): an effect may name a parameter like a preset key."""
    return isinstance(node, ast.Call) and getattr(node.func, "id", getattr(node.func, "attr", "")) == "EffectParam"


def _names_key(node: ast.AST) -> str | None:
    """The preset key ``node`` spells: the string "KEY", or an attribute ``x.KEY`` (a read of it)."""
    if isinstance(node, ast.Constant) and node.value in NUMERIC_KEYS:
        return node.value
    if isinstance(node, ast.Attribute) and node.attr in NUMERIC_KEYS:
        return node.attr
    return None


def range_literals(source: str) -> list[str]:
    """Where ``source`` writes numeric bounds next to a preset key: a dict entry ``"KEY": (lo, hi)`` or
    ``"KEY": Field(..., lo, hi)``, a call or tuple ``f("KEY", lo, hi)`` / ``("KEY", lo, hi)``, a keyword
    ``KEY=(lo, hi)``, a comparison ``lo <= p.KEY <= hi``. Returns "line: KEY" for each."""
    found = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Dict):
            for k, v in zip(node.keys, node.values):
                if (isinstance(k, ast.Constant) and (key := _names_key(k)) and _numbers(v) >= 2
                        and not _effect_parameter(v)):  # fmt: skip
                    found.append(f"{node.lineno}: {key}")
        elif isinstance(node, (ast.Call, ast.Tuple, ast.List)):
            items = list(node.args) + [kw.value for kw in node.keywords] if isinstance(node, ast.Call) else node.elts
            keys = [k for item in items if isinstance(item, ast.Constant) and (k := _names_key(item))]
            if keys and sum(_numbers(item) for item in items) >= 2:
                found.append(f"{node.lineno}: {keys[0]}")
            if isinstance(node, ast.Call):
                found += [f"{node.lineno}: {kw.arg}" for kw in node.keywords
                          if kw.arg in NUMERIC_KEYS and _numbers(kw.value) >= 2]  # fmt: skip
        elif isinstance(node, ast.Compare):
            operands = [node.left, *node.comparators]
            keys = [k for item in operands if (k := _names_key(item))]
            if keys and sum(_numbers(item) for item in operands) >= 2:
                found.append(f"{node.lineno}: {keys[0]}")
    return found


@pytest.mark.parametrize("source", [
    'FIELDS = {"cleanup_hole_px": Field(int, "holes smaller than this are filled (px)", 0, 1_000_000, default=0)}',
    'UnpairedParameter("cleanup_hole_px", 0, 32, log=False, integer=True)',
    'SensorParam(None, "cleanup_hole_px", False, ("range", 0.0, 32.0), 8.0, "cleanup", 2.0)',
    'DeviceBehaviour("hole_fill", "cleanup_hole_px", 0, (2, 4, 8, 16, 32), "px", "validity")',
    'grid = {"softargmax_beta": (5.0, 40.0)}',
    'search(key="min_confidence", low=0.05, high=0.35)',
    'p.replace(cleanup_hole_px=(0, 32))',
    'assert 0 <= preset.row_smoothing_weight <= 0.5',
])  # fmt: skip
def test_the_range_finder_sees_a_range_written_by_hand(source):
    assert range_literals(source)


def test_the_range_finder_lets_a_single_value_pass():
    assert not range_literals('p.replace(cleanup_hole_px=8, cx_px=(p.cx_px + 0.5) * 2 - 0.5)\n'
                              'x = {"cleanup_hole_px": 0, "ambient_counts": a if a > 1e-5 else 0.0}\n'
                              'if p.cleanup_hole_px > 0: pass\n'
                              'params = {"width_px": EffectParam(0.0, 0.0, 20.0, "px", "an effect\'s own")}')


def test_no_range_of_a_preset_key_is_written_outside_the_registry():
    offenders = {str(path.relative_to(PACKAGE)): hits for path in sorted(PACKAGE.rglob("*.py"))
                 if path != REGISTRY_MODULE and (hits := range_literals(path.read_text()))}  # fmt: skip
    assert not offenders, f"ranges of preset keys belong in ddsgen/parameters.py: {offenders}"
    assert range_literals(REGISTRY_MODULE.read_text())  # the finder does see the registry's own


def test_the_model_manual_names_every_preset_key():
    """docs/model.md lists each stage's keys: a key added to the registry is documented there too."""
    from pathlib import Path

    manual = (Path(__file__).resolve().parents[1] / "docs" / "model.md").read_text()
    missing = [name for name in PARAMETERS if name != "name" and f"`{name}`" not in manual]
    assert not missing, missing
