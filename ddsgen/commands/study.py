"""``ddsgen study``: studies of a sensor preset against published measurements of real devices."""

from __future__ import annotations

import click

from ddsgen.commands import SEED, FiniteFloat
from ddsgen.study.noise import DEFAULT_ALBEDO, DEFAULT_ANGLES, DEFAULT_Z
from ddsgen.study.noise_folder import write_noise_study


@click.group("study")
def study():
    """Studies of a sensor preset's behaviour against published real-device measurements."""


@study.command("noise")
@click.argument("preset")
@click.option("--z", "z_text", default=DEFAULT_Z, show_default=True, metavar="START:STOP:STEP|A,B,..",
              help="Plane distances (m).")
@click.option("--angles", "angles_text", default=DEFAULT_ANGLES, show_default=True, metavar="A,B,..|START:STOP:STEP",
              help="Tilts of the plane about the vertical axis (deg, 0 <= angle < 90).")
@click.option("--frames", "-k", type=int, default=4, show_default=True,
              help="Frames per (z, angle), each with its own noise seed; the ray cast is done once per point.")
@click.option("--out", type=click.Path(file_okay=False), default="noise_study", show_default=True,
              help="Output folder: noise.json, noise_study.png, noise_table.md, sensor.yaml.")
@click.option("--seed", type=SEED, default=0, show_default=True, help="Study seed (noise of every frame).")
@click.option("--rows", type=int, default=None,
              help="Render only a centred crop of this many image rows (faster; same physics). Default: all rows.")
@click.option("--albedo", type=FiniteFloat(0.0, 1.0, min_open=True), default=DEFAULT_ALBEDO, show_default=True,
              help="IR reflectance of the plane.")
@click.option("--lateral/--no-lateral", default=True, show_default=True,
              help="Also measure the lateral noise (how far a board's vertical edges wander from a line, against "
                   "Nguyen 2012): a second scene per (z, angle), so twice the frames.")
@click.option("--quiet", is_flag=True, help="No progress bar and no summary.")
def noise(preset, z_text, angles_text, frames, out, seed, rows, albedo, lateral, quiet):
    """The noise study of the paper (Fig. S4) for PRESET (a preset file or a shipped name such as kinect_v1).

    A flat surface at distance z, tilted by an angle about the vertical axis, is ray cast once per (z, angle)
    and simulated K times through the full sensor (IR image, block matching, depth) with different noise
    seeds. Per point: axial noise (std after removing the fitted plane), rms and bias against the true plane,
    valid fraction and the quantisation step (spacing of the distinct depth values). With --lateral (the
    default), also a board of finite width before a wall, its two vertical edges' distance from a fitted line
    per row (the lateral noise, px). Writes OUT/noise.json,
    OUT/noise_study.png (with the Nguyen 2012 and Khoshelham 2012 Kinect V1 curves and the real Kinect's
    depth values from ../shared/data when present), OUT/noise_table.md and OUT/sensor.yaml; prints how many
    points lie within +-30 % of each published curve (also in noise.json's "verdict" and the table).
    """
    write_noise_study(preset, z_text, angles_text, frames, out, seed, rows, albedo, lateral, quiet)
