"""``ddsgen compare``: how far is the simulated sensor from a folder of real scans."""

from __future__ import annotations

from pathlib import Path

import click

from ddsgen.errors import InputError


def adopt_camera(preset, scan_frames):
    """The preset with the scans' camera when they differ (image size, focal length, principal point).

    The simulation must see the real images' pixels, and the sensor sizes its disparity search
    from the preset's focal length. Frames must share one image size.
    """
    sizes = {(f.intrinsics.width, f.intrinsics.height) for f in scan_frames}
    if len(sizes) > 1:
        raise InputError(f"{scan_frames[0].source_depth_path}: frames have different image sizes {sorted(sizes)}; "
                         f"compare/fit them separately")  # fmt: skip
    c = scan_frames[0].intrinsics
    p = preset
    same = ((c.width, c.height) == (p.width_px, p.height_px) and abs(c.fx - p.focal_px) <= 0.01 * p.focal_px
            and abs(c.fy - p.focal_y_px) <= 0.01 * p.focal_y_px)  # fmt: skip
    if same:
        return preset, False
    try:
        return preset.replace(width_px=c.width, height_px=c.height, focal_px=c.fx, focal_y_px=c.fy, cx_px=c.cx,
                              cy_px=c.cy), True  # fmt: skip
    except InputError as error:
        raise InputError(f"{scan_frames[0].source_depth_path}: the scans' camera does not fit the preset: {error}") from None


def load_inputs(preset_path, real_dir, *, support_plane=True, crop=False, plausible_px=2.0, seed=0, progress=True):
    """(original preset, preset with the scans' camera, scan frames, prepared FrameData list)."""
    from ddsgen.fit.simulate import prepare_frames
    from ddsgen.io.scanfolder import read_scan_folder
    from ddsgen.preset import load_preset

    preset = load_preset(preset_path)
    scans = read_scan_folder(real_dir)
    if not scans:
        raise InputError(f"{real_dir}: no frames")
    camera_preset, adopted = adopt_camera(preset, scans)
    if adopted and progress:
        c = scans[0].intrinsics
        click.echo(f"using the scans' camera ({c.width}x{c.height} px, fx {c.fx:.2f} px) instead of the preset's", err=True)
    frames = prepare_frames(camera_preset, scans, support_plane=support_plane, crop=crop, plausible_px=plausible_px,
                            seed=seed, progress=progress)  # fmt: skip
    return preset, camera_preset, scans, frames


def common_options(f):
    f = click.option("--no-plane", is_flag=True, help="Do not add a RANSAC support plane fitted to the real depth.")(f)
    f = click.option("--crop", is_flag=True, help="Simulate only a box around the objects (faster; exact: a "
                     "sub-window of a pinhole image is a pinhole image).")(f)  # fmt: skip
    f = click.option("--plausible-px", type=float, default=2.0, show_default=True,
                     help="Compare only where |real - clean| disparity is below this (px), or real is invalid.")(f)
    f = click.option("--region", type=click.Choice(["all", "objects"]), default="all", show_default=True,
                     help="Pixels that count: every modelled surface, or only the objects'.")(f)
    f = click.option("--seed", type=int, default=0, show_default=True, help="Noise seed of the simulation.")(f)
    f = click.option("--quiet", is_flag=True, help="No progress bars.")(f)
    return f


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
    1.5 deg of view, 15 px at 640 x 480) + noise-texture mismatch (|Sobel| roughness per depth
    bin) + validity disagreement (100 mm x squared difference of local valid rates), averaged
    over frames; the noise floor
    is the same metric between two noise draws of the simulated sensor. Writes
    REPORT/comparison.json (gap, noise_floor, per-frame values, parts binned by depth, incidence
    angle and image radius, validity confusion, and the hole and quantisation statistics of real
    and sim), full-resolution real | simulated | difference pictures per frame, PNG plots and
    REPORT/index.html showing them all, and prints a short table. With --save-sim DIR the
    simulated frames are also written as a scan folder (readable by compare/fit/diagnose).
    """
    import contextlib

    from ddsgen.fit.compare import gap, table
    from ddsgen.fit.compare_outputs import FrameOutputs
    from ddsgen.fit.save_sim import SimFolderWriter, check_target
    from ddsgen.sensor.depth_sensor import DepthSensor

    if save_sim is not None:
        check_target(save_sim)  # before any work
        if Path(save_sim).resolve() == Path(report_dir).resolve():
            raise InputError(f"{save_sim}: --save-sim: must differ from the --report folder")
    _, camera_preset, scans, frames = load_inputs(preset, real_dir, support_plane=not no_plane, crop=crop,
                                                  plausible_px=plausible_px, seed=seed, progress=not quiet)  # fmt: skip
    sensor = DepthSensor(camera_preset).eval()
    title = f"{camera_preset.name} vs {real_dir} ({len(frames)} frame(s))"
    with SimFolderWriter(save_sim, camera_preset, seed) if save_sim else contextlib.nullcontext() as writer:
        border = camera_preset.block_size_px // 2 + 1 if crop else 0  # as prepare_frame's crop region
        outputs = FrameOutputs(scans, Path(report_dir), region, writer, border)
        report = gap(sensor, frames, region=region, seed=seed, keep_maps=True, progress=not quiet, on_frame=outputs)
    written = outputs.finish(report, title)
    click.echo(table(report, title))
    saved = f"; simulated frames in {save_sim}" if save_sim else ""
    click.echo(f"wrote {', '.join(str(p) for p in written)}{saved}")
