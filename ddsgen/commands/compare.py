"""``ddsgen compare``: how far is the simulated sensor from a folder of real scans."""

from __future__ import annotations

import click

from ddsgen.commands import common_options, echo_stderr
from ddsgen.realscan.compare import run_compare


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
    run_compare(preset, real_dir, report_dir, save_sim, support_plane=not no_plane, crop=crop,
                plausible_px=plausible_px, region=region, seed=seed, progress=not quiet, echo=echo_stderr)
