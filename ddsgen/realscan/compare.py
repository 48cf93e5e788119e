"""``ddsgen compare PRESET REAL_DIR``: simulate every real frame, measure the gap, write the report (and the
simulated frames as a scan folder)."""

from __future__ import annotations

import contextlib
from pathlib import Path

import click

from ddsgen.atomic import atomic_folder, check_can_create_folder, overlap
from ddsgen.errors import InputError
from ddsgen.realscan import inputs
from ddsgen.realscan.gap import gap, table
from ddsgen.realscan.outputs import FrameOutputs
from ddsgen.realscan.save_sim import SimFolderWriter, check_target
from ddsgen.sensor.depth_sensor import DepthSensor


def run_compare(preset: str, real_dir: str | Path, report_dir: str | Path, save_sim: str | Path | None = None, *,
                support_plane: bool = True, crop: bool = False, plausible_px: float = 2.0, region: str = "all",
                seed: int = 0, progress: bool = True, echo=None) -> list[Path]:  # fmt: skip
    """Compare ``preset`` with the scans in ``real_dir``: write REPORT (and the simulated frames to ``save_sim``),
    print the gap table; returns the report's files. Every output location is checked before any work."""
    check_can_create_folder(report_dir, "the report (--report)")
    if save_sim is not None:
        check_target(save_sim, inputs=(real_dir,))
        where = overlap(save_sim, report_dir)
        if where:
            raise InputError(f"{save_sim}: --save-sim: {where} the --report folder {report_dir}; give another folder")
    _, camera_preset, scans, frames = inputs.load_inputs(preset, real_dir, support_plane=support_plane, crop=crop,
                                                         plausible_px=plausible_px, seed=seed, progress=progress,
                                                         echo=echo)  # fmt: skip
    sensor = DepthSensor(camera_preset).eval()
    title = f"{camera_preset.name} vs {real_dir} ({len(frames)} frame(s))"
    # Both folders are built under temporary names and put in place only once complete: an interrupted run leaves
    # neither. The report goes in first, --save-sim last: a re-run replaces a report but refuses a --save-sim.
    with (SimFolderWriter(save_sim, camera_preset, seed) if save_sim else contextlib.nullcontext()) as writer, \
            atomic_folder(report_dir, "the report (--report)", last="index.html") as building:
        border = camera_preset.block_size_px // 2 + 1 if crop else 0  # as prepare_frame's crop region
        outputs = FrameOutputs(scans, building, region, writer, border, camera_preset.baseline_m)
        report = gap(sensor, frames, region=region, seed=seed, keep_maps=True, progress=progress, on_frame=outputs)
        written = [Path(report_dir) / p.relative_to(building) for p in outputs.finish(report, title)]
    click.echo(table(report, title))
    saved = f"; simulated frames in {save_sim}" if save_sim else ""
    click.echo(f"wrote {', '.join(str(p) for p in written)}{saved}")
    return written
