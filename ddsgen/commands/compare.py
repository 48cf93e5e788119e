"""``ddsgen compare``: how far is the simulated sensor from a folder of real scans."""

from __future__ import annotations

from pathlib import Path

import click

from ddsgen.commands import common_options, echo_stderr
from ddsgen.errors import InputError


@click.command("compare")
@click.argument("preset")
@click.argument("real_dir", type=click.Path(exists=True, file_okay=False))
@click.option("--report", "report_dir", type=click.Path(file_okay=False), default="compare_report", show_default=True,
              help="Folder for comparison.json, index.html, the plots and frames/ (real | sim | difference).")
@click.option("--save-sim", "save_sim", type=click.Path(file_okay=False), default=None,
              help="Also write the simulated version of every real frame to this new folder, in ddsgen's scan "
                   "layout (manifest.jsonl, depth/ in mm + EXR, clean/, ir/, mask/), in the real folder's order.")
@common_options
def compare(preset, real_dir, report_dir, save_sim, no_plane, crop, plausible_px, region, seed, quiet):
    """Measure the gap between the sensor PRESET and the real scans in REAL_DIR.

    REAL_DIR is a ddsgen scan folder (manifest.jsonl) or a BOP dataset/split/scene folder. Each
    frame's meshes are placed at their ground-truth poses and simulated through the full
    sensor; only pixels where modelled geometry is visible and plausible count.

    The headline gap (mm) = systematic depth error (Huber of the local mean of sim - real over
    1.5 deg of view, 15 px at 640 x 480, where one disparity step is at most a 50 mm depth step:
    nearer than 4.14 m for the Kinect V1) + noise-texture mismatch (|Sobel| roughness per depth
    bin) + validity disagreement (100 mm x squared difference of local valid rates), averaged
    over frames; the noise floor
    is the same metric between the simulation and other units of the simulated sensor (their own
    noise, laser speckle and dot positions: no model can know the real unit's), averaged over at
    least 4 units (one frame: 4 twins). Writes REPORT/comparison.json (gap, noise_floor and the floor
    against each unit, per-frame values, parts binned by depth, incidence
    angle and image radius, validity confusion, and the hole and quantisation statistics of real
    and sim, and local_patches: connected areas where the real depth lies off more than another unit's, with
    the gap and excess without them), full-resolution real | simulated | difference pictures per frame, PNG plots and
    REPORT/index.html showing them all, and prints a short table. With --save-sim DIR the
    simulated frames are also written as a scan folder (readable by compare/fit/diagnose).
    """
    import contextlib

    from ddsgen.realscan.gap import gap, table
    from ddsgen.realscan.inputs import load_inputs
    from ddsgen.realscan.outputs import FrameOutputs
    from ddsgen.realscan.save_sim import SimFolderWriter, check_target
    from ddsgen.atomic import atomic_folder, check_can_create_folder, overlap
    from ddsgen.sensor.depth_sensor import DepthSensor

    # Every output location is checked before any work.
    check_can_create_folder(report_dir, "the report (--report)")
    if save_sim is not None:
        check_target(save_sim, inputs=(real_dir,))
        where = overlap(save_sim, report_dir)
        if where:
            raise InputError(f"{save_sim}: --save-sim: {where} the --report folder {report_dir}; give another folder")
    _, camera_preset, scans, frames = load_inputs(preset, real_dir, support_plane=not no_plane, crop=crop,
                                                  plausible_px=plausible_px, seed=seed, progress=not quiet, echo=echo_stderr)  # fmt: skip
    sensor = DepthSensor(camera_preset).eval()
    title = f"{camera_preset.name} vs {real_dir} ({len(frames)} frame(s))"
    # Both folders are built under temporary names and put in place only once complete: an interrupted run leaves
    # neither. The report goes in first, --save-sim last: a re-run replaces a report but refuses a --save-sim.
    with (SimFolderWriter(save_sim, camera_preset, seed) if save_sim else contextlib.nullcontext()) as writer, \
            atomic_folder(report_dir, "the report (--report)", last="index.html") as building:
        border = camera_preset.block_size_px // 2 + 1 if crop else 0  # as prepare_frame's crop region
        outputs = FrameOutputs(scans, building, region, writer, border, camera_preset.baseline_m)
        report = gap(sensor, frames, region=region, seed=seed, keep_maps=True, progress=not quiet, on_frame=outputs)
        written = [Path(report_dir) / p.relative_to(building) for p in outputs.finish(report, title)]
    click.echo(table(report, title))
    saved = f"; simulated frames in {save_sim}" if save_sim else ""
    click.echo(f"wrote {', '.join(str(p) for p in written)}{saved}")
