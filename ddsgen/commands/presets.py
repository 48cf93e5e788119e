"""``ddsgen presets``: list the shipped sensor presets, or print one (to copy and edit)."""

from __future__ import annotations

import click

from ddsgen.errors import InputError
from ddsgen.preset import PRESET_DIR, load_preset, shipped_preset, shipped_preset_names


def preset_description(text: str) -> str:
    """The short description of a preset: its file's first comment line, up to any parenthesis."""
    for line in text.splitlines():
        if line.startswith("#"):
            return line.lstrip("#").split(" (")[0].strip().rstrip(".;,:")
    return ""


def preset_rows() -> list[tuple[str, ...]]:
    """(name, sensor, resolution, range, description) of each shipped preset."""
    rows = []
    for name in shipped_preset_names():
        path = shipped_preset(name)
        sensor = load_preset(path)
        geometry = f"b {1000 * sensor.baseline_m:g} mm, f {sensor.focal_px:.0f} px, w {sensor.block_size_px}"
        rows.append((name, geometry, f"{sensor.width_px}x{sensor.height_px}",
                     f"{sensor.z_min_m:g}-{sensor.z_max_m:g} m", preset_description(path.read_text(encoding="utf-8"))))  # fmt: skip
    return rows


@click.command("presets")
@click.argument("name", required=False)
def presets(name):
    """List the shipped sensor presets, one line each; with NAME, print that preset's YAML.

    Any of them works by name, from any folder: ``ddsgen render kinect_v1``. To make your
    own, ``ddsgen presets kinect_v1 > my_sensor.yaml``, edit it, then
    ``ddsgen render my_sensor.yaml`` (its ``pattern:`` is found beside your file first,
    then among the shipped patterns).
    """
    if name is not None:
        path = shipped_preset(name)
        if path is None:
            raise InputError(f"{name}: no shipped preset of that name ({', '.join(shipped_preset_names())})")
        click.echo(path.read_text(encoding="utf-8"), nl=False)
        return
    rows = [("NAME", "SENSOR", "RESOLUTION", "RANGE", "DESCRIPTION"), *preset_rows()]
    widths = [max(len(row[i]) for row in rows) for i in range(4)]
    for row in rows:
        click.echo("  ".join(cell.ljust(width) for cell, width in zip(row, widths)) + "  " + row[4])
    click.echo(f"({len(rows) - 1} presets in {PRESET_DIR}; use one by name: ddsgen render NAME)")
