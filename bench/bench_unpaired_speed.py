"""Issue 17's speed target: `fit --unpaired` on a 20-frame 640x480 folder in at most 10 minutes on 2 cores.

The folder: 20 depth PNGs of a device unlike the stock kinect_v1 (another disparity lattice, SNR and
confidence threshold; scene list A of the hidden-device bench), written by ``render``. The fit: the stock
kinect_v1 on the built-in scene list, every table key, the default 8 fit frames and 200 bootstrap
resamples, as the command runs it. Prints ``bench: unpaired_20_frames_seconds S`` and its ratio to
the 600 s target, and the frames rendered (the cost driver: the real frames only add features).
"""

from __future__ import annotations

import shutil
import sys
import tempfile
import time
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

TARGET_S = 600.0
FRAMES = 20


def main() -> None:
    from unpaired_hidden_device import scene_list_a

    from ddsgen.fit.unpaired.run import run_unpaired_fit
    from ddsgen.preset import load_preset, save_preset
    from ddsgen.runner import render_dataset

    work = Path(tempfile.mkdtemp(prefix="ddsgen_unpaired_speed_"))
    try:
        device = load_preset("kinect_v1").replace(subpixel_level=2, emitted_intensity=4.0e6, min_confidence=0.2,
                                                  name="device")  # fmt: skip
        save_preset(device, work / "device.yaml")
        (work / "scenes_a.yaml").write_text(yaml.safe_dump(scene_list_a()))
        render_dataset(str(work / "device.yaml"), str(work / "scenes_a.yaml"), FRAMES, str(work / "scans"), seed=3,
                       progress=False)  # fmt: skip
        real = work / "real"
        real.mkdir()
        for png in sorted((work / "scans" / "depth").glob("*.png")):
            shutil.copy(png, real / png.name)
        start = time.perf_counter()
        content = run_unpaired_fit("kinect_v1", real, out=work / "fitted.yaml", progress=False)
        seconds = time.perf_counter() - start
        print(f"bench: unpaired_20_frames_seconds {seconds:.1f} s (target {TARGET_S:.0f} s: ratio "
              f"{seconds / TARGET_S:.2f}) frames_rendered {content['frames_rendered']}", flush=True)  # fmt: skip
    finally:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
