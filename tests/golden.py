"""Fingerprints of what the commands write, for the golden test (``tests/test_golden.py``).

A fingerprint is a plain dict: SHA-256 digests of every image a render writes with each shipped preset, and the
headline numbers compare, fit and diagnose print for the shared real LineMOD cat frame. The golden file
``tests/golden_fingerprints.json`` holds them as measured on the code as it was before a behaviour-preserving
restructure; the test recomputes them and wants them equal. Run ``python tests/golden.py --write`` to record them
again after a change meant to alter what the commands write (and say why in the commit).

Every command runs in its own process with one torch thread, so the numbers do not depend on the test runner.
"""

from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys
from pathlib import Path

GOLDEN_FILE = Path(__file__).with_name("golden_fingerprints.json")
SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
CAT_FRAME = SHARED_DATA / "linemod_bop" / "test" / "000006"
SHIPPED_PRESETS = ("kinect_v1", "kinect_v1_paper", "matterport_pro2")
IMAGE_FOLDERS = ("depth", "clean", "ir", "mask")


def run_ddsgen(args: list[str], cwd: Path) -> None:
    """``ddsgen ARGS`` in a child process with one torch thread; raises with its stderr on failure."""
    env = dict(os.environ, OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
    code = "import sys; from ddsgen.cli import entry_point; sys.argv = ['ddsgen', *sys.argv[1:]]; entry_point()"
    result = subprocess.run([sys.executable, "-c", code, *args], cwd=cwd, env=env, capture_output=True, text=True)
    if result.returncode != 0:
        raise RuntimeError(f"ddsgen {' '.join(args)} exited {result.returncode}: {result.stderr[-2000:]}")


def render_fingerprints(work: Path) -> dict[str, str]:
    """{preset/folder/file: sha256} of two frames rendered with each shipped preset (default scenes, seed 5)."""
    digests = {}
    for preset in SHIPPED_PRESETS:
        out = work / f"render_{preset}"
        run_ddsgen(["render", preset, "-n", "2", "--out", str(out), "--workers", "1", "--seed", "5", "--quiet"], work)
        for folder in IMAGE_FOLDERS:
            for path in sorted((out / folder).iterdir()):
                digests[f"{preset}/{folder}/{path.name}"] = hashlib.sha256(path.read_bytes()).hexdigest()
    return digests


def real_frame_fingerprints(work: Path) -> dict:
    """compare (both regions), a short fit and a short diagnosis of the real cat frame: their headline numbers."""
    out: dict = {}
    cat = str(CAT_FRAME)
    for region in ("all", "objects"):
        report = work / f"compare_{region}"
        run_ddsgen(["compare", "kinect_v1", cat, "--report", str(report), "--region", region, "--quiet"], work)
        summary = json.loads((report / "comparison.json").read_text())
        out[f"compare_{region}"] = {key: summary[key] for key in ("gap", "noise_floor", "excess")}
    fitted, report = work / "fitted.yaml", work / "fit_report"
    run_ddsgen(["fit", "kinect_v1_paper", cat, "--steps", "6", "--out", str(fitted), "--report", str(report),
                "--quiet", "--threads", "1"], work)  # fmt: skip
    lines = [line for line in fitted.read_text().splitlines() if line and not line.startswith("#")]
    out["fit_preset"] = dict(line.split(": ", 1) for line in lines)
    out["fit_gaps"] = json.loads((report / "fit_report.json").read_text())["gaps_mm"]
    report = work / "diagnose_report"
    run_ddsgen(["diagnose", "kinect_v1_paper", cat, "--steps", "2", "--refit-steps", "0", "--candidates",
                "edge_keeping_matches,disparity_offset", "--max-effects", "1", "--report", str(report), "--quiet",
                "--threads", "1", "--region", "objects"], work)  # fmt: skip
    diagnosis = json.loads((report / "diagnosis.json").read_text())
    out["diagnose"] = {key: diagnosis[key] for key in ("baseline_gap", "steps", "final_gap", "unexplained")}
    return out


if __name__ == "__main__":
    import tempfile

    if "--write" not in sys.argv:
        sys.exit("usage: python tests/golden.py --write   (records tests/golden_fingerprints.json)")
    with tempfile.TemporaryDirectory() as tmp:
        prints = {"render": render_fingerprints(Path(tmp))}
        if CAT_FRAME.is_dir():
            prints["real"] = real_frame_fingerprints(Path(tmp))
    GOLDEN_FILE.write_text(json.dumps(prints, indent=1, sort_keys=True) + "\n")
    print(f"wrote {GOLDEN_FILE}")
