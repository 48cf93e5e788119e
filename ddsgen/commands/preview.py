"""``ddsgen preview``: a contact sheet of a dataset (depth, IR, instances with boxes), readable at a glance."""

from __future__ import annotations

import click

from ddsgen.preview import DEFAULT_FRAMES, write_preview


@click.command("preview")
@click.argument("folder", metavar="OUT")
@click.option("--out", "sheet", type=click.Path(dir_okay=False), default=None,
              help="Contact sheet PNG to write [default: OUT/preview.png when `ddsgen render` wrote OUT, else "
                   "preview_NAME.png in the current folder, so a dataset ddsgen did not make is not written into].")
@click.option("--frames", type=int, default=DEFAULT_FRAMES, show_default=True,
              help="Frames shown, evenly spaced over the dataset (first and last included).")
def preview(folder, sheet, frames):
    """Draw a contact sheet of the scan folder OUT (a ddsgen render, real scans, or a BOP dataset).

    One row per frame: depth colour-mapped over a range shared by every row (colour bar in metres;
    invalid pixels black), the IR image auto-exposed, and the instance mask with each object's
    bounding box and class name. The title names the sensor preset and the frames shown.
    """
    path, panels = write_preview(folder, sheet, frames)
    rows = len({p.frame for p in panels})
    click.echo(f"wrote {path} ({rows} frame(s))")
