"""``ddsgen diagnose PRESET REAL_DIR``: read the scans, run the diagnosis, write its report and the extended preset."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import click

from ddsgen.diagnose.config import DiagnoseConfig
from ddsgen.diagnose.device_candidates import BEHAVIOURS
from ddsgen.diagnose.loop import diagnose
from ddsgen.diagnose.report import write_diagnosis
from ddsgen.diagnose.results import Diagnosis
from ddsgen.errors import InputError
from ddsgen.fit.fitted_preset import assemble_preset, sensor_changes, write_preset
from ddsgen.preset import SensorPreset
from ddsgen.realscan import inputs
from ddsgen.realscan.gap_report import BELOW_FLOOR


def extended_preset(diagnosis: Diagnosis, original: SensorPreset, camera_preset: SensorPreset) -> SensorPreset:
    """The user's preset ``original`` extended by what ``diagnosis`` accepted: the refitted base values, the effects
    added, the device behaviours accepted (preset keys) and the output window measured on the scans (written in
    ``original``'s pixels; ``camera_preset`` is the scans' camera the diagnosis ran at)."""
    sensor = diagnosis.sensor
    changes = sensor_changes(sensor, original)
    for step in diagnosis.steps:  # accepted device behaviours are preset keys
        if step.effect in BEHAVIOURS:
            key = BEHAVIOURS[step.effect].key
            changes[key] = getattr(sensor.preset, key)
    if diagnosis.output_window is not None:
        changes.update(diagnosis.output_window.rescaled(camera_preset.width_px, camera_preset.height_px,
                                                        original.width_px, original.height_px).as_keys())  # fmt: skip
    return assemble_preset(original, changes, "diagnosed")


def run_diagnose(preset: str, real_dir: str | Path, report_dir: str | Path, config: DiagnoseConfig, *,
                 region: str = "all", support_plane: bool = True, plausible_px: float = 2.0,
                 apply_path: str | Path | None = None, progress: bool = True, echo=None) -> list[Path]:  # fmt: skip
    """Diagnose ``preset`` on the scans in ``real_dir``; write REPORT (and the extended preset at ``apply_path``),
    print the summary lines; returns the files written."""
    original, camera_preset, _, frames = inputs.load_inputs(
        preset, real_dir, support_plane=support_plane, plausible_px=plausible_px, seed=config.seed,
        progress=progress, echo=echo, window_hint=False)  # diagnose measures the window itself  # fmt: skip
    if region == "objects":
        frames = [dataclasses.replace(f, region=f.object_region.clone()) for f in frames]
        if not any(bool(f.region.any()) for f in frames):
            raise InputError(f"{real_dir}: --region objects: no annotated object is visible in any frame")

    def log(line: str) -> None:
        if progress:
            click.echo(line, err=True)

    result = diagnose(camera_preset, frames, config, echo=log, progress=progress)
    written = write_diagnosis(result, report_dir, f"ddsgen diagnose: {original.name} vs {real_dir}",
                              [f"Sensor preset {preset}; scans {real_dir} ({len(frames)} frame(s))."])  # fmt: skip
    if apply_path is not None:
        added = ", ".join(s.effect for s in result.steps) or "none"
        written.append(write_preset(extended_preset(result, original, camera_preset), apply_path,
                                    f"extended by ddsgen diagnose from {preset} on {real_dir}\n"
                                    f"effects added: {added}"))  # fmt: skip
    summary = ", ".join(f"{s.effect} ({s.gap_before:.2f} -> {s.gap_after:.2f} mm)" for s in result.steps) or "none"
    click.echo(f"held-out gap beyond the noise floor {result.baseline_gap:.2f} -> {result.final_gap:.2f} mm "
               f"(compare gap {result.baseline.gap:.2f} -> {result.final.gap:.2f} mm); effects added: {summary}")
    if result.final_gap < 0:
        click.echo(f"  {BELOW_FLOOR}")
    for u in result.unexplained:
        click.echo(f"unexplained: residual varies along {u['axis']} ({u['strength']:.1f} mm beyond noise)")
    click.echo(f"wrote {', '.join(str(p) for p in written)}")
    return written
