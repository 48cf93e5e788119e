"""``ddsgen refine``: refine the annotated object poses of real scans against their depth."""

from __future__ import annotations

from pathlib import Path

import click

from ddsgen.commands import REPRODUCIBLE_THREADS_HELP, SEED, threads_option, use_threads
from ddsgen.errors import InputError


@click.command("refine")
@click.argument("preset")
@click.argument("real_dir", type=click.Path(exists=True, file_okay=False))
@click.option("--out", "out_dir", type=click.Path(file_okay=False), required=True,
              help="Output folder: the refined poses in the input's layout (BOP: <split>/<scene>/scene_gt.json; "
                   "ddsgen: manifest.jsonl) and report/.")
@click.option("--steps", type=int, default=120, show_default=True,  # = RefineSettings().steps (torch is imported lazily)
              help="Adam steps per frame (the result averages the poses of the last half of them).")
@click.option("--recast-every", type=int, default=5, show_default=True,
              help="Ray-cast again every K steps (visibility, silhouettes and shadows follow the poses).")
@click.option("--band-mm", type=float, default=25.0, show_default=True,
              help="Compare only where the real depth is within this of the rendered one (clutter, occluders).")
@click.option("--gradient", type=click.Choice(["sensor", "geometry"]), default="sensor", show_default=True,
              help="Pose gradient through the IR image and matcher, or the clean depth's (straight-through, faster).")
@click.option("--edge-weight", type=float, default=1.0, show_default=True,
              help="Weight of the depth-edge term (the objects' outlines pulled onto the real depth discontinuities; "
                   "pins in-plane slides and turns depth cannot see). 0: depth only (for simulated scans).")
@click.option("--holdout-block-px", type=int, default=6, show_default=True,
              help="Every other block of this many pixels is held out of the optimiser; an object keeps its refined "
                   "pose only if that lowers its gap there. 0: no hold-out (objects keep their refined poses unless "
                   "the frame's gap rises).")
@click.option("--no-plane", is_flag=True, help="Do not fit and refine a support plane.")
@click.option("--static-scene", is_flag=True,
              help="Frames that show one static scene (BOP: a scene folder; ddsgen: consecutive frames with the same "
                   "objects at the same world poses) are refined together, each object's correction shared by "
                   "all of them: their noise averages out. Objects are matched by their order in each frame.")
@click.option("--static-views", type=int, default=8, show_default=True,
              help="With --static-scene: frames simulated per scene (evenly spaced); the correction they find "
                   "is applied to the scene's other frames too.")
@click.option("--seed", type=SEED, default=0, show_default=True, help="Noise seed of the simulation.")
@threads_option(None, REPRODUCIBLE_THREADS_HELP)
@click.option("--quiet", is_flag=True, help="No progress bars.")
def refine(preset, real_dir, out_dir, steps, recast_every, band_mm, gradient, edge_weight, holdout_block_px, no_plane,
           static_scene, static_views, seed, threads, quiet):  # fmt: skip
    """Refine every annotated object's pose (and the support plane) in REAL_DIR with the sensor PRESET.

    Each frame's objects are moved until the simulated depth matches the real one (Huber loss on the
    pixels where the real depth is within --band-mm of the rendered scene; a real surface more than
    15 mm in front of it is an occluder and pulls nothing) and their outlines lie on the real depth's
    discontinuities (--edge-weight). An object keeps its refined pose only if it lowers its gap on
    held-out pixels (--holdout-block-px), a frame only if it lowers the frame's gap; otherwise the
    start is written and the lines say so. Writes OUT (a new or empty folder, not REAL_DIR)
    with the refined poses in the input's layout, and OUT/report/ (refine_report.json: per-object pose
    change in deg/mm, gap before/after; one PNG per frame: real | before | after).
    """
    from tqdm import tqdm

    from ddsgen.atomic import atomic_folder, check_new_folder
    from ddsgen.io.pose_writer import write_refined_poses
    from ddsgen.io.scanfolder import read_scan_folder
    from ddsgen.preset import load_preset
    from ddsgen.scene_gradients.refine import RefineSettings
    from ddsgen.scene_gradients.report import write_report
    from ddsgen.scene_gradients.scan import refine_scan_frame, refine_static_scan, static_scenes

    use_threads(threads)
    if steps < 0:
        raise click.BadParameter("must be >= 0", param_hint="--steps")
    if recast_every < 1:
        raise click.BadParameter("must be >= 1", param_hint="--recast-every")
    if not band_mm > 0:
        raise click.BadParameter("must be > 0", param_hint="--band-mm")
    if not edge_weight >= 0:
        raise click.BadParameter("must be >= 0", param_hint="--edge-weight")
    if holdout_block_px < 0:
        raise click.BadParameter("must be >= 0", param_hint="--holdout-block-px")
    if static_views < 1:
        raise click.BadParameter("must be >= 1", param_hint="--static-views")
    # Before any work: OUT is a new folder, not the input (whose manifest it would overwrite) nor in it.
    check_new_folder(out_dir, "--out", inputs=(real_dir,))
    base = load_preset(preset)
    frames = read_scan_folder(real_dir)
    if not frames:
        raise InputError(f"{real_dir}: no frames")
    for frame in frames:
        if not frame.objects:
            raise InputError(f"{frame.source_depth_path}: frame {frame.name} lists no objects (nothing to refine)")
    settings = RefineSettings(steps=steps, recast_every=recast_every, band_m=band_mm / 1000.0, seed=seed,
                              gradient=gradient, edge_weight=edge_weight, holdout_block_px=holdout_block_px)  # fmt: skip
    refinements, refined = [], {}
    if static_scene:
        for first, scene_frames in tqdm(static_scenes(frames), desc="scenes", unit="scene", disable=quiet):
            sensor_preset = _camera_preset(base, scene_frames)
            simulated, poses = refine_static_scan(sensor_preset, scene_frames, settings, support_plane=not no_plane,
                                                  progress=not quiet, first_index=first, max_views=static_views)  # fmt: skip
            refinements += simulated
            refined.update(poses)
            for frame in scene_frames:
                frame.release()
    for index, frame in enumerate(tqdm([] if static_scene else frames, desc="frames", unit="frame", disable=quiet)):
        refinements.append(refine_scan_frame(_camera_preset(base, [frame]), frame, index, settings,
                                             support_plane=not no_plane, progress=not quiet))  # fmt: skip
        refined[frame.name] = refinements[-1].refined_poses()
        frame.release()
    out = Path(out_dir)
    with atomic_folder(out, "--out", merge=False) as building:  # OUT appears whole or not at all
        written = write_refined_poses(frames, refined, building, final=out)
        write_report(refinements, building / "report", {"preset": str(preset), "real_dir": str(real_dir),
                     "static_scene": bool(static_scene), "static_views": int(static_views), **{k: v for k, v in vars(settings).items()}})  # fmt: skip
    for r in refinements:
        for change in r.object_changes():
            seen = change.get("visible_fraction_dataset", change.get("visible_fraction_estimated"))
            click.echo(f"{r.name} {change['label']}"
                       + (f" ({100 * seen:.0f} % visible)" if seen is not None else "")
                       + f": moved {change['rotation_deg']:.2f} deg, "
                       f"{change['translation_mm']:.2f} mm; {change['decision']}"
                       + (f"; not determined by the data, kept at the start: {', '.join(change['undetermined'])}"
                          if change.get("undetermined") else ""))  # fmt: skip
        verdict = (f" (optimised {r.result.gap_optimised_mm:.2f} mm, not lower: start poses kept)"
                   if r.result.kept_start else "")  # fmt: skip
        click.echo(f"{r.name}: gap {r.result.gap_before_mm:.2f} mm -> {r.result.gap_after_mm:.2f} mm{verdict}")
    click.echo(f"wrote {', '.join(str(p) for p in written)} and {out / 'report'}/")


def _camera_preset(base, frames):
    """The preset with the frames' camera (one line naming the first frame if it does not fit)."""
    from ddsgen.realscan.inputs import adopt_camera

    try:
        return adopt_camera(base, frames)[0]
    except InputError as error:
        raise InputError(f"{frames[0].source_depth_path}: the scan's camera does not fit the preset: {error}") from None
