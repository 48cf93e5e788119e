"""`make bench`: run every bench/bench_*.py and print their `bench: NAME VALUE UNIT` lines.

Each benchmark runs in its own process (so peak-memory figures are its own) and
measures its references (e.g. OpenCV StereoBM) in the same run, so the ratios
are comparable across machines. bench_realism.py prints issue 12's hole, validity and quantisation
statistics of real frames (../shared/data) next to the kinect_v1 preset's simulation of them.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent


def main() -> int:
    failures = 0
    for script in sorted(HERE.glob("bench_*.py")):
        print(f"# {script.name}", flush=True)
        result = subprocess.run([sys.executable, str(script)], cwd=HERE.parent)
        if result.returncode != 0:
            print(f"# {script.name} failed with exit code {result.returncode}", flush=True)
            failures += 1
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
