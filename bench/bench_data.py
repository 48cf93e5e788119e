"""Training-data benchmark: frames/s that ddsgen.data delivers through a torch DataLoader with 2 workers.

Prints `bench: NAME VALUE UNIT` lines:
  data_fps_folder_2workers   kinect_v1 frames/s read from a rendered folder (ScanFolderDataset: depth EXR, clean
                             EXR, IR PNG, mask, labels -> tensors), batch 8 with collate_frames (target >= 8)
  data_fps_online_2workers   kinect_v1 frames/s rendered on the fly in the workers (RenderedFrames), steady state

The folder is rendered first (--workers 2, not timed). Each rate is timed from the end of the first round of batches
(one per worker) to the last, so worker start-up (and torch.compile in the online case) is left out. DDSGEN_BENCH_FRAMES sets the frame
count (default 64) for a quick smoke run.
"""

from __future__ import annotations

import os
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from torch.utils.data import DataLoader  # noqa: E402

from ddsgen.data import RenderedFrames, ScanFolderDataset, collate_frames  # noqa: E402
from ddsgen.runner import render_dataset  # noqa: E402

PRESET = "kinect_v1"
FRAMES = int(os.environ.get("DDSGEN_BENCH_FRAMES", "64"))
BATCH = 8
WORKERS = 2


def timed_rate(loader: DataLoader) -> float:
    """Frames/s from the end of the first round of batches (one per worker) to the end of the last batch.

    The workers batch in parallel, so their first batches arrive together; after that every worker is busy all
    the time (the loop only counts), which is the steady state a training loop that keeps up would see.
    """
    start, seen, counted = None, 0, 0
    for batch in loader:
        seen += 1
        if seen == WORKERS:
            start = time.perf_counter()
        elif seen > WORKERS:
            counted += len(batch["frame"])
    return counted / max(time.perf_counter() - start, 1e-9) if counted else float("nan")


def main() -> None:
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "out"
        render_dataset(PRESET, None, FRAMES, str(out), workers=WORKERS, seed=1, progress=False)
        loader = DataLoader(ScanFolderDataset(out), batch_size=BATCH, num_workers=WORKERS, collate_fn=collate_frames)
        print(f"bench: data_fps_folder_2workers {timed_rate(loader):.2f} frames/s", flush=True)
    online = RenderedFrames(PRESET, FRAMES, seed=1)
    loader = DataLoader(online, batch_size=BATCH, num_workers=WORKERS, collate_fn=collate_frames)
    print(f"bench: data_fps_online_2workers {timed_rate(loader):.2f} frames/s", flush=True)


if __name__ == "__main__":
    main()
