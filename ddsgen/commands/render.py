"""``ddsgen render``: generate a labelled synthetic depth dataset."""

from __future__ import annotations

from pathlib import Path

import click

from ddsgen.commands import SEED
from ddsgen.preview import write_preview
from ddsgen.runner import render_dataset


@click.command("render")
@click.argument("preset")
@click.option("--scenes", type=click.Path(dir_okay=False), default=None,
              help="Scene list YAML (meshes, clutter, camera sampling). Default: the built-in scene list "
                   "(4-12 procedural shapes on a table, camera 0.7-1.6 m away; needs no files).")
@click.option("-n", "--frames", "n", type=int, default=10, show_default=True, help="Number of frames in the dataset.")
@click.option("--out", type=click.Path(file_okay=False), default="out", show_default=True,
              help="Output folder. Re-running into the same folder resumes: finished frames are skipped.")
@click.option("--workers", type=int, default=1, show_default=True,
              help="Local worker processes. The output does not depend on it (same seed, same bytes).")
@click.option("--seed", type=SEED, default=0, show_default=True,
              help="Dataset seed: frame i depends only on (seed, i).")
@click.option("--scheduler", default=None, metavar="ADDR",
              help="Address of a Dask scheduler (tcp://HOST:PORT) to render on a cluster (needs ddsgen[dask] on the "
                   "client and the workers, and an --out folder every worker reaches under the same path). Start "
                   "workers with one thread each: dask worker ADDR --nworkers K --nthreads 1.")
@click.option("--batch-size", type=int, default=1, show_default=True, help="Frames per task sent to a worker.")
@click.option("--format", "output_format", type=click.Choice(["ddsgen", "bop"]), default="ddsgen", show_default=True,
              help="Output layout: ddsgen's (manifest.jsonl, EXR/PNG) or BOP's (models/, camera.json, "
                   "train_pbr/SCENE/{scene_camera,scene_gt,scene_gt_info}.json, depth/, mask_visib/; the ddsgen "
                   "render is kept in OUT/ddsgen/).")
@click.option("--camera", default=None, metavar="FX,FY,CX,CY",
              help="Camera intrinsics (px) overriding the preset's focal_px, focal_y_px, cx_px and cy_px, e.g. a "
                   "real device's calibration (LineMOD: 572.41,573.57,325.26,242.05). fx is also the projector's "
                   "focal length (disparity = fx x baseline / depth). Recorded in the manifest's intrinsics.")
@click.option("--models", "models_dir", type=click.Path(file_okay=False), default=None, metavar="DIR",
              help="Folder where mesh files the scene list names but that are not at their path are looked up by "
                   "file name (default: the environment variable DDSGEN_MODELS).")
@click.option("--no-preview", is_flag=True,
              help="Do not write OUT/preview.png (a contact sheet of the dataset, as `ddsgen preview OUT` draws it).")
@click.option("--quiet", is_flag=True, help="No progress bar and no summary.")
def render(preset, scenes, n, out, workers, seed, scheduler, batch_size, output_format, camera, models_dir, no_preview,
           quiet):  # fmt: skip
    """Render N frames with the sensor PRESET (a preset YAML file or a shipped name such as kinect_v1).

    Writes, per frame, depth as float32 EXR (metres) and 16-bit PNG (millimetres, 0 = invalid),
    the clean depth (EXR), the simulated IR image (8-bit PNG, auto-exposed per frame and
    square-root encoded: counts = ir_white_counts x (PNG / 255) ** ir_gamma, both in the
    record), the instance mask (16-bit PNG, 0 = background), and one JSON line in
    OUT/manifest.jsonl with intrinsics, camera pose and per-object class, obj_id, class_id, pose,
    bounding box and visible fraction; OUT/classes.json is the class table (obj_id, class, mesh);
    OUT/sensor.yaml holds the resolved preset. When the render completes,
    OUT/preview.png shows a few frames (see `ddsgen preview`).
    """
    if batch_size < 1:
        raise click.BadParameter("must be >= 1", param_hint="--batch-size")
    summary = render_dataset(preset, scenes, n, out, workers=workers, seed=seed, scheduler=scheduler,
                             progress=not quiet, batch_size=batch_size, output_format=output_format, camera=camera,
                             models_dir=models_dir)  # fmt: skip
    sheet = None
    if not no_preview and summary.frames_total > 0:
        # Drawn from the finished folder (not part of the manifest's frames): a resumed render redraws it.
        sheet, _ = write_preview(summary.out, Path(out) / "preview.png")
    if not quiet:
        rate = f"{summary.frames_per_second:.2f} frames/s" if summary.frames_rendered else "nothing to do"
        click.echo(
            f"rendered {summary.frames_rendered} frame(s) ({summary.frames_skipped} already done) of "
            f"{summary.frames_total} in {summary.seconds:.1f} s ({rate}) -> {summary.out}/manifest.jsonl"
        )
        if output_format == "bop":
            click.echo(f"BOP dataset: {out}/ (camera.json, models/, train_pbr/)")
        if sheet is not None:
            click.echo(f"contact sheet: {sheet}")
