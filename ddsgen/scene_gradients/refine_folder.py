"""``ddsgen refine PRESET REAL_DIR --out OUT``: refine the annotated poses of every frame of a scan folder, write them
in the input's layout with a report."""

from __future__ import annotations

from pathlib import Path

import click
from tqdm import tqdm

from ddsgen.atomic import atomic_folder, check_new_folder
from ddsgen.errors import InputError
from ddsgen.io.pose_writer import write_refined_poses
from ddsgen.io.scanfolder import read_scan_folder
from ddsgen.preset import SensorPreset, load_preset
from ddsgen.realscan.inputs import adopt_camera
from ddsgen.scene_gradients import scan
from ddsgen.scene_gradients.refine import RefineSettings
from ddsgen.scene_gradients.report import write_report


def camera_preset(base: SensorPreset, frames) -> SensorPreset:
    """The preset with the frames' camera (one line naming the first frame if it does not fit)."""
    try:
        return adopt_camera(base, frames)[0]
    except InputError as error:
        raise InputError(f"{frames[0].source_depth_path}: the scan's camera does not fit the preset: {error}") from None


def run_refine(preset: str, real_dir: str | Path, out_dir: str | Path, settings: RefineSettings, *,
               static_scene: bool = False, static_views: int = 8, support_plane: bool = True,
               progress: bool = True) -> list[Path]:  # fmt: skip
    """Refine every frame's poses in ``real_dir`` (one correction per object and static scene with
    ``static_scene``), write OUT and OUT/report/, print one line per object and frame; returns the files written."""
    # Before any work: OUT is a new folder, not the input (whose manifest it would overwrite) nor in it.
    check_new_folder(out_dir, "--out", inputs=(real_dir,))
    base = load_preset(preset)
    frames = read_scan_folder(real_dir)
    if not frames:
        raise InputError(f"{real_dir}: no frames")
    for frame in frames:
        if not frame.objects:
            raise InputError(f"{frame.source_depth_path}: frame {frame.name} lists no objects (nothing to refine)")
    refinements, refined = [], {}
    if static_scene:
        for first, scene_frames in tqdm(scan.static_scenes(frames), desc="scenes", unit="scene", disable=not progress):
            simulated, poses = scan.refine_static_scan(camera_preset(base, scene_frames), scene_frames, settings,
                                                       support_plane=support_plane, progress=progress,
                                                       first_index=first, max_views=static_views)  # fmt: skip
            refinements += simulated
            refined.update(poses)
            for frame in scene_frames:
                frame.release()
    for index, frame in enumerate(tqdm([] if static_scene else frames, desc="frames", unit="frame",
                                       disable=not progress)):  # fmt: skip
        refinements.append(scan.refine_scan_frame(camera_preset(base, [frame]), frame, index, settings,
                                                  support_plane=support_plane, progress=progress))  # fmt: skip
        refined[frame.name] = refinements[-1].refined_poses()
        frame.release()
    out = Path(out_dir)
    with atomic_folder(out, "--out", merge=False) as building:  # OUT appears whole or not at all
        written = write_refined_poses(frames, refined, building, final=out)
        write_report(refinements, building / "report", {"preset": str(preset), "real_dir": str(real_dir),
                     "static_scene": bool(static_scene), "static_views": int(static_views), **vars(settings)})  # fmt: skip
    for r in refinements:
        for change in r.object_changes():
            seen = change.get("visible_fraction_dataset", change.get("visible_fraction_estimated"))
            click.echo(f"{r.name} {change['label']}"
                       + (f" ({100 * seen:.0f} % visible)" if seen is not None else "")
                       + f": moved {change['rotation_deg']:.2f} deg, "
                       f"{change['translation_mm']:.2f} mm; {change['decision']}"
                       + (f"; not determined by the data, kept at the start: {', '.join(change['undetermined'])}"
                          if change.get("undetermined") else ""))  # fmt: skip
        result = r.result
        heldout = (f"; held-out gap {result.heldout_gap_before_mm:.2f} mm -> {result.heldout_gap_after_mm:.2f} mm"
                   if result.heldout_gap_before_mm == result.heldout_gap_before_mm else "")  # fmt: skip
        verdict = " (not lower: start poses kept)" if result.kept_start else ""
        click.echo(f"{r.name}: gap {result.gap_before_mm:.2f} mm -> {result.gap_after_mm:.2f} mm{heldout}{verdict}")
    click.echo(f"wrote {', '.join(str(p) for p in written)} and {out / 'report'}/")
    return written
