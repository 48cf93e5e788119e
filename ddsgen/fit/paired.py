"""``ddsgen fit PRESET REAL_DIR``: fit the sensor to real scans with known poses; judge, report, write the preset.

The frames are split into fit and held-out frames (:func:`~ddsgen.fit.split.split_fit_held_out`); the sensor is fitted
on the fit frames (:func:`~ddsgen.fit.fitting.fit_sensor`), each parameter group whose change does not lower the
held-out gap is reverted (:func:`~ddsgen.fit.revert.revert_unhelpful`), and the report is built beside the preset. The
disparity quantum is measured from the real depth's levels first (:mod:`ddsgen.fit.lattice`) and the fit runs on it. The
fitted preset is written last, inside the report's atomic folder: an interrupted fit leaves neither.
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass
from pathlib import Path

import click
import torch

from ddsgen.atomic import atomic_folder, atomic_write_text
from ddsgen.fit.device_keys import device_key_values
from ddsgen.fit.fit_report import fitted_line, parameter_rows, write_fit_report
from ddsgen.fit.fitted_preset import assemble_preset, sensor_changes, write_preset
from ddsgen.fit.fitting import fit_sensor, refine_frame_poses
from ddsgen.fit.lattice import measure_quantum
from ddsgen.fit.parameters import SENSOR_PARAMS, physical_values, resolve_params
from ddsgen.fit.priors import Priors
from ddsgen.fit.revert import output_holds_fit, param_group, revert_summary, revert_unhelpful, snapshot
from ddsgen.fit.split import SPLIT_MEANING, split_fit_held_out
from ddsgen.fit.uncertainty import estimate_uncertainty
from ddsgen.preset import load_preset
from ddsgen.realscan import inputs
from ddsgen.realscan.gap import gap, write_report
from ddsgen.realscan.losses import FIT_WEIGHTS
from ddsgen.realscan.plane_depth import plane_depth_for
from ddsgen.realscan.plots import plot_residuals
from ddsgen.realscan.simulate import prepare_frames
from ddsgen.sensor.depth_sensor import DepthSensor
from ddsgen.sensor.postprocess import save_postprocess


@dataclass(frozen=True)
class PairedFitSettings:
    """How ``ddsgen fit`` runs (its options; ``--help`` says what each does).

    params: names to fit (:func:`~ddsgen.fit.parameters.resolve_params`); steps, lr, tile_px (0: whole frames),
    prior_mm: Adam's; holdout: fraction held out; search: the 1-D searches and distortion start; keep_all: no revert;
    refine_poses, pose_steps, static_scene, static_views: poses as nuisance parameters; support_plane, crop,
    plausible_px, region, seed: the real-scan options shared with ``compare``.
    """

    params: list[str]
    steps: int = 100
    tile_px: int = 0
    lr: float = 1e-3
    holdout: float = 0.25
    prior_mm: float = 0.1
    search: bool = True
    keep_all: bool = False
    refine_poses: bool = False
    pose_steps: int = 40
    static_scene: bool = False
    static_views: int = 8
    support_plane: bool = True
    crop: bool = False
    plausible_px: float = 2.0
    region: str = "all"
    seed: int = 0


def run_paired_fit(preset: str, real_dir: str | Path, out_path: Path, report: Path, settings: PairedFitSettings,
                   progress: bool = True, echo=None) -> dict:  # fmt: skip
    """Fit ``preset`` to the scans in ``real_dir``; write the fitted preset ``out_path`` and the report folder
    ``report``. Returns the report's ``fit_report.json`` content (gaps in mm, parameter rows, split, revert)."""
    s = settings
    resolve_params(DepthSensor(load_preset(preset)), s.params)  # the names are checked before any work
    original, camera_preset, scans, frames = inputs.load_inputs(
        preset, real_dir, support_plane=s.support_plane, crop=s.crop, plausible_px=s.plausible_px, seed=s.seed,
        progress=progress, echo=echo)  # fmt: skip
    sensor = DepthSensor(camera_preset)
    fit_frames, held, split_kind = split_fit_held_out(frames, s.holdout, s.seed)

    def counted(frames):  # the pixels the fit works on
        return [dataclasses.replace(f, region=f.object_region) for f in frames] if s.region == "objects" else frames

    sets = {"fit": fit_frames, "held-out": held}

    def gaps_now(keep_maps=False):
        return {(which, r): gap(sensor, fs, region=r, seed=s.seed + 1, keep_maps=keep_maps and which == "held-out",
                                noise_floor=False, progress=progress)
                for which, fs in sets.items() for r in ("all", "objects")}  # fmt: skip

    before = gaps_now(keep_maps=True)  # the input preset as it is
    # The disparity quantum is measured from the real depth's levels, not fitted (ddsgen.fit.lattice); the fit runs
    # on the measured lattice and the change is judged on the held-out gap with the rest, below.
    with torch.no_grad():
        quantum = measure_quantum(fit_frames, held, camera_preset.subpixel_level, float(sensor.baseline),
                                  float(sensor.focal_scale)) if s.search else None  # fmt: skip
    if quantum and quantum["changed"]:
        sensor = DepthSensor(camera_preset.replace(subpixel_level=quantum["level"]))
    resolved = resolve_params(sensor, s.params)
    start = snapshot(resolved)
    pose_rounds = []

    def refine_all():  # poses as nuisance parameters, with the sensor as it is now; the same split again
        refined, changes = refine_frame_poses(sensor, camera_preset, scans, s.pose_steps, progress=progress,
                                              seed=s.seed, static_views=s.static_views if s.static_scene else 0,
                                              support_plane=s.support_plane, crop=s.crop,
                                              plausible_px=s.plausible_px)  # fmt: skip
        pose_rounds.append(changes)
        fit_frames, held, _ = split_fit_held_out(refined, s.holdout, s.seed)
        sets.update({"fit": fit_frames, "held-out": held})
        return fit_frames, held

    def prepare_for(current):  # support planes where `current`'s disparity errors put them; the same split
        if not s.support_plane or not current.disparity_effects.effects:
            return sets["fit"], sets["held-out"]
        refreshed = prepare_frames(camera_preset, scans, crop=s.crop, plausible_px=s.plausible_px, seed=s.seed,
                                   plane_depth=plane_depth_for(current))  # fmt: skip
        return split_fit_held_out(refreshed, s.holdout, s.seed)[:2]

    if s.refine_poses:
        fit_frames, held = refine_all()
    fit_on = counted(fit_frames)
    result = fit_sensor(sensor, fit_on, s.params, steps=s.steps, lr=s.lr, progress=progress, seed=s.seed,
                        search=s.search, prior_mm=s.prior_mm, start_effects=s.search, tile_px=s.tile_px or None,
                        weights=FIT_WEIGHTS)  # fmt: skip
    if s.refine_poses:
        fit_frames, held = refine_all()
        fit_on = counted(fit_frames)
    fit_frames, held = prepare_for(sensor)
    sets.update({"fit": fit_frames, "held-out": held})
    fit_on = counted(fit_frames)
    searched = {result.searches.get("snr", {}).get("parameter"), "baseline" if "baseline" in result.searches else None}
    priors = Priors(sensor, {n: SENSOR_PARAMS[n] for n in result.params if n in SENSOR_PARAMS and n not in searched},
                    s.prior_mm)  # fmt: skip
    uncertainty = estimate_uncertainty(sensor, fit_on, result, SENSOR_PARAMS, seed=s.seed, priors=priors,
                                       weights=FIT_WEIGHTS)  # fmt: skip
    if s.keep_all or split_kind == "none":
        outcome = None
        revert_lines = ["--keep-all: every fitted change kept" if s.keep_all else
                        "no held-out frames: every fitted change kept (nothing to judge transfer by)"]  # fmt: skip
    else:
        outcome = revert_unhelpful(sensor, resolved, start, lambda current: prepare_for(current)[1], SENSOR_PARAMS,
                                   region=s.region, seed=s.seed + 1)  # fmt: skip
        fit_frames, held = prepare_for(sensor)
        sets.update({"fit": fit_frames, "held-out": held})
        revert_lines = revert_summary(outcome)
    kept = {n: True if outcome is None else output_holds_fit(outcome, param_group(n, SENSOR_PARAMS))
            for n in result.params}  # fmt: skip
    if quantum and quantum["changed"] and outcome is not None:
        sensor = _judge_quantum(sensor, quantum, lambda current: prepare_for(current)[1], s.region, s.seed + 1)
    after = gaps_now(keep_maps=True)

    # The fitted preset: the user's preset (its camera) with the fitted physical values.
    changes = {**sensor_changes(sensor, original), **device_key_values(sensor, SENSOR_PARAMS)}
    if quantum and quantum["changed"]:
        changes["subpixel_level"] = quantum["level"]
    weights_path = None
    if sensor.postprocess is not None and "cnn" in result.params and kept.get("cnn", True):
        weights_path = out_path.with_name(out_path.stem + ".postprocess.pt")
        changes["postprocess"] = weights_path.name
    fitted = assemble_preset(original, changes, "fitted")

    rows = parameter_rows(physical_values(DepthSensor(camera_preset)), result.after, physical_values(sensor),
                          uncertainty, kept, result.bounds)  # fmt: skip
    held_key = ("held-out", s.region)
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
        "parameters": rows, "revert": outcome, "revert_summary": revert_lines, "disparity_quantum": quantum,
        "fit": result.to_dict(),
    }  # fmt: skip
    if s.refine_poses:
        summary["pose_refinement"] = {"steps": s.pose_steps, "rounds": pose_rounds, "static_scene": s.static_scene,
                                      "static_views": s.static_views if s.static_scene else None}  # fmt: skip
    comment = [f"fitted by ddsgen fit to {real_dir} from {preset}", f"params: {', '.join(s.params)}",
               f"split: {split_kind}; held-out gap ({s.region}) {before[held_key].gap:.2f} -> "
               f"{after[held_key].gap:.2f} mm", *revert_lines,
               *([f"disparity quantum: {quantum['reason']}"] if quantum else []),
               "value +- uncertainty (1 s.d.) of each fitted parameter:"]  # fmt: skip
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
        write_preset(fitted, out_path, "\n".join(comment))
    return summary


def print_summary(summary: dict, report: Path) -> None:
    """The command's closing lines: the split, each gap before/after, the reverts, each parameter, the searches."""
    click.echo(f"split: {summary['split']['kind']} ({summary['split']['meaning']})")
    for g in summary["gaps_mm"]:
        click.echo(f"  {g['frames']:8s} gap, region {g['region']:7s}: {g['before']:.2f} mm -> {g['after']:.2f} mm "
                   f"({g['pixels']:,} px)")  # fmt: skip
    for line in summary["revert_summary"]:
        click.echo(f"  {line}")
    if summary.get("disparity_quantum"):
        click.echo(f"  disparity quantum: {summary['disparity_quantum']['reason']}")
    for r in summary["parameters"]:
        click.echo(f"  {r['key']:24s} {r['before']:.6g} -> fitted {fitted_line(r)}"
                   + ("" if r["kept"] else f" (reverted: keeps {r['after']:.6g})")
                   + (" -- at a bound: the data push beyond the physical range" if r["at_bound"] else ""))  # fmt: skip
    for name, info in summary["fit"]["searches"].items():
        if "method" not in info:  # e.g. a distortion start with no pixels to solve on
            continue
        click.echo(f"  {name}: {info['method']}" + ("" if info.get("accepted", True) else " (not identifiable: kept)"))
    click.echo(f"wrote {summary['fitted_preset']} and {report}/")


#: The measured quantum is kept unless it raises the held-out gap by more than this factor (see _judge_quantum).
QUANTUM_GAP_TOLERANCE = 1.05


def _judge_quantum(sensor, quantum: dict, held_out_for, region: str, seed: int):
    """The fitted ``sensor`` on the measured lattice, or the same sensor on the preset's own lattice when the
    measured one raises the held-out gap by more than QUANTUM_GAP_TOLERANCE (the change is judged with the rest of
    the fit). Updates ``quantum``'s ``changed`` and ``reason``; ``held_out_for(sensor)`` gives the held-out frames
    prepared for a sensor.

    The tolerance: the quantum moves a pixel's depth by at most half a step (1/16 px: 1.5 mm at 1 m), far less than
    what a preset that lacks other device behaviours misses per pixel, so the held-out gap cannot resolve it (the
    real cat from kinect_v1_paper, its objects: 4.02 mm on 1/4 px, 4.11 mm on the measured 1/8); the levels,
    confirmed on held-out pixels, decide unless the gap says clearly otherwise."""
    without = DepthSensor(sensor.to_preset().replace(subpixel_level=quantum["preset_level"]))
    without.postprocess = sensor.postprocess
    with_gap = gap(sensor, held_out_for(sensor), region=region, seed=seed, noise_floor=False, progress=False).gap
    without_gap = gap(without, held_out_for(without), region=region, seed=seed, noise_floor=False,
                      progress=False).gap  # fmt: skip
    if with_gap > QUANTUM_GAP_TOLERANCE * without_gap:
        quantum.update(changed=False, level=quantum["preset_level"],
                       reason=f"{quantum['reason']}; not kept: held-out gap {with_gap:.2f} mm on it, more than "
                              f"{QUANTUM_GAP_TOLERANCE:g} x the {without_gap:.2f} mm on the preset's")  # fmt: skip
        return without
    quantum["reason"] += f"; held-out gap {with_gap:.2f} mm on it, {without_gap:.2f} mm on the preset's"
    return sensor
