"""Posed scans with nothing to work on: a depth image without one valid pixel, objects posed out of view.

``compare``, ``fit``, ``diagnose`` and ``refine`` must refuse them with one line and exit code 2 before writing
anything: an all-zero frame used to crash ``compare`` (a traceback from its table) and be "fitted" by ``fit``
and ``diagnose`` (a new effect explaining the empty frame), and objects behind the camera gave ``refine`` a NaN gap.
"""

from __future__ import annotations

import json
import shutil

import cv2
import numpy as np
import pytest
from test_compare import render, write_presets

from ddsgen.cli import main


@pytest.fixture(scope="module")
def scans(tmp_path_factory):
    """A rendered one-frame scan folder and two broken copies: ``zero`` (every depth pixel 0) and ``behind``
    (every annotated object 1 m behind the camera)."""
    root = tmp_path_factory.mktemp("empty_scans")
    paths = write_presets(root)
    good = render(paths["stock"], paths["scenes"], root / "good", 1)
    zero = root / "zero"
    shutil.copytree(good, zero)
    record = json.loads((zero / "manifest.jsonl").read_text().splitlines()[0])
    png = zero / record["depth"]
    cv2.imwrite(str(png), np.zeros_like(cv2.imread(str(png), cv2.IMREAD_UNCHANGED)))
    behind = root / "behind"
    shutil.copytree(good, behind)
    for obj in record["objects"]:
        obj["cam_T_obj"][2][3] = -1.0
    (behind / "manifest.jsonl").write_text(json.dumps(record) + "\n")
    return {"preset": str(paths["stock"]), "good": good, "zero": zero, "behind": behind, "png": png}


def _one_line_exit_2(capsys, argv, expect: str) -> str:
    capsys.readouterr()
    assert main(argv) == 2
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert "Traceback" not in err and len(lines) == 1, err
    assert lines[0].startswith("ddsgen: error: ") and expect in lines[0], lines[0]
    return lines[0]


@pytest.mark.parametrize("command", ["compare", "fit", "diagnose", "refine"])
def test_a_frame_without_one_valid_pixel_is_refused_by_every_posed_scan_command(command, scans, tmp_path, capsys):
    out = tmp_path / "out"
    argv = {"compare": ["compare", scans["preset"], str(scans["zero"]), "--report", str(out), "--quiet"],
            "fit": ["fit", scans["preset"], str(scans["zero"]), "--out", str(out / "fitted.yaml"), "--steps", "1",
                    "--quiet"],
            "diagnose": ["diagnose", scans["preset"], str(scans["zero"]), "--report", str(out), "--quiet"],
            "refine": ["refine", scans["preset"], str(scans["zero"]), "--out", str(out), "--steps", "1", "--quiet"],
            }[command]  # fmt: skip
    line = _one_line_exit_2(capsys, argv, "no valid pixel (all zero)")
    assert scans["png"].name in line
    assert not out.exists()


def test_objects_out_of_view_are_refused_where_only_the_objects_count(scans, tmp_path, capsys):
    out = tmp_path / "out"
    _one_line_exit_2(capsys, ["compare", scans["preset"], str(scans["behind"]), "--region", "objects",
                              "--report", str(out), "--quiet"], "--region objects: no annotated object is visible")  # fmt: skip
    _one_line_exit_2(capsys, ["refine", scans["preset"], str(scans["behind"]), "--out", str(out), "--steps", "1",
                              "--quiet"], "no annotated object is in view")  # fmt: skip
    assert not out.exists()
    # The control: the same folder with its objects in view compares and refines.
    assert main(["compare", scans["preset"], str(scans["good"]), "--region", "objects", "--report", str(out),
                 "--quiet"]) == 0  # fmt: skip


def test_an_unreadable_mesh_of_a_scan_is_named_once(scans, tmp_path, capsys):
    folder = tmp_path / "garbage_mesh"
    shutil.copytree(scans["good"], folder)
    (folder / "garbage.ply").write_bytes(b"ply\nformat ascii 1.0\nelement vertex 3\nend_header\n0 0\n")
    record = json.loads((folder / "manifest.jsonl").read_text().splitlines()[0])
    record["objects"][0]["mesh"] = "garbage.ply"
    (folder / "manifest.jsonl").write_text(json.dumps(record) + "\n")
    line = _one_line_exit_2(capsys, ["compare", scans["preset"], str(folder), "--report", str(tmp_path / "r"),
                                     "--quiet"], "cannot read mesh")  # fmt: skip
    assert line.count("garbage.ply") == 1, line
