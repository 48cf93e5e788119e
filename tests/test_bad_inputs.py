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
