"""``ddsgen fit``: fit the sensor's parameters to a folder of real scans."""

from __future__ import annotations

import json
from pathlib import Path

import click

from ddsgen.commands import (POSITIVE, REPRODUCIBLE_THREADS_HELP, common_options, echo_stderr, split_names,
                             threads_option, use_threads)
from ddsgen.fit import DEFAULT_TILE_PX
from ddsgen.realscan.inputs import load_inputs
from ddsgen.fit.unpaired.parameters import UNPAIRED_PARAMETERS
from ddsgen.errors import InputError
from ddsgen.atomic import atomic_folder, check_can_create_folder


@click.command("fit")
@click.argument("preset")
@click.argument("real_dir", type=click.Path(exists=True, file_okay=False))
@click.option("--out", type=click.Path(dir_okay=False), default="fitted.yaml", show_default=True,
              help="Fitted preset (loadable by render). With --params cnn the weights go next to it.")
@click.option("--params", "params", multiple=True, metavar="NAMES",
              help="Parameters to fit (comma-separated or repeated). Default: the paper's four sensor parameters "
                   "emitted_intensity (eta_c), read_noise_std, beta, baseline. Also: focal, speckle_scale, ambient, "
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
                   "For a preset registered to an RGB camera see --registration.")
@click.option("--scenes", type=click.Path(dir_okay=False), default=None,
              help="With --unpaired: scene list resembling the real scenes (default: the built-in list).")
@click.option("--depth-scale", type=POSITIVE, default=0.001, show_default=True,
              help="With --unpaired: metres per PNG unit of the real depth images.")
@click.option("--registration", type=click.Choice(["auto", "registered", "unregistered"]), default="auto",
              show_default=True,
              help="With --unpaired and a preset whose depth is registered to an RGB camera (kinect_v1): read the "
                   "real depth as registered the same way (its IR frame's border bands measured through the "
                   "registration), as unregistered (the bands measured as they are, registration switched off in "
                   "the fitted preset), or auto: render both at the stock values and take the one whose validity "
                   "by image radius is closer to the real frames'.")
@threads_option(None, REPRODUCIBLE_THREADS_HELP)
@common_options
def fit(preset, real_dir, out, params, steps, tile_px, lr, holdout, report_dir, no_search, prior_mm, keep_all, refine_poses,
        pose_steps, static_scene, static_views, unpaired, scenes, depth_scale, registration, threads, no_plane, crop,
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
    use_threads(threads)
    out_path = Path(out)
    report = Path(report_dir) if report_dir else out_path.with_name(out_path.stem + "_report")
    check_can_create_folder(out_path.parent, "the fitted preset")
    check_can_create_folder(report, "the report")
    if unpaired:
        from ddsgen.fit.unpaired.run import print_summary, run_unpaired_fit

        content = run_unpaired_fit(preset, real_dir, scenes=scenes, depth_scale=depth_scale, out=out,
                                   report_dir=report_dir, seed=seed, keys=split_names(params) or None,
                                   registration=registration, progress=not quiet)  # fmt: skip
        print_summary(content)
        return
    import dataclasses

    from ddsgen.realscan.gap import gap, write_report
    from ddsgen.realscan.plots import plot_residuals
    from ddsgen.fit.device_keys import device_key_values
    from ddsgen.realscan.losses import FIT_WEIGHTS
    from ddsgen.realscan.plane_depth import plane_depth_for
    from ddsgen.realscan.simulate import prepare_frames
    from ddsgen.fit.fit_report import fitted_line, parameter_rows, write_fit_report
    from ddsgen.fit.fitting import fit_sensor, refine_frame_poses
    from ddsgen.fit.parameters import DEFAULT_PARAMS, SENSOR_PARAMS, physical_values, preset_values, resolve_params
    from ddsgen.fit.priors import Priors
    from ddsgen.fit.revert import output_holds_fit, param_group, revert_summary, revert_unhelpful, snapshot
    from ddsgen.fit.split import SPLIT_MEANING, split_fit_held_out
    from ddsgen.fit.uncertainty import estimate_uncertainty
    from ddsgen.atomic import atomic_write_text
    from ddsgen.preset import PATTERN_DIR, load_preset, save_preset
    from ddsgen.sensor.depth_sensor import DepthSensor
    from ddsgen.sensor.postprocess import save_postprocess

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
    names = split_names(params) or list(DEFAULT_PARAMS)
    if out_path.suffix.lower() not in (".yaml", ".yml"):
        raise InputError(f"--out: {out}: the fitted preset must be a .yaml file")
    resolve_params(DepthSensor(load_preset(preset)), names)  # validate names before any work
    original, camera_preset, scans, frames = load_inputs(preset, real_dir, support_plane=not no_plane, crop=crop,
                                                         plausible_px=plausible_px, seed=seed, progress=not quiet,
                                                         echo=echo_stderr)  # fmt: skip
    sensor = DepthSensor(camera_preset)
    fit_frames, held, split_kind = split_fit_held_out(frames, holdout, seed)

    def counted(frames):  # the pixels the fit works on
        return [dataclasses.replace(f, region=f.object_region) for f in frames] if region == "objects" else frames

    progress = not quiet
    resolved = resolve_params(sensor, names)
    start = snapshot(resolved)
    sets = {"fit": fit_frames, "held-out": held}

    def gaps_now(keep_maps=False):
        return {(which, r): gap(sensor, fs, region=r, seed=seed + 1, keep_maps=keep_maps and which == "held-out",
                                noise_floor=False, progress=progress)
                for which, fs in sets.items() for r in ("all", "objects")}  # fmt: skip

    before = gaps_now(keep_maps=True)
    pose_rounds = []

    def refine_all():  # poses as nuisance parameters, with the sensor as it is now; the same split again
        refined, changes = refine_frame_poses(sensor, camera_preset, scans, pose_steps, progress=progress, seed=seed,
                                              static_views=static_views if static_scene else 0,
                                              support_plane=not no_plane, crop=crop, plausible_px=plausible_px)  # fmt: skip
        pose_rounds.append(changes)
        fit_frames, held, _ = split_fit_held_out(refined, holdout, seed)
        sets.update({"fit": fit_frames, "held-out": held})
        return fit_frames, held

    def prepare_for(current):  # support planes where `current`'s disparity errors put them; the same split
        if no_plane or not any(e.stage == "disparity" for e in current.effects):
            return sets["fit"], sets["held-out"]
        refreshed = prepare_frames(camera_preset, scans, crop=crop, plausible_px=plausible_px, seed=seed,
                                   plane_depth=plane_depth_for(current))  # fmt: skip
        return split_fit_held_out(refreshed, holdout, seed)[:2]

    if refine_poses:
        fit_frames, held = refine_all()
    fit_on = counted(fit_frames)
    result = fit_sensor(sensor, fit_on, names, steps=steps, lr=lr, progress=progress, seed=seed,
                        search=not no_search, prior_mm=prior_mm, start_effects=not no_search,
                        tile_px=tile_px or None, weights=FIT_WEIGHTS)  # fmt: skip
    if refine_poses:
        fit_frames, held = refine_all()
        fit_on = counted(fit_frames)
    fit_frames, held = prepare_for(sensor)
    sets.update({"fit": fit_frames, "held-out": held})
    fit_on = counted(fit_frames)
    searched = {result.searches.get("snr", {}).get("parameter"), "baseline" if "baseline" in result.searches else None}
    priors = Priors(sensor, {n: SENSOR_PARAMS[n] for n in result.params if n in SENSOR_PARAMS and n not in searched},
                    prior_mm)  # fmt: skip
    uncertainty = estimate_uncertainty(sensor, fit_on, result, SENSOR_PARAMS, seed=seed, priors=priors,
                                       weights=FIT_WEIGHTS)  # fmt: skip
    if keep_all or split_kind == "none":
        outcome = None
        revert_lines = ["--keep-all: every fitted change kept" if keep_all else
                        "no held-out frames: every fitted change kept (nothing to judge transfer by)"]  # fmt: skip
    else:
        outcome = revert_unhelpful(sensor, resolved, start, lambda current: prepare_for(current)[1], SENSOR_PARAMS,
                                   region=region, seed=seed + 1)  # fmt: skip
        fit_frames, held = prepare_for(sensor)
        sets.update({"fit": fit_frames, "held-out": held})
        revert_lines = revert_summary(outcome)
    kept = {n: True if outcome is None else output_holds_fit(outcome, param_group(n, SENSOR_PARAMS))
            for n in result.params}  # fmt: skip
    after = gaps_now(keep_maps=True)
    final_values = physical_values(sensor)

    # The fitted preset: the user's preset (its camera) with the fitted physical values.
    changes = {**preset_values(sensor, original), **device_key_values(sensor, SENSOR_PARAMS)}
    changes["effects"] = [e.to_entry() for e in sensor.effects]
    pattern_path = original.resolve_path(original.pattern)
    if pattern_path.parent.resolve() != PATTERN_DIR.resolve():
        changes["pattern"] = str(pattern_path.resolve())
    weights_path = None
    if sensor.postprocess is not None and "cnn" in result.params and kept.get("cnn", True):
        weights_path = out_path.with_name(out_path.stem + ".postprocess.pt")
        changes["postprocess"] = weights_path.name
    elif original.postprocess:
        changes["postprocess"] = str(original.resolve_path(original.postprocess).resolve())
    fitted = original.replace(**changes, name=f"{original.name}_fitted")

    rows = parameter_rows(physical_values(DepthSensor(camera_preset)), result.after, final_values, uncertainty, kept, result.bounds)
    held_key = ("held-out", region)
    gap_pairs = {k: (before[k].gap, after[k].gap) for k in before}
    # How many pixels each gap rests on: one frame's halves can put an object almost wholly on one side.
    gap_pixels = {k: sum(frame["pixels"] for frame in after[k].frames) for k in after}
    summary = {
        "preset": str(preset), "real_dir": str(real_dir), "fitted_preset": str(out_path),
        "split": {"kind": split_kind, "meaning": SPLIT_MEANING[split_kind]},
        "frames": {"fit": [f.name for f in fit_frames], "held_out": [f.name for f in held]},
        "held_out_gap_before": before[held_key].gap, "held_out_gap_after": after[held_key].gap,
        "gaps_mm": [{"frames": w, "region": r, "before": b, "after": a, "pixels": gap_pixels[(w, r)]}
                    for (w, r), (b, a) in gap_pairs.items()],
        "parameters": rows, "revert": outcome, "revert_summary": revert_lines,
        "fit": result.to_dict(),
    }  # fmt: skip
    if refine_poses:
        summary["pose_refinement"] = {"steps": pose_steps, "rounds": pose_rounds, "static_scene": bool(static_scene),
                                      "static_views": int(static_views) if static_scene else None}  # fmt: skip
    comment = [f"fitted by ddsgen fit to {real_dir} from {preset}", f"params: {', '.join(names)}",
               f"split: {split_kind}; held-out gap ({region}) {before[held_key].gap:.2f} -> {after[held_key].gap:.2f} mm",
               *revert_lines, "value +- uncertainty (1 s.d.) of each fitted parameter:"]  # fmt: skip
    comment += [f"  {r['key']}: {fitted_line(r)}" + ("" if r["kept"] else
                f" (reverted: the preset keeps the input's {r['after']:.6g})") for r in rows]  # fmt: skip
    # The report is built under a temporary name and put in place once complete, after the preset: an interrupted
    # fit leaves no half-written report (a re-run replaces an earlier one).
    with atomic_folder(report, "the report", last="index.html") as building:
        write_report(before[held_key], building, "comparison_before")
        write_report(after[held_key], building, "comparison_after")
        plot_residuals([before[held_key], after[held_key]], building / "residuals.png", ["before fit", "after fit"])
        write_fit_report(building, title=f"ddsgen fit: {preset} on {real_dir}", rows=rows, gaps=gap_pairs,
                         gap_pixels=gap_pixels, split_kind=split_kind, split_meaning=SPLIT_MEANING[split_kind],
                         revert_lines=revert_lines,
                         history=result.history, before_maps=before[held_key], after_maps=after[held_key])  # fmt: skip
        atomic_write_text(building / "fit_report.json", json.dumps(summary, indent=1, default=float) + "\n")
        if weights_path is not None:
            save_postprocess(sensor.postprocess, weights_path)
        out_path.parent.mkdir(parents=True, exist_ok=True)
        save_preset(fitted, out_path, comment="\n".join(comment))
    click.echo(f"split: {split_kind} ({SPLIT_MEANING[split_kind]})")
    for (which, r), (b, a) in gap_pairs.items():
        click.echo(f"  {which:8s} gap, region {r:7s}: {b:.2f} mm -> {a:.2f} mm ({gap_pixels[(which, r)]:,} px)")
    for line in revert_lines:
        click.echo(f"  {line}")
    for r in rows:
        click.echo(f"  {r['key']:24s} {r['before']:.6g} -> fitted {fitted_line(r)}"
                   + ("" if r["kept"] else f" (reverted: keeps {r['after']:.6g})")
                   + (" -- at a bound: the data push beyond the physical range" if r["at_bound"] else ""))  # fmt: skip
    for name, info in result.searches.items():
        if "method" not in info:  # e.g. a distortion start with no pixels to solve on
            continue
        click.echo(f"  {name}: {info['method']}" + ("" if info.get("accepted", True) else " (not identifiable: kept)"))
    click.echo(f"wrote {out_path} and {report}/")
