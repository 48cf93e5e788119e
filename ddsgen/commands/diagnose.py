"""``ddsgen diagnose``: find the physical effect the sensor model is missing, add it, show the gap shrink."""

from __future__ import annotations

from pathlib import Path

import click

from ddsgen.commands import POSITIVE, SEED, echo_stderr, split_names, threads_option, use_threads
from ddsgen.atomic import check_can_create_folder
from ddsgen.diagnose.config import DiagnoseConfig
from ddsgen.diagnose.device_candidates import BEHAVIOURS
from ddsgen.diagnose.run import run_diagnose
from ddsgen.errors import InputError
from ddsgen.fit import DEFAULT_TILE_PX
from ddsgen.sensor.effects import REGISTRY


@click.command("diagnose")
@click.argument("preset")
@click.argument("real_dir", type=click.Path(exists=True, file_okay=False))
@click.option("--report", "report_dir", type=click.Path(file_okay=False), default="diagnosis", show_default=True,
              help="Folder for diagnosis.json and report.html.")
@click.option("--apply", "apply_path", type=click.Path(dir_okay=False), default=None, metavar="OUT.yaml",
              help="Write the extended preset (fitted base parameters plus the effects found) to OUT.yaml.")
@click.option("--holdout", type=float, default=1.0 / 3.0, show_default="1/3",
              help="Fraction of frames held out: every gap is measured on them.")
@click.option("--steps", type=int, default=15, show_default=True, help="Adam steps of the base fit.")
@click.option("--refit-steps", type=int, default=10, show_default=True,
              help="Adam steps of the refit after each accepted effect.")
@click.option("--tile", "tile_px", type=int, default=DEFAULT_TILE_PX, show_default=True,
              help="Each Adam step of the base fit and the refits simulates a random TILE x TILE window of each fit "
                   "frame, as `ddsgen fit` does (a stochastic gradient at a fraction of the price); 0: whole frames.")
@click.option("--candidates", multiple=True, metavar="NAMES",
              help="Effects to try (comma-separated or repeated). Default: the named library effects except "
                   "disparity_distortion (opt-in: its 3x5 field can absorb an offset, a scale or a lens distortion), "
                   "plus the device behaviours the preset has switched off (edge_keeping_matches, hole_fill, "
                   "narrow_gap_fill, speckle_removal: what a PrimeSense-family device does to its own matches; "
                   "beam_falloff, lens_vignetting: its signal fading towards the corners).")
@click.option("--grid-frames", type=int, default=4, show_default=True,
              help="Fit frames on which each candidate effect's parameters are searched (0: all of them).")
@click.option("--max-effects", type=int, default=4, show_default=True, help="Stop after adding this many effects.")
@click.option("--no-plane", is_flag=True, help="Do not add a RANSAC support plane fitted to the real depth.")
@click.option("--plausible-px", type=POSITIVE, default=2.0, show_default=True,
              help="Compare only where |real - clean| disparity is below this (px), or real is invalid.")
@click.option("--region", type=click.Choice(["all", "objects"]), default="all", show_default=True,
              help="Pixels every gap is measured on: 'all' (every modelled, plausible pixel: the objects and the "
                   "support plane) or 'objects' (the annotated objects only, where unmodelled clutter and a second "
                   "table level cannot enter).")
@click.option("--seed", type=SEED, default=0, show_default=True, help="Noise seed of the simulation and frame split.")
@threads_option(1, "Torch threads. The diagnosis runs many small simulations: on a shared machine one thread per "
                   "process is usually fastest.")
@click.option("--quiet", is_flag=True, help="No progress output.")
def diagnose(preset, real_dir, report_dir, apply_path, holdout, steps, refit_steps, tile_px, candidates, grid_frames,
             max_effects, no_plane, plausible_px, region, seed, threads, quiet):  # fmt: skip
    """Find where the sensor PRESET and the real scans in REAL_DIR disagree and name the missing effect.

    1. fit the base sensor parameters on the fit frames;
    2. analyse the residual (bias and validity) by depth, incidence angle, image radius, row,
       column, distance to depth edges and IR signal;
    3. fit every library effect not yet in the model and measure the held-out gap it removes;
    4. accept the best only if it removes at least 5 % of the held-out gap beyond the change of
       the noise floor and a bootstrap over held-out frames confirms it; add it, refit, repeat;
    5. report residual structure that no effect explains, by axis; when no axis has any but the gap
       is still beyond its noise floor, locate it: the patches of the scene that carry it (outlined
       on the residual map; on a partly modelled real scene, the geometry the model lacks).

    Writes REPORT/diagnosis.json ({baseline_gap, steps: [{effect, params, gap_before, gap_after}],
    final_gap, unexplained: [{axis, strength}], local_patches: null or {patches, share, carried,
    gap_beyond_floor_without, offsets_mm}}, gaps in mm on held-out frames) and
    REPORT/report.html (one sentence per step; residual profiles before/after each step and
    full-resolution residual maps of held-out frames, as PNG files in REPORT/plots/).
    """
    if steps < 0:
        raise click.BadParameter("must be >= 0", param_hint="--steps")
    if refit_steps < 0:
        raise click.BadParameter("must be >= 0", param_hint="--refit-steps")
    if tile_px < 0:
        raise click.BadParameter("must be >= 0", param_hint="--tile")
    if grid_frames < 0:
        raise click.BadParameter("must be >= 0", param_hint="--grid-frames")
    if max_effects < 0:
        raise click.BadParameter("must be >= 0", param_hint="--max-effects")
    if not 0.0 < holdout < 1.0:
        raise click.BadParameter("must be in (0, 1)", param_hint="--holdout")
    if apply_path is not None and Path(apply_path).suffix.lower() not in (".yaml", ".yml"):
        raise InputError(f"--apply: {apply_path}: the extended preset must be a .yaml file")
    # The output locations are checked before any work (a diagnosis takes minutes to hours).
    check_can_create_folder(report_dir, "the report (--report)")
    if apply_path is not None:
        if Path(apply_path).is_dir():
            raise InputError(f"{apply_path}: --apply: is a folder; give the extended preset's .yaml file")
        check_can_create_folder(Path(apply_path).parent, "the extended preset (--apply)")
    names = split_names(candidates)
    unknown = [n for n in names if n not in REGISTRY and n not in BEHAVIOURS]
    if unknown:
        raise InputError(f"--candidates: unknown effect(s) {', '.join(unknown)} "
                         f"(known: {', '.join(sorted(REGISTRY) + sorted(BEHAVIOURS))})")  # fmt: skip

    use_threads(threads)
    config = DiagnoseConfig(holdout=holdout, base_steps=steps, refit_steps=refit_steps, max_steps=max_effects,
                            seed=seed, candidates=tuple(names) or None, grid_frames=grid_frames,
                            tile_px=tile_px or None)  # fmt: skip
    run_diagnose(preset, real_dir, report_dir, config, region=region, support_plane=not no_plane,
                 plausible_px=plausible_px, apply_path=apply_path, progress=not quiet, echo=echo_stderr)
