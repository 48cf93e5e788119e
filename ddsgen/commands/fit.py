"""``ddsgen fit``: fit the sensor's parameters to a folder of real scans."""

from __future__ import annotations

import json
from pathlib import Path

import click

from ddsgen.commands import common_options, echo_stderr, split_names
from ddsgen.fit.inputs import load_inputs
from ddsgen.errors import InputError


@click.command("fit")
@click.argument("preset")
@click.argument("real_dir", type=click.Path(exists=True, file_okay=False))
@click.option("--out", type=click.Path(dir_okay=False), default="fitted.yaml", show_default=True,
              help="Fitted preset (loadable by render). With --params cnn the weights go next to it.")
@click.option("--params", "params", multiple=True, metavar="NAMES",
              help="Parameters to fit (comma-separated or repeated). Default: the paper's four sensor parameters "
                   "emitted_intensity (eta_c), read_noise_std, beta, baseline. Also: focal, speckle_scale, ambient, "
                   "read_noise_mean, effects, effect:NAME[.PARAM], cnn (2-layer post-processing CNN).")
@click.option("--steps", type=int, default=100, show_default=True, help="Adam steps.")
@click.option("--lr", type=float, default=1e-3, show_default=True,
              help="Adam learning rate (CNN weights; log-space sensor parameters use 30 x lr).")
@click.option("--holdout", type=float, default=0.25, show_default=True,
              help="Fraction of frames held out to measure the gap before/after (one frame: it is used for both).")
@click.option("--report", "report_dir", type=click.Path(file_okay=False), default=None,
              help="Report folder (default: OUT without .yaml + _report).")
@click.option("--no-search", is_flag=True, help="Fit eta_c/noise and baseline by Adam too, instead of the 1-D searches.")
@click.option("--refine-poses", is_flag=True,
              help="Poses as nuisance parameters: refine every frame's object poses (ddsgen refine's loop) with the "
                   "current sensor before the fit and again after it; the held-out gap after uses the final poses.")
@click.option("--pose-steps", type=int, default=40, show_default=True, help="Pose-refinement steps per frame and round.")
@click.option("--unpaired", is_flag=True,
              help="REAL_DIR is any folder of depth images (16-bit PNG, EXR in m), no poses: fit the sensor by "
                   "matching distributions of patch features on renders of --scenes (docs/unpaired_fit.md).")
@click.option("--scenes", type=click.Path(dir_okay=False), default=None,
              help="With --unpaired: scene list resembling the real scenes (default: the built-in list).")
@click.option("--depth-scale", type=float, default=0.001, show_default=True,
              help="With --unpaired: metres per PNG unit of the real depth images.")
@common_options
def fit(preset, real_dir, out, params, steps, lr, holdout, report_dir, no_search, refine_poses, pose_steps, unpaired,
        scenes, depth_scale, no_plane, crop, plausible_px, region, seed, quiet):  # fmt: skip
    """Fit the sensor PRESET to the real scans in REAL_DIR and write the fitted preset.

    Frames are split into fit and held-out sets. Adam (Huber + Sobel-gradient + validity
    loss) fits what has a useful gradient (beta, focal, effects, CNN); the IR signal-to-noise
    ratio (only eta_c / noise is identifiable from depth) and the baseline (it cancels from
    z = f b / d except through the disparity quantisation) are found by 1-D searches. Writes
    OUT, and REPORT/fit_report.json, loss_curve.png, residuals.png (held-out, before/after),
    comparison_before/after.json.
    """
    if unpaired:
        from ddsgen.fit.unpaired.run import print_summary, run_unpaired_fit

        content = run_unpaired_fit(preset, real_dir, scenes=scenes, depth_scale=depth_scale, out=out,
                                   report_dir=report_dir, seed=seed, progress=not quiet)  # fmt: skip
        print_summary(content)
        return
    import torch

    from ddsgen.fit.compare import gap, plot_residuals, write_report
    from ddsgen.fit.fitting import DEFAULT_PARAMS, fit_sensor, fitted_preset, refine_frame_poses, resolve_params, split_frames
    from ddsgen.io.atomic import atomic_write_text
    from ddsgen.preset import PATTERN_DIR, save_preset
    from ddsgen.sensor.depth_sensor import DepthSensor
    from ddsgen.sensor.postprocess import save_postprocess

    if steps < 0:
        raise click.BadParameter("must be >= 0", param_hint="--steps")
    if not lr > 0:
        raise click.BadParameter("must be > 0", param_hint="--lr")
    if pose_steps < 0:
        raise click.BadParameter("must be >= 0", param_hint="--pose-steps")
    names = split_names(params) or list(DEFAULT_PARAMS)
    out_path = Path(out)
    if out_path.suffix.lower() not in (".yaml", ".yml"):
        raise InputError(f"--out: {out}: the fitted preset must be a .yaml file")
    report = Path(report_dir) if report_dir else out_path.with_name(out_path.stem + "_report")
    from ddsgen.preset import load_preset

    resolve_params(DepthSensor(load_preset(preset)), names)  # validate names before any work
    original, camera_preset, scans, frames = load_inputs(preset, real_dir, support_plane=not no_plane, crop=crop,
                                                     plausible_px=plausible_px, seed=seed, progress=not quiet, echo=echo_stderr)  # fmt: skip
    sensor = DepthSensor(camera_preset)

    def counted(frames):
        if region == "objects":  # fit on the pixels that count
            import dataclasses

            return [dataclasses.replace(f, region=f.object_region) for f in frames]
        return frames

    frames = counted(frames)
    fit_frames, held = split_frames(frames, holdout, seed)
    progress = not quiet
    before = gap(sensor, held, region=region, seed=seed + 1, keep_maps=True, progress=progress)
    pose_rounds = []

    def refine_all():  # poses as nuisance parameters, with the sensor as it is now
        refined, changes = refine_frame_poses(sensor, camera_preset, scans, pose_steps, progress=progress, seed=seed,
                                              support_plane=not no_plane, crop=crop, plausible_px=plausible_px)  # fmt: skip
        pose_rounds.append(changes)
        return split_frames(counted(refined), holdout, seed)

    if refine_poses:
        fit_frames, held = refine_all()
    result = fit_sensor(sensor, fit_frames, names, steps=steps, lr=lr, progress=progress, seed=seed)
    if refine_poses:
        fit_frames, held = refine_all()
    after = gap(sensor, held, region=region, seed=seed + 1, keep_maps=True, progress=progress)

    # The fitted preset: the user's preset (its camera) with the fitted physical values.
    values = sensor.physical_parameters()
    scale = float(sensor.focal_scale.detach())
    values["focal_px"], values["focal_y_px"] = original.focal_px * scale, original.focal_y_px * scale
    changes = {k: v for k, v in values.items()}
    changes["effects"] = [e.to_entry() for e in sensor.effects]
    pattern_path = original.resolve_path(original.pattern)
    if pattern_path.parent.resolve() != PATTERN_DIR.resolve():
        changes["pattern"] = str(pattern_path.resolve())
    weights_path = None
    if sensor.postprocess is not None and "cnn" in result.params:
        weights_path = out_path.with_name(out_path.stem + ".postprocess.pt")
        changes["postprocess"] = weights_path.name
    elif original.postprocess:
        changes["postprocess"] = str(original.resolve_path(original.postprocess).resolve())
    fitted = original.replace(**changes, name=f"{original.name}_fitted")

    report.mkdir(parents=True, exist_ok=True)
    write_report(before, report, "comparison_before")
    write_report(after, report, "comparison_after")
    plot_residuals([before, after], report / "residuals.png", ["before fit", "after fit"])
    _plot_loss(result.history, report / "loss_curve.png")
    summary = {
        "preset": str(preset), "real_dir": str(real_dir), "fitted_preset": str(out_path),
        "frames": {"fit": [f.name for f in fit_frames], "held_out": [f.name for f in held]},
        "held_out_gap_before": before.gap, "held_out_gap_after": after.gap,
        "noise_floor_before": before.noise_floor, "noise_floor_after": after.noise_floor,
        "fit": result.to_dict(),
    }  # fmt: skip
    if refine_poses:
        summary["pose_refinement"] = {"steps": pose_steps, "rounds": pose_rounds}
    atomic_write_text(report / "fit_report.json", json.dumps(summary, indent=1, default=float) + "\n")
    if weights_path is not None:
        save_postprocess(sensor.postprocess, weights_path)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    save_preset(fitted, out_path, comment=f"fitted by ddsgen fit to {real_dir} from {preset}\nparams: {', '.join(names)}")
    click.echo(f"held-out gap: {before.gap:.2f} mm -> {after.gap:.2f} mm (noise floor {after.noise_floor:.2f} mm) "
               f"on {len(held)} frame(s)")  # fmt: skip
    for key in ("emitted_intensity", "read_noise_std_counts", "softargmax_beta", "baseline_m", "focal_px"):
        click.echo(f"  {key:24s} {result.before[key]:.6g} -> {result.after[key]:.6g}")
    for name, info in result.searches.items():
        click.echo(f"  {name}: {info['method']}" + ("" if info.get("accepted", True) else " (not identifiable: kept)"))
    click.echo(f"wrote {out_path} and {report}/")


def _plot_loss(history: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4), constrained_layout=True)
    if history:
        steps = [h["step"] for h in history]
        for key in ("total", "depth", "gradient", "validity"):
            ax.plot(steps, [h[key] for h in history], label=key)
        ax.legend()
    else:
        ax.text(0.5, 0.5, "no Adam steps (searches only)", ha="center", transform=ax.transAxes)
    ax.set_xlabel("Adam step")
    ax.set_ylabel("loss (mm)")
    fig.savefig(path, dpi=80)
    plt.close(fig)
