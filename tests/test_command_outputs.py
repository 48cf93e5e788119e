"""Where the real-scan commands write, and what an interrupted run leaves behind.

The contract (README "Guarantees"): an output location that cannot be written, or that would overwrite the input,
is one line ``ddsgen: error: ...`` and exit 2 before any work; a report folder, a ``compare --save-sim`` folder and
a ``refine --out`` folder appear only complete, so a run interrupted by Ctrl-C (exit 130) leaves none of them
half-written and a re-run works. The interrupts are made deterministic by raising KeyboardInterrupt (what Python
raises on SIGINT) from a function the command calls while it writes.

Small and fast: test_compare's 160 x 120 Kinect-like preset, two rendered frames.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from torch_threads import torch_threads
from ddsgen.cli import main
from test_compare import render, write_presets


@pytest.fixture(scope="module")
def small(tmp_path_factory):
    with torch_threads(2):
        root = tmp_path_factory.mktemp("outputs")
        paths = write_presets(root)
        paths["real"] = render(paths["stock"], paths["scenes"], root / "real", 2)
        yield paths


@pytest.fixture
def no_work(monkeypatch):
    """Make the first step of real work fail loudly: a check that passes it came too late."""

    def work_started(*args, **kwargs):
        raise AssertionError("the command started its work before checking its outputs")

    import ddsgen.realscan.inputs
    import ddsgen.scene_gradients.scan

    monkeypatch.setattr(ddsgen.realscan.inputs, "load_inputs", work_started)
    monkeypatch.setattr(ddsgen.scene_gradients.scan, "refine_scan_frame", work_started)
    monkeypatch.setattr(ddsgen.scene_gradients.scan, "refine_static_scan", work_started)


def one_error_line(capsys) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("ddsgen: error:"), err
    return err[0]


def leftovers(folder: Path) -> list[str]:
    """Hidden temporary folders the atomic writers left (there must be none)."""
    return sorted(p.name for p in folder.rglob(".*") if p.name.endswith(".partial") or ".replaced." in p.name)


# ---------------------------------------------------------------------------------- output paths checked up front


def test_output_paths_under_a_file_are_refused_before_any_work(small, tmp_path, capsys, no_work):
    afile = tmp_path / "afile"
    afile.write_text("not a folder")
    stock, real = str(small["stock"]), str(small["real"])
    report = tmp_path / "d"

    # diagnose --apply under a file: names --apply and says the parent is a file; the report is not written
    assert main(["diagnose", stock, real, "--report", str(report), "--apply", str(afile / "out.yaml"), "--quiet"]) == 2
    line = one_error_line(capsys)
    assert "--apply" in line and f"{afile} is a file" in line
    assert not report.exists()
    # diagnose --apply that is a folder
    (tmp_path / "folder.yaml").mkdir()
    assert main(["diagnose", stock, real, "--report", str(report), "--apply", str(tmp_path / "folder.yaml")]) == 2
    assert "--apply" in one_error_line(capsys) and not report.exists()
    # every --report under a file
    for args in (["diagnose", stock, real], ["compare", stock, real],
                 ["compare", stock, real, "--save-sim", str(tmp_path / "sim")]):  # fmt: skip
        assert main([*args, "--report", str(afile / "rep"), "--quiet"]) == 2, args
        line = one_error_line(capsys)
        assert "--report" in line and f"{afile} is a file" in line, line
    # refine --out under a file
    assert main(["refine", stock, real, "--out", str(afile / "rf"), "--steps", "2", "--quiet"]) == 2
    line = one_error_line(capsys)
    assert "--out" in line and f"{afile} is a file" in line
    assert afile.read_text() == "not a folder" and not (tmp_path / "sim").exists()
    assert leftovers(tmp_path) == []


def test_refine_refuses_its_input_and_non_empty_folders_before_any_work(small, tmp_path, capsys, no_work):
    scans = tmp_path / "in"
    shutil.copytree(small["real"], scans)
    manifest = (scans / "manifest.jsonl").read_text()
    busy = tmp_path / "busy"
    busy.mkdir()
    (busy / "notes.txt").write_text("mine")
    cases = {
        str(scans): "is the input folder",
        str(scans / "refined"): "is inside the input folder",
        str(tmp_path): "holds the input folder",
        str(busy): "folder is not empty",
    }
    for out, words in cases.items():
        assert main(["refine", str(small["stock"]), str(scans), "--out", out, "--steps", "2", "--quiet"]) == 2, out
        line = one_error_line(capsys)
        assert "--out" in line and words in line, line
    assert (scans / "manifest.jsonl").read_text() == manifest  # the ground-truth poses are untouched
    assert not (scans / "refined").exists() and (busy / "notes.txt").read_text() == "mine"


def test_refine_writes_a_new_folder_whole_and_an_interrupted_refine_leaves_none(small, tmp_path, capsys, monkeypatch):
    import ddsgen.scene_gradients.report
    from ddsgen.io.scanfolder import read_scan_folder

    out = tmp_path / "new" / "refined"
    args = ["refine", str(small["stock"]), str(small["real"]), "--out", str(out), "--steps", "1", "--recast-every",
            "1", "--quiet"]  # fmt: skip
    original = ddsgen.scene_gradients.report.save_side_by_side

    def interrupted(*a, **k):  # the manifest is written; the report's first picture is being drawn
        raise KeyboardInterrupt

    monkeypatch.setattr(ddsgen.scene_gradients.report, "save_side_by_side", interrupted)
    assert main(args) == 130
    assert not out.exists() and not (tmp_path / "new").exists() and leftovers(tmp_path) == []
    monkeypatch.setattr(ddsgen.scene_gradients.report, "save_side_by_side", original)
    assert main(args) == 0  # the re-run is not refused
    refined = read_scan_folder(out)  # the manifest's paths lead back to the source files from OUT itself
    assert len(refined) == 2 and refined[0].depth.shape == (120, 160)
    assert (out / "report" / "refine_report.json").is_file() and leftovers(tmp_path) == []
    # an existing empty folder is a new folder
    empty = tmp_path / "empty"
    empty.mkdir()
    assert main([*args[:4], str(empty), *args[5:]]) == 0 and (empty / "manifest.jsonl").is_file()


# ---------------------------------------------------------------------------------- interrupted reports


def test_interrupted_compare_leaves_no_report_nor_save_sim_and_reruns(small, tmp_path, capsys, monkeypatch):
    import ddsgen.realscan.outputs

    report, saved = tmp_path / "o" / "r", tmp_path / "o" / "s"
    args = ["compare", str(small["stock"]), str(small["real"]), "--report", str(report), "--save-sim", str(saved),
            "--quiet"]  # fmt: skip
    original = ddsgen.realscan.outputs.write_index

    def interrupted(*a, **k):  # every frame, comparison.json and the plots are written; the index page is next
        raise KeyboardInterrupt

    monkeypatch.setattr(ddsgen.realscan.outputs, "write_index", interrupted)
    capsys.readouterr()
    assert main(args) == 130
    assert capsys.readouterr().err == "ddsgen: interrupted\n"  # one line; compare starts again, it does not resume
    assert not report.exists() and not saved.exists() and leftovers(tmp_path) == []
    monkeypatch.setattr(ddsgen.realscan.outputs, "write_index", original)
    assert main(args) == 0  # not refused: "--save-sim: folder is not empty"
    assert (report / "index.html").is_file() and (saved / "manifest.jsonl").is_file()
    assert len(json.loads((report / "comparison.json").read_text())["frames"]) == 2
    assert sorted(p.name for p in (report / "frames").iterdir()) == ["000000.png", "000001.png"]
    assert "wrote " + str(report / "comparison.json") in capsys.readouterr().out  # the final paths are printed

    # Re-run into the complete report, interrupted while simulating the second frame: the earlier report stays
    # whole; a finished re-run replaces it (the user's own files in the folder stay).
    (report / "notes.txt").write_text("mine")
    before = (report / "comparison.json").read_text()
    calls = []
    original_call = ddsgen.realscan.outputs.FrameOutputs.__call__

    def second_frame_interrupted(self, *a, **k):
        calls.append(1)
        if len(calls) == 2:
            raise KeyboardInterrupt
        return original_call(self, *a, **k)

    monkeypatch.setattr(ddsgen.realscan.outputs.FrameOutputs, "__call__", second_frame_interrupted)
    rerun = ["compare", str(small["stock"]), str(small["real"]), "--report", str(report), "--quiet", "--seed", "1"]
    assert main(rerun) == 130
    assert (report / "comparison.json").read_text() == before and (report / "index.html").is_file()
    assert sorted(p.name for p in (report / "frames").iterdir()) == ["000000.png", "000001.png"]
    monkeypatch.setattr(ddsgen.realscan.outputs.FrameOutputs, "__call__", original_call)
    assert main(rerun) == 0
    assert (report / "comparison.json").read_text() != before  # another seed: another gap
    assert (report / "notes.txt").read_text() == "mine" and (report / "index.html").is_file()
    assert leftovers(tmp_path) == []


def test_interrupted_fit_leaves_no_report_nor_preset_and_reruns(small, tmp_path, monkeypatch):
    import ddsgen.fit.paired

    out = tmp_path / "fitted.yaml"
    report = tmp_path / "fitted_report"
    args = ["fit", str(small["stock"]), str(small["real"]), "--out", str(out), "--params", "beta", "--steps", "1",
            "--no-search", "--holdout", "0", "--quiet"]  # fmt: skip
    original = ddsgen.fit.paired.write_fit_report

    def interrupted(folder, **kwargs):  # comparison_before/after.json and residuals.png are written by now
        assert (Path(folder) / "comparison_before.json").is_file()
        raise KeyboardInterrupt

    monkeypatch.setattr(ddsgen.fit.paired, "write_fit_report", interrupted)
    assert main(args) == 130
    assert not report.exists() and not out.exists() and leftovers(tmp_path) == []
    monkeypatch.setattr(ddsgen.fit.paired, "write_fit_report", original)
    assert main(args) == 0
    assert out.is_file() and (report / "index.html").is_file() and (report / "fit_report.json").is_file()
    assert (report / "comparison_before.json").is_file() and leftovers(tmp_path) == []


def test_an_interrupted_diagnosis_report_leaves_no_folder(tmp_path, monkeypatch):
    """write_diagnosis builds the report whole or not at all; a report written twice is replaced (the same
    function the command calls, with a stand-in diagnosis: the command's own run is test_diagnose's)."""
    import ddsgen.diagnose.report as report_module

    class Stub:
        """What the report's writer reads of a diagnosis that found nothing: its gaps and no steps."""

        fit_frames, held_frames, steps, rounds, unexplained, maps_baseline, maps_final = [1], [2], [], [], [], [], []
        baseline = final = type("Gap", (), {"gap": 3.0, "floor": 1.0, "floor_draws": 4})()
        baseline_gap = final_gap = 2.0
        local = None
        analysis_baseline = analysis_final = {}

        def to_dict(self):
            return {"baseline_gap": self.baseline_gap}

    monkeypatch.setattr(report_module, "strengths_figure", lambda before, after, path: report_module._save(
        report_module._figure(100, 100), path))  # fmt: skip
    original = report_module.write_html

    def interrupted(*a, **k):  # diagnosis.json and the plots are written; report.html is next
        raise KeyboardInterrupt

    folder = tmp_path / "diagnosis"
    monkeypatch.setattr(report_module, "write_html", interrupted)
    with pytest.raises(KeyboardInterrupt):
        report_module.write_diagnosis(Stub(), folder, "title")
    assert not folder.exists() and leftovers(tmp_path) == []
    monkeypatch.setattr(report_module, "write_html", original)
    written = report_module.write_diagnosis(Stub(), folder, "title")
    assert written == [folder / "diagnosis.json", folder / "report.html"]
    assert all(p.is_file() for p in written) and (folder / "plots" / "structure_per_axis.png").is_file()
    assert leftovers(tmp_path) == []


# ---------------------------------------------------------------------------------- the folder writer itself


def test_atomic_folder_puts_a_folder_in_place_whole_or_leaves_everything_as_it_was(tmp_path):
    from ddsgen.errors import InputError
    from ddsgen.atomic import atomic_folder

    target = tmp_path / "a" / "b" / "report"
    with pytest.raises(KeyboardInterrupt):
        with atomic_folder(target, "the report") as building:
            (building / "half.json").write_text("{}")
            raise KeyboardInterrupt
    assert not (tmp_path / "a").exists()  # nor the parent folders made for it
    with atomic_folder(target, "the report") as building:
        (building / "frames").mkdir()
        (building / "frames" / "0.png").write_text("old")
        (building / "index.html").write_text("old")
    (target / "notes.txt").write_text("mine")
    with atomic_folder(target, "the report", last="index.html") as building:
        (building / "frames").mkdir()
        (building / "frames" / "1.png").write_text("new")
        (building / "index.html").write_text("new")
    assert sorted(p.name for p in target.iterdir()) == ["frames", "index.html", "notes.txt"]
    assert [p.name for p in (target / "frames").iterdir()] == ["1.png"] and (target / "index.html").read_text() == "new"
    with pytest.raises(InputError, match="give a new folder"):
        with atomic_folder(target, "--out", merge=False):
            pass
    assert (target / "notes.txt").read_text() == "mine" and leftovers(tmp_path) == []


KILLED_MID_BUILD = """
import sys, time
from ddsgen.atomic import atomic_folder
with atomic_folder(sys.argv[1], "the report") as building:
    (building / "half.json").write_text("{}")
    print("building", flush=True)
    time.sleep(120)
"""


def test_the_folder_a_killed_process_was_building_is_removed_by_the_next_run(tmp_path):
    """SIGKILL leaves no chance to clean up: the next build of the same folder removes the hidden folder of the dead
    process, and leaves those of a live process and of another host alone."""
    import os
    import signal
    import subprocess
    import sys

    from ddsgen.atomic import _HOST, atomic_folder

    target = tmp_path / "report"
    killed = subprocess.Popen([sys.executable, "-c", KILLED_MID_BUILD, str(target)], stdout=subprocess.PIPE, text=True)
    assert killed.stdout.readline() == "building\n"
    os.kill(killed.pid, signal.SIGKILL)
    killed.wait()
    left = leftovers(tmp_path)
    assert len(left) == 1 and left[0].startswith(f".report.{_HOST}-{killed.pid}."), left
    alive = tmp_path / f".report.{_HOST}-{os.getpid()}.x1.partial"  # this process: still building it
    elsewhere = tmp_path / f".report.otherhost-{killed.pid}.x2.partial"  # the same pid on another host
    alive.mkdir(), elsewhere.mkdir()
    with atomic_folder(target, "the report") as building:
        (building / "index.html").write_text("whole")
    assert leftovers(tmp_path) == sorted([alive.name, elsewhere.name])
    assert [p.name for p in target.iterdir()] == ["index.html"]


@pytest.mark.parametrize("signal_name", ["SIGINT", "SIGTERM"])
def test_a_ctrl_c_while_the_folder_is_put_in_place_waits_for_the_renames(signal_name, tmp_path, monkeypatch):
    """SIGINT, or SIGTERM under the CLI's handler, arriving between the renames of a merge is acted on once the
    folder is whole."""
    import contextlib
    import os
    import signal

    from ddsgen.cli import _sigterm_raises
    from ddsgen.atomic import atomic_folder

    target = tmp_path / "report"
    target.mkdir()
    (target / "frames").mkdir()
    (target / "index.html").write_text("old")
    rename = Path.rename

    def rename_then_ctrl_c(self, to):
        result = rename(self, to)
        os.kill(os.getpid(), getattr(signal, signal_name))  # delivered at once to this (the main) thread
        return result

    handling = _sigterm_raises() if signal_name == "SIGTERM" else contextlib.nullcontext()
    # Ctrl-C as Python's own, whatever the process started with: a suite started in the background of a shell
    # without job control inherits SIGINT ignored, and an ignored signal is not deferred or raised
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        with pytest.raises(KeyboardInterrupt), handling:
            with atomic_folder(target, "the report", last="index.html") as building:
                (building / "frames").mkdir()
                (building / "frames" / "0.png").write_text("new")
                (building / "index.html").write_text("new")
                monkeypatch.setattr(Path, "rename", rename_then_ctrl_c)
    finally:
        signal.signal(signal.SIGINT, previous)
    monkeypatch.undo()
    assert (target / "index.html").read_text() == "new" and (target / "frames" / "0.png").read_text() == "new"
    assert leftovers(tmp_path) == []
