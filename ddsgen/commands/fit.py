"""``ddsgen fit``: fit the sensor's parameters to a folder of real scans."""

from __future__ import annotations

from pathlib import Path

import click

from ddsgen.commands import (POSITIVE, REPRODUCIBLE_THREADS_HELP, common_options, echo_stderr, split_names,
                             threads_option, use_threads)
from ddsgen.atomic import check_can_create_folder
from ddsgen.errors import InputError
from ddsgen.fit import DEFAULT_TILE_PX
from ddsgen.fit.paired import PairedFitSettings, print_summary, run_paired_fit
from ddsgen.fit.parameters import COMMAND_DEFAULT_PARAMS
from ddsgen.fit.unpaired.parameters import UNPAIRED_PARAMETERS
from ddsgen.fit.unpaired.run import print_summary as print_unpaired_summary
from ddsgen.fit.unpaired.run import run_unpaired_fit
from ddsgen.realscan.folder_camera import FolderCamera, folder_camera
from ddsgen.realscan.realfolder import DEFAULT_DEPTH_SCALE_M


@click.command("fit")
@click.argument("preset")
@click.argument("real_dir", type=click.Path(exists=True, file_okay=False))
@click.option("--out", type=click.Path(dir_okay=False), default="fitted.yaml", show_default=True,
              help="Fitted preset (loadable by render). With --params cnn the weights go next to it.")
@click.option("--params", "params", multiple=True, metavar="NAMES",
              help="Parameters to fit (comma-separated or repeated). Default: the paper's four sensor parameters "
                   "emitted_intensity (eta_c), read_noise_std, beta, baseline, and the device's edge rule and "
                   "clean-up confirmed_match, cleanup_fill_width, cleanup_hole, cleanup_speckle (1-D searches, each "
                   "group kept only if it lowers the held-out gap). Also: focal, speckle_scale, ambient, "
                   "read_noise_mean; the device keys projector_falloff, vignetting, speckle_grain, speckle_shape, "
                   "shot_noise_gain, cleanup_speckle, cleanup_hole, cleanup_max_diff, cleanup_fill_width, confirmed_match "
                   "(1-D searches); effects, "
                   "effect:NAME[.PARAM], cnn (2-layer post-processing CNN). With --unpaired: the preset keys "
                   f"{', '.join(UNPAIRED_PARAMETERS)} (default: all of them).")
@click.option("--steps", type=int, default=100, show_default=True, help="Adam steps.")
@click.option("--tile", "tile_px", type=int, default=DEFAULT_TILE_PX, show_default=True,
              help="Each Adam step simulates a random TILE x TILE window of each fit frame (a stochastic gradient "
                   "at a fraction of the price); 0: whole frames.")
@click.option("--lr", type=float, default=1e-3, show_default=True,
              help="Adam learning rate (CNN weights; log-space sensor parameters use 30 x lr).")
@click.option("--holdout", type=float, default=0.25, show_default=True,
              help="Fraction of scenes held out (one scene: of frames; one frame: half its region is held out; "
                   "0: measure in-sample).")
@click.option("--report", "report_dir", type=click.Path(file_okay=False), default=None,
              help="Report folder: index.html with held-out real | sim | difference pictures before/after, loss "
                   "curve, parameter table with uncertainties (default: OUT without .yaml + _report).")
@click.option("--no-search", is_flag=True,
              help="Fit eta_c/noise and baseline by Adam too, instead of the 1-D searches (and no least-squares "
                   "start of a disparity_distortion grid).")
@click.option("--prior", "prior_mm", type=float, default=0.1, show_default=True,
              help="Weight (mm) of the regulariser toward the input preset, per prior width squared; 0: bounds only.")
@click.option("--keep-all", is_flag=True,
              help="Keep every fitted change (default: revert groups that do not lower the held-out gap).")
@click.option("--refine-poses", is_flag=True,
              help="Poses as nuisance parameters: refine every frame's object poses (ddsgen refine's loop) with the "
                   "current sensor before the fit and again after it; the held-out gap after uses the final poses.")
@click.option("--pose-steps", type=int, default=40, show_default=True,
              help="Pose-refinement steps per frame (per static scene with --static-scene) and round.")
@click.option("--static-scene", is_flag=True,
              help="With --refine-poses: the frames of one static scene (BOP: a scene folder; ddsgen: consecutive "
                   "frames with the same objects at the same world poses) share one pose correction per object, "
                   "refined on all of them together (ddsgen refine --static-scene): several views average out what "
                   "one frame's noise leaves in a pose.")
@click.option("--static-views", type=int, default=8, show_default=True,
              help="With --static-scene: frames simulated per scene and round (evenly spaced); their correction is "
                   "applied to every frame of the scene.")
@click.option("--unpaired", is_flag=True,
              help="REAL_DIR is any folder of depth images (16-bit PNG, EXR in m), no poses: fit the sensor by "
                   "matching distributions of patch features on renders of --scenes (docs/validation.md). "
                   "The output window (border columns/rows empty in every frame) is measured from the folder: "
                   "give frames of varied views, or a camera that always sees nothing at one border gets a band. "
                   "Each value is reported with the range that fits as well against the scene content of the fit "
                   "scenes; where PRESET's value is in that range it is kept. "
                   "The frames are held out by sequence (the first folder below REAL_DIR; one sequence: every other "
                   "frame): the fit sees only its part, and the fitted preset is written only if it is closer than "
                   "PRESET to the held-out frames, else PRESET's values are written unchanged (one frame: always). "
                   "For a preset registered to an RGB camera see --registration.")
@click.option("--scenes", type=click.Path(dir_okay=False), default=None,
              help="With --unpaired: scene list resembling the real scenes (default: the built-in list).")
@click.option("--depth-scale", type=POSITIVE, default=None,
              help="With --unpaired: metres per PNG unit of the real depth images [default: a BOP camera file's "
                   "depth_scale (see --camera), else 0.001].")
@click.option("--registration", type=click.Choice(["auto", "registered", "unregistered"]), default="auto",
              show_default=True,
              help="With --unpaired and a preset whose depth is registered to an RGB camera (kinect_v1): read the "
                   "real depth as registered the same way (its IR frame's border bands measured through the "
                   "registration), as unregistered (the bands measured as they are, registration switched off in "
                   "the fitted preset), or auto: render both at the stock values and take the one whose validity "
                   "by image radius is closer to the real frames'.")
@click.option("--camera", default=None, metavar="FX,FY,CX,CY|FILE.json",
              help="With --unpaired: the real frames' camera, focal lengths and principal point in px of the frames' "
                   "own size, for a device whose optics differ from PRESET's (e.g. an Asus Xtion in cropped mode, "
                   "f ~ 1066 px at 640x480); or a BOP camera.json / scene_camera.json holding it. Without it a BOP "
                   "camera file in REAL_DIR (or scene_camera.json in its sequence folders) is used, else PRESET's "
                   "camera. The fit renders with it and the written preset keeps it.")
@threads_option(None, REPRODUCIBLE_THREADS_HELP)
@common_options
def fit(preset, real_dir, out, params, steps, tile_px, lr, holdout, report_dir, no_search, prior_mm, keep_all, refine_poses,
        pose_steps, static_scene, static_views, unpaired, scenes, depth_scale, registration, camera, threads, no_plane,
        crop,
        plausible_px, region, seed, quiet):  # fmt: skip
    """Fit the sensor PRESET to the real scans in REAL_DIR and write the fitted preset.

    Whole scenes are held out (frames when there is one scene, half the region when there is
    one frame). Adam (Huber + Sobel-gradient + validity loss, plus a prior toward PRESET)
    fits what has a useful gradient (beta, focal, effects, CNN) within physical bounds; the IR
    signal-to-noise ratio (only eta_c / noise is identifiable from depth) and the baseline (it
    cancels from z = f b / d except through the disparity quantisation) are found by 1-D
    searches. Each parameter gets an uncertainty; parameter groups whose change does not lower
    the held-out gap are reverted to PRESET's values. Writes OUT (values and uncertainties in
    its comments) and REPORT/ (index.html, fit_report.json, parameters.txt, gaps.txt,
    loss_curve.png, residuals.png, frames/).
    """
    out_path = Path(out)
    report = Path(report_dir) if report_dir else out_path.with_name(out_path.stem + "_report")
    if steps < 0:
        raise click.BadParameter("must be >= 0", param_hint="--steps")
    if tile_px < 0:
        raise click.BadParameter("must be >= 0", param_hint="--tile")
    if not lr > 0:
        raise click.BadParameter("must be > 0", param_hint="--lr")
    if not prior_mm >= 0:
        raise click.BadParameter("must be >= 0", param_hint="--prior")
    if not 0.0 <= holdout < 1.0:
        raise InputError(f"--holdout: must be in [0, 1), got {holdout}")
    if pose_steps < 0:
        raise click.BadParameter("must be >= 0", param_hint="--pose-steps")
    if static_scene and not refine_poses:
        raise click.BadParameter("needs --refine-poses (it says how the poses are refined)", param_hint="--static-scene")
    if static_views < 1:
        raise click.BadParameter("must be >= 1", param_hint="--static-views")
    if out_path.suffix.lower() not in (".yaml", ".yml"):
        raise InputError(f"--out: {out}: the fitted preset must be a .yaml file")
    if camera is not None and not unpaired:
        raise click.BadParameter("is for --unpaired (a paired fit reads the camera of the scans)",
                                 param_hint="--camera")
    folder = folder_camera(camera, real_dir) if unpaired else FolderCamera()
    if depth_scale is None:
        depth_scale = folder.depth_scale_m or DEFAULT_DEPTH_SCALE_M
    check_can_create_folder(out_path.parent, "the fitted preset")
    check_can_create_folder(report, "the report")
    use_threads(threads)
    if unpaired:
        content = run_unpaired_fit(preset, real_dir, scenes=scenes, depth_scale=depth_scale, out=out,
                                   report_dir=report_dir, seed=seed, keys=split_names(params) or None,
                                   registration=registration, camera=folder.intrinsics, camera_source=folder.source,
                                   progress=not quiet)  # fmt: skip
        print_unpaired_summary(content)
        return
    settings = PairedFitSettings(params=split_names(params) or list(COMMAND_DEFAULT_PARAMS), steps=steps, tile_px=tile_px,
                                 lr=lr, holdout=holdout, prior_mm=prior_mm, search=not no_search, keep_all=keep_all,
                                 refine_poses=refine_poses, pose_steps=pose_steps, static_scene=static_scene,
                                 static_views=static_views, support_plane=not no_plane, crop=crop,
                                 plausible_px=plausible_px, region=region, seed=seed)  # fmt: skip
    summary = run_paired_fit(preset, real_dir, out_path, report, settings, progress=not quiet, echo=echo_stderr)
    print_summary(summary, report)
