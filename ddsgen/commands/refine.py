"""``ddsgen refine``: refine the annotated object poses of real scans against their depth."""

from __future__ import annotations

import click

from ddsgen.commands import REPRODUCIBLE_THREADS_HELP, SEED, threads_option, use_threads
from ddsgen.scene_gradients.refine import RefineSettings
from ddsgen.scene_gradients.refine_folder import run_refine


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
    settings = RefineSettings(steps=steps, recast_every=recast_every, band_m=band_mm / 1000.0, seed=seed,
                              gradient=gradient, edge_weight=edge_weight, holdout_block_px=holdout_block_px)  # fmt: skip
    run_refine(preset, real_dir, out_dir, settings, static_scene=static_scene, static_views=static_views,
               support_plane=not no_plane, progress=not quiet)
