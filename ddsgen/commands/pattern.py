"""``ddsgen pattern``: regenerate a Kinect-like dot pattern for a preset and measure its uniqueness."""

from __future__ import annotations

from pathlib import Path

import click
import cv2
import numpy as np

from ddsgen.commands import SEED, FiniteFloat
from ddsgen.errors import InputError
from ddsgen.atomic import atomic_write_bytes, check_can_create_folder
from ddsgen.preset import load_preset
from ddsgen.sensor.pattern import generate_pattern, load_pattern, pattern_requirements, pattern_statistics


def _print_statistics(label: str, stats: dict) -> None:
    click.echo(
        f"{label}: {stats['width']}x{stats['height']} px, {100 * stats['lit_fraction']:.1f}% lit; "
        f"second-best ZNCC along rows: median {stats['second_best_zncc_median']:.3f}, "
        f"p99 {stats['second_best_zncc_p99']:.3f}, max {stats['second_best_zncc_max']:.3f}; "
        f"ambiguous windows (>0.9): {100 * stats['ambiguous_fraction']:.3f}%"
    )


@click.command("pattern")
@click.argument("preset", default="kinect_v1")
@click.option("--seed", type=SEED, default=0, show_default=True,
              help="Random seed: the same seed gives the same pattern.")
@click.option("--density", type=FiniteFloat(0.0, 1.0, min_open=True, max_open=True), default=0.11,
              show_default=True, help="Fraction of lit pixels (real Kinect V1: 0.111; dots that never touch, as on "
                                      "the real pattern, fill at most about 0.19).")
@click.option("--out", type=click.Path(dir_okay=False), default=None,
              help="Output PNG [default: the preset's pattern file name, in the current folder]. To use it, "
                   "put it beside your preset file (a preset's pattern is looked up there first).")
@click.option("--compare", "compare_with", type=click.Path(exists=True, dir_okay=False), default=None,
              help="Also measure another pattern image (e.g. the real Kinect pattern) the same way.")
def pattern(preset, seed, density, out, compare_with):
    """Generate the dot pattern for PRESET (a preset file or name) and measure it.

    The pattern is a 3x3 layout of identical pseudo-random dot tiles with a brighter
    marker at each tile centre, sized to cover the field of view plus the largest
    disparity. Every window of the preset's block size is made unambiguous along its
    row within the disparity range: the command prints the second-best ZNCC match
    score (1 = ambiguous) over all windows.
    """
    sensor = load_preset(preset)
    need = pattern_requirements(sensor)
    # Never into the package's own folder (site-packages in a wheel install): the current folder by default.
    target = Path(out) if out else Path(Path(sensor.pattern).name)
    # Every input and the output's folder are checked before anything is written.
    try:
        check_can_create_folder(target.parent, "the pattern PNG")
    except InputError as error:
        raise InputError(f"--out: {error}") from None
    if not target.suffix.lower() == ".png":
        raise InputError(f"--out: {target}: the pattern is written as PNG: give a name ending in .png")
    other = None
    if compare_with:
        try:
            other = load_pattern(compare_with)
        except InputError as error:
            raise InputError(f"--compare: {error}") from None
    try:
        image = generate_pattern(need["width"], need["height"], seed=seed, density=density, block=need["block"],
                                 max_shift=need["max_shift"])  # fmt: skip
    except ValueError as error:  # a density the dots cannot reach: nothing is written
        raise click.BadParameter(str(error), param_hint="--density") from None
    ok, data = cv2.imencode(".png", image)
    atomic_write_bytes(target, data.tobytes())
    _print_statistics(f"wrote {target}", pattern_statistics(image, need["block"], need["max_shift"]))
    if other is not None:
        _print_statistics(compare_with, pattern_statistics(other.astype(np.float32), need["block"], need["max_shift"]))
