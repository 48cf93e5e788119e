"""``ddsgen study noise PRESET``: the noise study run, judged against the published curves, written to a folder."""

from __future__ import annotations

from pathlib import Path

import click
from tqdm import tqdm

from ddsgen.atomic import atomic_write_text
from ddsgen.errors import InputError
from ddsgen.preset import load_preset, save_preset
from ddsgen.study.lateral import run_lateral_study
from ddsgen.study.noise import parse_grid, run_noise_study, study_intrinsics
from ddsgen.study.noise_report import (
    lateral_table, noise_table, plot_noise_study, quantisation_table, verdict, verdict_line, verdict_section,
    write_noise_json,
)  # fmt: skip
from ddsgen.study.quantisation import real_quantisation


def write_noise_study(preset: str, z_text: str, angles_text: str, frames: int, out: str | Path, seed: int,
                      rows: int | None, albedo: float, lateral: bool, quiet: bool) -> None:  # fmt: skip
    """Run the noise (and lateral) study of ``preset`` on the grid ``z_text`` x ``angles_text`` (the command's
    option texts) and write OUT/noise.json, noise_study.png, noise_table.md and sensor.yaml; prints the verdict."""
    zs = parse_grid(z_text, "--z", 0.0, 100.0, low_open=True)
    angles = parse_grid(angles_text, "--angles", 0.0, 89.0)
    if frames < 1:
        raise InputError(f"--frames: must be >= 1, got {frames}")
    sensor = load_preset(preset)
    study_intrinsics(sensor, rows)  # checks --rows before anything is written
    out_dir = Path(out)
    out_dir.mkdir(parents=True, exist_ok=True)

    scenes = 2 if lateral else 1
    bar = tqdm(total=scenes * len(zs) * len(angles) * frames, unit="frame", desc="study noise", disable=quiet,
               dynamic_ncols=True)  # fmt: skip
    try:
        points = run_noise_study(sensor, zs, angles, frames=frames, seed=seed, rows=rows, albedo=albedo,
                                 on_frame=lambda: bar.update(1))  # fmt: skip
        edges = None
        if lateral:
            edges = run_lateral_study(sensor, zs, angles, frames=frames, seed=seed, rows=rows, albedo=albedo,
                                      on_frame=lambda: bar.update(1))  # fmt: skip
    finally:
        bar.close()
    real = real_quantisation()
    save_preset(sensor, out_dir / "sensor.yaml", comment=f"sensor used by: ddsgen study noise {preset}")
    write_noise_json(points, out_dir / "noise.json", lateral=edges)
    table = noise_table(points)
    quant = quantisation_table(points, sensor, real)
    notes = "".join(f"- {m}\n" for m in real.messages)
    lateral_section = "" if edges is None else f"\n## Lateral noise\n\n{lateral_table(edges, sensor.intrinsics.fx)}"
    judged = verdict(points)
    published = f"## Against the published curves\n\n{verdict_section(judged)}"
    atomic_write_text(out_dir / "noise_table.md", f"# Noise study: {sensor.name}\n\n{table}\n{published}\n"
                      f"## Quantisation step\n\n{quant}\n{notes}{lateral_section}")  # fmt: skip
    plot_noise_study(points, sensor, real, out_dir / "noise_study.png", lateral=edges)
    if not quiet:
        for message in real.messages:
            click.echo(f"note: {message}", err=True)
        click.echo(f"std {verdict_line(judged)}")
        click.echo(f"{len(points)} points x {frames} frames -> {out_dir}/noise.json, {out_dir}/noise_study.png, "
                   f"{out_dir}/noise_table.md")  # fmt: skip
