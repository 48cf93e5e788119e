"""What ``compare`` makes of each simulated frame besides the gap: statistics, pictures, a saved copy.

:class:`FrameOutputs` is the ``on_frame`` hook of :func:`ddsgen.realscan.gap.gap`: for each
frame it computes the realism statistics of real and sim (:mod:`ddsgen.realscan.realism`), draws the
full-resolution real | simulated | difference picture (:mod:`ddsgen.realscan.pictures`) and
hands the frame to a :class:`~ddsgen.realscan.save_sim.SimFolderWriter` when one is given. Nothing is
kept per frame but a few numbers (the flat residuals by depth go into bounded pools,
:class:`~ddsgen.surface_roughness.FlatRoughnessPool`), so long folders stream. :meth:`FrameOutputs.finish` adds the
statistics to the report and writes ``comparison.json``, the plots and ``index.html``.
"""

from __future__ import annotations

import textwrap
from pathlib import Path

import numpy as np

from ddsgen.realscan import realism
from ddsgen.realscan.gap import region_mask, table, write_report
from ddsgen.realscan.gap_report import region_rule
from ddsgen.realscan.pictures import side_by_side, write_index

FRAMES_FOLDER = "frames"


class FrameOutputs:
    """Per-frame outputs of a compare run.

    Args:
        scans: the real :class:`~ddsgen.io.scan_frame.ScanFrame` list; FrameData ``index`` i is scans[i].
        report_dir: folder the report is written to (pictures go to ``report_dir/frames/NNNNNN.png``); ``compare``
            passes the temporary folder it builds the report in (:func:`ddsgen.atomic.atomic_folder`).
        region: ``"all"`` or ``"objects"`` (the compare region of the statistics and pictures).
        sim_writer: a :class:`~ddsgen.realscan.save_sim.SimFolderWriter` inside its ``with``, or None.
        crop_border_px: with ``--crop``, the crop window's border the matcher cannot reach (see
            :func:`ddsgen.realscan.realism.frame_realism`); 0 without crop.
        baseline_m: the sensor's baseline (the roughness statistics are in its disparity); None: without them.
    """

    def __init__(self, scans, report_dir: str | Path, region: str = "all", sim_writer=None, crop_border_px: int = 0,
                 baseline_m: float | None = None):  # fmt: skip
        self.scans = scans
        self.report_dir = Path(report_dir)
        self.region = region
        self.sim_writer = sim_writer
        self.crop_border_px = int(crop_border_px)
        self.baseline_m = baseline_m
        self.statistics: list[dict] = []
        self.roughness = realism.roughness_pools()
        self.pictures: list[tuple[str, str]] = []

    def __call__(self, frame, sim, patches=None) -> None:
        scan = self.scans[frame.index]
        real = np.asarray(scan.depth, dtype=np.float32)
        real = np.where(np.isfinite(real) & (real > 0), real, 0.0).astype(np.float32)
        # PNG values are rounded to the file's unit; EXR values are not
        resolution = 0.0 if str(scan.source_depth_path).lower().endswith(".exr") else float(scan.depth_scale)
        region = region_mask(frame, self.region).numpy()
        statistics = realism.frame_realism(frame, sim, region, real, resolution, self.crop_border_px, self.baseline_m)
        self.statistics.append(realism.pool_frame_roughness(statistics, self.roughness))
        relative = f"{FRAMES_FOLDER}/{len(self.pictures):06d}.png"
        side_by_side(self.report_dir / relative, f"{frame.name}: real | simulated | difference", real,
                     realism.full_frame(sim.depth.detach().numpy(), frame, 0.0),
                     realism.full_frame(sim.valid.numpy(), frame, False),
                     realism.full_frame(region, frame, False),
                     None if patches is None else realism.full_frame(patches, frame, False))  # fmt: skip
        self.pictures.append((frame.name, relative))
        if self.sim_writer is not None:
            self.sim_writer.add(frame, sim, scan)
        scan.release()

    def finish(self, report, title: str) -> list[Path]:
        """Add the statistics to ``report``; write comparison.json, the plots and index.html. Returns the files."""
        report.realism = realism.aggregate(self.statistics, self.roughness)
        written = write_report(report, self.report_dir)
        plots = [p.relative_to(self.report_dir).as_posix() for p in written[1:]]
        summary = table(report, title) + "\n\n" + textwrap.fill(region_rule(report.region), 110)
        index = write_index(self.report_dir, title, summary, self.pictures, plots)
        return [*written, self.report_dir / FRAMES_FOLDER, index]
