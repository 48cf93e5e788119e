"""The bad-input corpus (tests/bad_inputs/, listed in its manifest.json).

Every malformed preset, scene list and scan folder must give: exit code 2, exactly one
line on stderr that names the file and the problem, no traceback, nothing on stdout,
and nothing written in the --out folder. Presets and scene lists go through
``ddsgen render`` (in-process via ``ddsgen.cli.main``; a few also as a real subprocess);
scan folders through the first command that reads them (``diagnose``/``fit``/``compare``)
when it exists, else through ``read_scan_folder`` with the CLI's error formatting.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from ddsgen.cli import cli, main
from ddsgen.errors import InputError

CORPUS = Path(__file__).resolve().parent / "bad_inputs"
CASES = json.loads((CORPUS / "manifest.json").read_text())["cases"]
GOOD_PRESET = "kinect_v1"  # bad scene lists are rejected before anything is rendered
REPO = CORPUS.parent.parent


def _case_id(case: dict) -> str:
    return case["path"].replace("/", ":")


def _scan_command() -> str | None:
    for name in ("diagnose", "fit", "compare"):
        if name in cli.commands:
            return name
    return None


def _argv(case: dict, out: Path) -> list[str] | None:
    path = str(CORPUS / case["path"])
    if case["kind"] == "preset":
        return ["render", path, "-n", "1", "--out", str(out), "--quiet"]
    if case["kind"] == "scenes":
        return ["render", GOOD_PRESET, "--scenes", path, "-n", "1", "--out", str(out), "--quiet"]
    command = _scan_command()
    if command == "diagnose":
        return ["diagnose", GOOD_PRESET, path, "--report", str(out)]
    if command == "fit":
        return ["fit", GOOD_PRESET, path, "--out", str(out / "fitted.yaml"), "--steps", "1"]
    return None


def _check_line(case: dict, err: str, out_text: str = "") -> None:
    assert "Traceback" not in err, err
    lines = err.strip().splitlines()
    assert len(lines) == 1, f"expected one line on stderr, got {len(lines)}:\n{err}"
    line = lines[0]
    assert line.startswith("ddsgen: error: "), line
    assert Path(case["path"]).name in line, f"the line does not name the file {case['path']}: {line}"
    assert case["expect"].lower() in line.lower(), f"the line does not say {case['expect']!r}: {line}"
    assert out_text == "", out_text


def test_corpus_is_large_and_listed():
    kinds = {kind: sum(c["kind"] == kind for c in CASES) for kind in ("preset", "scenes", "scan")}
    assert len(CASES) >= 30 and all(v >= 5 for v in kinds.values()), kinds
    for case in CASES:
        assert (CORPUS / case["path"]).exists(), case["path"]
        assert case["tests"] and case["expect"]
    assert len({c["path"] for c in CASES}) == len(CASES)


@pytest.mark.parametrize("case", CASES, ids=_case_id)
def test_bad_input_is_one_line_exit_2(case, tmp_path, capsys):
    out = tmp_path / "out"
    argv = _argv(case, out)
    if argv is None:  # no CLI command reads scan folders yet: the library call the commands make
        from ddsgen.io.scanfolder import read_scan_folder

        with pytest.raises(InputError) as error:
            read_scan_folder(CORPUS / case["path"], eager=True)
        _check_line(case, f"ddsgen: error: {error.value}\n")
        return
    code = main(argv)
    captured = capsys.readouterr()
    assert code == 2, f"exit {code}; stderr: {captured.err}"
    _check_line(case, captured.err, captured.out)
    assert not out.exists(), f"{out} was written: {sorted(p.name for p in out.rglob('*'))}"


@pytest.mark.parametrize("path", ["presets/block_even.yaml", "presets/truncated.yaml", "scenes/mesh_no_faces.yaml"])
def test_bad_input_through_console_script(path, tmp_path):
    case = next(c for c in CASES if c["path"] == path)
    out = tmp_path / "out"
    argv = _argv(case, out)
    env = dict(os.environ, PYTHONWARNINGS="ignore")
    result = subprocess.run([sys.executable, "-c", "from ddsgen.cli import entry_point; entry_point()", *argv],
                            capture_output=True, text=True, cwd=tmp_path, env=env, timeout=120)  # fmt: skip
    assert result.returncode == 2, result.stderr
    _check_line(case, result.stderr, result.stdout)
    assert not out.exists()


@pytest.mark.parametrize("control", json.loads((CORPUS / "manifest.json").read_text())["controls"], ids=_case_id)
def test_controls_load(control):
    """The valid originals load: each bad case fails because of its one change, not because of the setup."""
    from ddsgen.io.scanfolder import read_scan_folder
    from ddsgen.preset import load_preset
    from ddsgen.scene.scenelist import load_scene_list

    path = CORPUS / control["path"]
    loader = {"preset": load_preset, "scenes": load_scene_list, "scan": lambda p: read_scan_folder(p, eager=True)}
    assert loader[control["kind"]](path)


def _leaf_commands(group=cli, path=()):
    """(command path, click command) of every command below ``group``, subcommands included."""
    for name, command in group.commands.items():
        if hasattr(command, "commands"):
            yield from _leaf_commands(command, path + (name,))
        else:
            yield path + (name,), command


def _options(command) -> list:
    return [p for p in command.params if p.param_type_name == "option"]


LEAVES = dict(_leaf_commands())
SEED_COMMANDS = sorted(path for path, command in LEAVES.items() if any("--seed" in p.opts for p in _options(command)))


def test_every_seeded_command_is_checked():
    assert {"render", "compare", "fit", "diagnose", "pattern"} <= {p[-1] for p in SEED_COMMANDS}, SEED_COMMANDS


@pytest.mark.parametrize("command", SEED_COMMANDS, ids=" ".join)
def test_negative_seed_is_one_line_exit_2(command, tmp_path, capsys):
    """numpy's seeds are >= 0: a negative --seed is bad input named on one line, before anything is read or written
    (it was a traceback after render had started its output folder)."""
    out = tmp_path / "out"
    out_option = "--out" if any("--out" in p.opts for p in _options(LEAVES[command])) else "--report"
    argv = [*command, "--seed", "-1", out_option, str(out)]
    code = main(argv)
    captured = capsys.readouterr()
    assert code == 2, f"exit {code}; stderr: {captured.err}"
    assert "Traceback" not in captured.err
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1 and "--seed" in lines[0] and "-1" in lines[0], captured.err
    assert not out.exists()


def test_ranged_float_options_reject_nan():
    """click's FloatRange lets NaN through (every comparison with NaN is False): a ranged float option must be a
    FiniteFloat, so that `--albedo nan` is bad input, not a run."""
    import click

    from ddsgen.commands import FiniteFloat

    ranged = [(" ".join(path), p.opts[0], isinstance(p.type, FiniteFloat)) for path, command in LEAVES.items()
              for p in _options(command) if isinstance(p.type, click.FloatRange)]  # fmt: skip
    assert len(ranged) >= 4, ranged
    assert all(finite for _, _, finite in ranged), [r for r in ranged if not r[2]]


NAN_CASES = [
    ("compare", "kinect_v1", "{dir}", "--plausible-px"),
    ("diagnose", "kinect_v1", "{dir}", "--plausible-px"),
    ("diagnose", "kinect_v1", "{dir}", "--holdout"),
    ("fit", "kinect_v1", "{dir}", "--out", "{dir}/f.yaml", "--plausible-px"),
    ("fit", "kinect_v1", "{dir}", "--out", "{dir}/f.yaml", "--depth-scale"),
    ("fit", "kinect_v1", "{dir}", "--out", "{dir}/f.yaml", "--lr"),
    ("fit", "kinect_v1", "{dir}", "--out", "{dir}/f.yaml", "--prior"),
    ("fit", "kinect_v1", "{dir}", "--out", "{dir}/f.yaml", "--holdout"),
    ("refine", "kinect_v1", "{dir}", "--out", "{dir}/out", "--band-mm"),
    ("refine", "kinect_v1", "{dir}", "--out", "{dir}/out", "--edge-weight"),
    ("stereo", "{dir}/l.png", "{dir}/r.png", "--max-disparity"),
    ("stereo", "{dir}/l.png", "{dir}/r.png", "--min-disparity"),
    ("stereo", "{dir}/l.png", "{dir}/r.png", "--beta"),
    ("stereo", "{dir}/l.png", "{dir}/r.png", "--min-confidence"),
    ("study", "noise", "kinect_v1", "--albedo"),
    ("pattern", "kinect_v1", "--density"),
]


@pytest.mark.parametrize("case", NAN_CASES, ids=lambda c: f"{c[0]} {c[-1]}")
def test_nan_float_option_is_one_line_exit_2(case, tmp_path, capsys):
    """A NaN number on the command line is named on one line with exit 2, before anything is read or written
    (`stereo --beta nan` and `fit --depth-scale nan` ran; `compare --plausible-px nan` failed later with a
    message about the scene)."""
    (tmp_path / "l.png").write_bytes(b"")
    (tmp_path / "r.png").write_bytes(b"")
    out = tmp_path / "out"
    argv = [a.format(dir=tmp_path) for a in case] + ["nan"]
    if case[0] in ("stereo", "pattern", "study"):
        argv += ["--out", str(out)]
    code = main(argv)
    captured = capsys.readouterr()
    assert code == 2, f"exit {code}; stderr: {captured.err}"
    lines = captured.err.strip().splitlines()
    assert "Traceback" not in captured.err and len(lines) == 1, captured.err
    assert case[-1] in lines[0], lines[0]
    assert not out.exists() and not (tmp_path / "f.yaml").exists()


def test_zero_frames_is_one_line_exit_2_and_no_folder(tmp_path, capsys):
    """-n 0 started the output folder (run.json, sensor.yaml) and then failed on the manifest no frame had written."""
    out = tmp_path / "out"
    assert main(["render", "kinect_v1", "-n", "0", "--out", str(out), "--quiet"]) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert lines == ["ddsgen: error: -n: must be >= 1, got 0"], lines
    assert not out.exists()


@pytest.mark.parametrize("unpaired", [False, True])
def test_fit_output_under_a_file_is_one_line_exit_2_before_any_work(unpaired, tmp_path, capsys):
    """A file where the fitted preset's folder should be was a traceback at the very end of a fit."""
    blocker = tmp_path / "a_file"
    blocker.write_text("")
    real = tmp_path / "real"
    real.mkdir()
    argv = ["fit", "kinect_v1", str(real), "--out", str(blocker / "fitted.yaml")] + (["--unpaired"] if unpaired else [])
    assert main(argv) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and "a_file is a file, not a folder" in lines[0], lines


def test_an_os_error_no_command_expected_is_one_line_exit_2(monkeypatch, capsys):
    """The last net: an OSError (no space, no permission, ...) is one line naming the path, never a traceback."""
    def refuse(*args, **kwargs):
        raise PermissionError(13, "Permission denied", "/somewhere/out.png")

    monkeypatch.setattr(cli.commands["pattern"], "callback", refuse)
    assert main(["pattern"]) == 2
    err = capsys.readouterr().err
    assert err.strip() == "ddsgen: error: /somewhere/out.png: permission denied", err
