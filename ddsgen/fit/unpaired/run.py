"""``ddsgen fit PRESET REAL_DIR --unpaired``: read, split, fit, judge on held-out frames, report, write the preset.

Inputs are checked before any rendering (bad input -> InputError, nothing written). The real frames are split by
sequence (:mod:`.holdout`); the fit sees only its part, and the fitted preset is written only if it is closer than the
input to the held-out frames -- otherwise the input's values are written, and the summary says so. The preset is
written last, after the report.
"""

from __future__ import annotations

import math
from pathlib import Path

import click

from ddsgen.atomic import atomic_folder
from ddsgen.errors import InputError
from ddsgen.fit.fitted_preset import assemble_preset, write_preset
from ddsgen.fit.unpaired.device_window import UNREGISTERED, choose_window_model
from ddsgen.fit.unpaired.features import frame_features, pool
from ddsgen.fit.unpaired.holdout import GROUPS, HOLDOUT_MEANING, judge, split_frames
from ddsgen.fit.unpaired.parameters import UNPAIRED_PARAMETERS
from ddsgen.fit.unpaired.report import write_report
from ddsgen.fit.unpaired.search import (
    camera_for,
    cast_scenes,
    fit_unpaired,
    render_depths,
)
from ddsgen.preset import load_preset
from ddsgen.runner import apply_camera
from ddsgen.realscan.pictures import write_index
from ddsgen.realscan.realfolder import DEFAULT_DEPTH_SCALE_M, read_depth_folder, round_like
from ddsgen.scene.scenelist import load_scene_list

#: Frames of the scene list rendered per evaluation.
DEFAULT_SIM_FRAMES = 8


def run_unpaired_fit(preset_ref: str, real_dir: str | Path, *, scenes: str | Path | None = None,
                     depth_scale: float = DEFAULT_DEPTH_SCALE_M, out: str | Path = "fitted.yaml",
                     report_dir: str | Path | None = None,
                     seed: int = 0, sim_frames: int = DEFAULT_SIM_FRAMES, bootstrap: int = 200, keys=None,
                     registration: str = "auto", camera=None, camera_source: str | None = None,
                     progress: bool = True) -> dict:  # fmt: skip
    """Fit the preset to the real depth frames below ``real_dir``; write OUT and the report.

    ``keys``: fit only these keys of the table (default: all; see :mod:`.parameters`); another name is an
    InputError, raised before anything is read or rendered.
    ``registration``: how to read the frames' depth (:data:`~.device_window.READINGS`; "auto" measures it).
    ``camera``: (fx, fy, cx, cy) px of the real frames' size, replacing the preset's camera scaled to that size
    (:func:`ddsgen.runner.apply_camera`); the written preset keeps it, in its own pixels. ``camera_source``: where
    it came from (:func:`ddsgen.realscan.folder_camera.folder_camera`), for the summary.
    Returns the report's JSON content.
    """
    out = Path(out)
    if out.suffix.lower() not in (".yaml", ".yml"):
        raise InputError(f"--out: {out}: the fitted preset must be a .yaml file")
    if sim_frames < 2:
        raise InputError(f"--sim-frames: {sim_frames}: need at least 2 frames")
    unknown = [key for key in keys or () if key not in UNPAIRED_PARAMETERS]
    if unknown:
        raise InputError(f"--params: {unknown[0]!r} is not fitted by --unpaired "
                         f"(it fits {', '.join(UNPAIRED_PARAMETERS)})")  # fmt: skip
    report = Path(report_dir) if report_dir else out.with_name(out.stem + "_report")
    original = load_preset(preset_ref)
    scene_list = load_scene_list(scenes)
    real = read_depth_folder(real_dir, depth_scale)

    height, width = real[0].depth.shape
    # The device's output window is measured, not searched: border columns/rows without depth in every real
    # frame; read through the preset's registration or without it, whichever renders closer (device_window.py).
    stock_camera = apply_camera(camera_for(original, width, height), camera)
    if camera is not None:  # the user's camera is the input from here on: kept whichever preset is written
        original = original.replace(**_intrinsics(camera_for(stock_camera, original.width_px, original.height_px)))
    # The real frames' features once: the window choice, the fit and the report compare against them (the
    # candidates differ in window and registration, not in f b).
    fb = stock_camera.focal_px * stock_camera.baseline_m
    real_features = [frame_features(f.depth, fb) for f in real]
    fit_indices, held_indices, holdout_kind = split_frames([f.name for f in real], seed)
    fit_real, fit_features = [real[i] for i in fit_indices], [real_features[i] for i in fit_indices]
    model, candidates = choose_window_model(stock_camera, fit_real, scene_list, sim_frames, seed, progress,
                                            reading=registration, real_features=fit_features)  # fmt: skip
    resolution = max(f.resolution_m for f in real)

    def fit_reading(reading):
        """The keys fitted on the fit frames read ``reading``'s way, and fresh renders of them (noise the fit did not
        use): (result, depths, features)."""
        fitted = fit_unpaired(reading.camera, fit_real, reading.geometries, seed=seed, bootstrap=bootstrap, keys=keys,
                              real_features=fit_features, progress=progress)  # fmt: skip
        rendered = [round_like(d, resolution)
                    for d in render_depths(reading.camera.replace(**fitted.after), reading.geometries, seed + 1)]
        return fitted, rendered, [frame_features(d, fb) for d in rendered]

    result, fitted_depths, fitted_features = fit_reading(model)
    work = {"seconds": result.seconds, "frames_rendered": result.frames_rendered}  # of every fit run
    # The stock preset as it is (its own window and registration, so its own ray casts).
    stock_keys = {key: getattr(stock_camera, key) for key in UNREGISTERED}
    stock_reading = next((m for m in candidates if m.registration_keys == stock_keys), None)
    stock_geometries = stock_reading.geometries if stock_reading is not None else None
    if stock_geometries is None:  # --registration unregistered with a registered preset
        stock_geometries = cast_scenes(stock_camera, scene_list, sim_frames, seed)
    stock_depths = [round_like(d, resolution) for d in render_depths(stock_camera, stock_geometries, seed + 1)]
    depths = {"real": [f.depth for f in real], "stock": stock_depths, "fitted": fitted_depths}
    rendered_features = {"stock": [frame_features(d, fb) for d in depths["stock"]], "fitted": fitted_features}
    # The judgement: the held-out real frames against fresh renders of the input and of the fitted preset.
    held_features = [real_features[i] for i in held_indices]
    verdict = judge(held_features, rendered_features["stock"], rendered_features["fitted"], seed=seed)
    # The registration reading is a change like any other. The fit frames choose one (device_window.py); a reading
    # other than the input's is written only if the held-out frames confirm it. The keys are fitted under the input's
    # reading too, since values fitted under a wrong reading compensate for it (a hidden registered device fitted
    # read unregistered: beta 4.9 for 16, paired gap 1.6x the stock's once read registered again). The fit frames'
    # reading is kept only if its fit renders closer to the held-out frames than the input reading's fit by more
    # than the total's spread, and no feature group is farther beyond its own: unpaired features tell the readings
    # apart weakly (on hidden devices each set of frames alone chose wrongly once in three, and once both chose the
    # unregistered reading of a registered device by less than the spread). (An explicit --registration is the
    # user's: one reading, not judged.)
    structure = {"chosen": model.name}
    if stock_reading is not None and stock_reading is not model and held_features:
        input_result, input_depths, input_features = fit_reading(stock_reading)
        work = {key: value + getattr(input_result, key) for key, value in work.items()}
        as_input = judge(held_features, rendered_features["stock"], input_features, seed=seed)
        readings = judge(held_features, input_features, rendered_features["fitted"], seed=seed)  # input's -> fit's
        structure.update(fit_choice=model.name, heldout={model.name: verdict["fitted"],
                                                         stock_reading.name: as_input["fitted"]},
                         groups=readings["groups"], farther=readings["farther"])  # fmt: skip
        if not (readings["fitted_better"] and readings["groups"]["total"] == "closer"):  # the input's reading
            result, depths["fitted"], rendered_features["fitted"], verdict = (input_result, input_depths,
                                                                              input_features, as_input)  # fmt: skip
            model = stock_reading
            structure["chosen"] = model.name
    camera, window = model.camera, model.window.as_keys()
    pooled = {"real": pool(real_features), **{label: pool(f) for label, f in rendered_features.items()}}
    verdict.update(kind=holdout_kind, meaning=HOLDOUT_MEANING[holdout_kind],
                   fit_frames=[real[i].name for i in fit_indices], held_out_frames=[real[i].name for i in held_indices])
    content = {
        "preset": str(preset_ref), "real_dir": str(real_dir), "fitted_preset": str(out), "report": str(report),
        "scenes": str(scenes) if scenes else "built-in default", "real_frames": [f.name for f in real],
        "depth_scale_m": depth_scale,
        "assumed_intrinsics": camera.intrinsics.as_dict(), "camera_source": camera_source or NO_CAMERA,
        "sim_frames": sim_frames, **result.to_dict(), **work,
        "held_out": verdict, "written": "fitted" if verdict["fitted_better"] else "input",
        "output_window": {"stock": {key: getattr(stock_camera, key) for key in (*window, *UNREGISTERED)},
                          "measured": {**window, **model.registration_keys},
                          "rule": "border columns (rows) valid in at most 1 % of the real frames' pixels (a "
                                  "registered device's: mapped back into its IR frame; its left band: the most "
                                  "common first IR column of a row)",
                          "model": model.name,
                          "stock_radius_distance": {m.name: m.distance for m in candidates},
                          "judged": structure},
    }  # fmt: skip
    with atomic_folder(report, "the report") as building:  # in place only when complete (an interrupt leaves none)
        content = write_report(building, content, pooled, depths, resolution, seed, fb)
        write_index(building, f"ddsgen fit --unpaired: {preset_ref} on {real_dir}", "\n".join(summary_lines(content)),
                    [], ["distributions.png", "profiles.png", "patches.png", "frames.png"],
                    plots_heading="Feature distributions, search profiles, patches and frames: real | input | fitted")
    # The window in the preset's own pixels (the fit ran at the real frames' size).
    in_preset_px = model.window.rescaled(width, height, original.width_px, original.height_px)
    registration = UNREGISTERED if model.name == "unregistered" else {}  # registered: the preset's own, unscaled
    input_window = tuple(getattr(original, key) for key in in_preset_px.as_keys())
    reading = (f"depth registration: {model.name}; output window (px without depth at the left, right, top, bottom): "
               f"{input_window} -> {tuple(in_preset_px.as_keys().values())}")  # fmt: skip
    if structure.get("fit_choice", model.name) != model.name:
        reading += (f" (the input's: the held-out frames did not confirm the fit frames' {structure['fit_choice']} "
                    "beyond the spread)")
    if verdict["fitted_better"]:
        fitted = assemble_preset(original, {**registration, **in_preset_px.as_keys(), **result.after}, "unpaired")
        changed = [f"{key}: {content['before'][key]:.6g} -> {value:.6g} ({spread_text(content, key)})"
                   for key, value in result.after.items() if value != content["before"][key]]  # fmt: skip
        kept = [key for key, value in result.after.items() if value == content["before"][key]]
        write_preset(fitted, out, "\n".join([
            f"fitted by ddsgen fit --unpaired to {real_dir} from {preset_ref}",
            f"held out: {verdict['meaning']}; feature distance on the held-out frames "
            f"{verdict['stock']:.4f} (input) -> {verdict['fitted']:.4f} (this preset)",
            "by feature group: " + group_verdicts(verdict),
            reading,
            "changed: " + ("; ".join(changed) if changed else "none of the searched keys"),
            "kept (the input's value fits as well): " + (", ".join(kept) if kept else "none"),
            f"not identifiable from unpaired depth: {NOT_IDENTIFIABLE}",
            "every other key: the input's"]))  # fmt: skip
    else:
        write_preset(assemble_preset(original, {}, "unpaired"), out, "\n".join([
            f"ddsgen fit --unpaired to {real_dir} from {preset_ref}: the input's values, kept",
            f"held out: {verdict['meaning']}" + ("" if verdict["stock"] is None else
            f"; the fit was not closer to the held-out frames (feature distance {verdict['stock']:.4f} input, "
            f"{verdict['fitted']:.4f} fitted; by feature group: {group_verdicts(verdict)})")]))  # fmt: skip
    return content


#: Where the camera comes from when neither --camera nor the folder gives one.
NO_CAMERA = "the preset's, scaled to the frames (no --camera, no BOP camera file in the folder)"

#: What depth statistics cannot show, and what would show it (said in every summary).
NOT_IDENTIFIABLE = ("a global disparity offset or scale and the focal length (they move every depth alike, which a "
                    "scene of unknown geometry absorbs); a paired fit (ddsgen fit with poses) or a plane at a known "
                    "distance determines them")


def summary_lines(content: dict) -> list[str]:
    """What the fit did, in lines: distance before/after on the fit frames, each value with its uncertainty, the
    registration and window, the held-out judgement and which preset is written (the terminal and index.html)."""
    lines = []
    before, after = content["distance_before"]["total"], content["distance_after"]["total"]
    lines.append(f"feature distance on the fit frames: {before:.4f} (stock) -> {after:.4f} (fitted) over "
                 f"{len(content['held_out']['fit_frames'])} real frame(s), {content['evaluations']} value sets, "
                 f"{content['frames_rendered']} frames rendered")  # fmt: skip
    for key, value in content["after"].items():
        scene = content["bootstrap"][key]["scene_content"]
        note = "; kept: the input's value fits as well" if scene["kept_input_value"] else ""
        lines.append(f"  {key:20s} {content['before'][key]:.6g} -> {value:.6g}, {spread_text(content, key)}{note}")
    stock, measured = content["output_window"]["stock"], content["output_window"]["measured"]
    window = content["output_window"]
    distances = ", ".join(f"{name} {d:.4f}" for name, d in window["stock_radius_distance"].items() if d is not None)
    judged = window.get("judged", {})
    switched = judged.get("fit_choice", window["model"]) != window["model"]
    lines.append(f"  depth registration: {window['model']}"
                 + (f" (the fit frames chose {judged.get('fit_choice')}; the held-out frames did not confirm it "
                    "beyond the spread)" if switched else "")
                 + (f" (validity by radius, stock values: {distances})" if distances else ""))
    lines.append("  output window (measured; px without depth at the left, right, top, bottom): "
                 f"{tuple(stock.values())[:4]} -> {tuple(measured.values())[:4]}")  # fmt: skip
    heldout = window.get("judged", {}).get("heldout", {})
    if heldout:
        farther = judged.get("farther") or []
        lines.append("    held out, the keys fitted under each reading: "
                     + ", ".join(f"{name} {value:.4f}" for name, value in heldout.items())
                     + (f"; read the fit frames' way, {', '.join(farther)} farther beyond the spread" if farther
                        else ""))  # fmt: skip
    camera = content["assumed_intrinsics"]
    lines.append(f"  camera of the frames: fx {camera['fx']:.6g}, fy {camera['fy']:.6g}, cx {camera['cx']:.6g}, "
                 f"cy {camera['cy']:.6g} px, {content.get('camera_source', NO_CAMERA)}")  # fmt: skip
    lines.append(f"  not identifiable from unpaired depth, left at the input's values: {NOT_IDENTIFIABLE}")
    held = content["held_out"]
    lines.append(f"held out: {held['meaning']} ({len(held['held_out_frames'])} of "
                 f"{len(content['real_frames'])} frames)")  # fmt: skip
    if held["stock"] is not None:
        lines.append(f"  feature distance on the held-out frames: {held['stock']:.4f} (input) -> {held['fitted']:.4f} "
                     f"(fitted)")  # fmt: skip
        lines.append(f"  by feature group (input -> fitted, the difference +- its spread over draws of frames): "
                     f"{group_verdicts(held)}")  # fmt: skip
    if content["written"] == "input":
        farther = held.get("farther") or []
        lines.append("the fit is not closer to frames it did not see"
                     + (f" ({', '.join(farther)} farther beyond the spread)" if farther else "")
                     + ": the input preset's values are written, unchanged")  # fmt: skip
    return lines


def spread_text(content: dict, key: str) -> str:
    """How well the fit determined ``key``, in words: +- one standard deviation, a factor (log-scale keys), or the
    range that fits as well when the resamples did not bound it."""
    scene = content["bootstrap"][key]["scene_content"]
    if content["bootstrap"][key]["lower_bound"]:  # the resamples did not bound it: no spread to quote
        return f"not determined by these frames ({scene['low']:.3g}..{scene['high']:.3g} fit as well)"
    if UNPAIRED_PARAMETERS[key].log:  # a log-scale key is known within a factor
        return f"known within a factor {math.exp(content['uncertainty_search'][key]):.2g}"
    return f"+- {content['uncertainty'][key]:.2g}"


def group_verdicts(verdict: dict) -> str:
    """Each feature group's held-out distance, input -> fitted, the difference with its spread and what it means
    (:func:`~.holdout.judge`), in one line."""
    terms, spread = verdict["terms"], verdict.get("spread", {})
    parts = []
    for group in GROUPS:
        before, after = terms["stock"][group], terms["fitted"][group]
        plus_minus = f" +- {spread[group]:.4f}" if group in spread else ""
        meaning = f", {verdict['groups'][group]}" if "groups" in verdict else ""
        parts.append(f"{group} {before:.4f} -> {after:.4f} ({after - before:+.4f}{plus_minus}{meaning})")
    return "; ".join(parts)


def print_summary(content: dict) -> None:
    """The command's closing lines (:func:`summary_lines`) and what was written."""
    for line in summary_lines(content):
        click.echo(line)
    click.echo(f"wrote {content['fitted_preset']} and {content['report']}/")


def _intrinsics(preset) -> dict:
    """The preset's camera as preset keys."""
    return {"focal_px": preset.focal_px, "focal_y_px": preset.focal_y_px, "cx_px": preset.cx_px, "cy_px": preset.cy_px}
