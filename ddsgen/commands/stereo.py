"""``ddsgen stereo LEFT RIGHT``: the block matcher alone, on an ordinary rectified stereo pair.

Writes float32 disparity in pixels (0 = invalid) as EXR (``--out`` must end in .exr), and optionally a
colour-mapped PNG (``--png``, ending in .png).
The pair must be rectified (epipolar lines = image rows); a pixel u of the left image
matches u - d in the right image.
"""

from __future__ import annotations

import math
from pathlib import Path

import click
import cv2
import numpy as np
import torch

from ddsgen.atomic import atomic_path, check_can_create_folder
from ddsgen.errors import InputError
from ddsgen.io.exr import write_exr
from ddsgen.io.images import read_image
from ddsgen.sensor.matcher import match, stereo_reference_phases


def _read_grey(path: str) -> np.ndarray:
    """Image file -> float32 (H, W) grey levels; InputError if it cannot be read."""
    image = read_image(path, "image")
    if image.ndim == 3:
        if image.shape[2] == 4:
            image = image[:, :, :3]
        image = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY) if image.shape[2] == 3 else image[:, :, 0]
    image = image.astype(np.float32)
    if not np.isfinite(image).all():
        raise InputError(f"{path}: image has NaN/inf values")
    return image


def _check_output(option: str, path: str, suffix: str, what: str, why: str) -> None:
    """Before any work: ``path`` ends in ``suffix`` (the format written; never EXR bytes in a .png file) and its
    folder can be created (not below a plain file)."""
    if Path(path).suffix.lower() != suffix:
        raise InputError(f"{option}: {path}: {why}; give a name ending in {suffix}")
    try:
        check_can_create_folder(Path(path).parent, what)
    except InputError as error:
        raise InputError(f"{option}: {error}") from None


def _colour_png(path: Path, disparity: np.ndarray, valid: np.ndarray, max_disparity: float) -> None:
    scaled = np.clip(disparity / max(max_disparity, 1e-6), 0.0, 1.0)
    colour = cv2.applyColorMap((scaled * 255).astype(np.uint8), cv2.COLORMAP_TURBO)
    colour[~valid] = 0
    with atomic_path(path) as tmp:
        if not cv2.imwrite(str(tmp), colour):
            raise InputError(f"{path}: cannot write PNG")


@click.command("stereo")
@click.argument("left", type=click.Path(dir_okay=False))
@click.argument("right", type=click.Path(dir_okay=False))
@click.option("--max-disparity", "-D", type=float, default=64.0, show_default=True, help="Largest disparity searched (px).")
@click.option("--min-disparity", type=float, default=0.0, show_default=True, help="Smallest disparity searched (px).")
@click.option("--block", "-w", type=int, default=9, show_default=True, help="ZNCC window size (odd, px).")
@click.option("--subpixel", "n_sub", type=int, default=2, show_default=True, help="Sub-pixel level n: steps of 2^-n px.")
@click.option("--beta", type=float, default=15.0, show_default=True, help="Soft-argmax temperature.")
@click.option("--min-confidence", type=float, default=0.0, show_default=True,
              help="Confidence (best ZNCC minus the best other peak, 0..1) below which a pixel is invalid; "
                   "0 keeps every pixel with a unique match (flat windows and matches outside RIGHT stay invalid).")
@click.option("--band-rows", type=int, default=64, show_default=True, help="Rows per matching band (bounds memory).")
@click.option("--out", "-o", type=click.Path(dir_okay=False), default="disparity.exr", show_default=True, help="Output EXR: float32 disparity (px), 0 = invalid.")
@click.option("--png", type=click.Path(dir_okay=False), default=None, help="Also write a colour-mapped PNG to look at.")
def stereo(left, right, max_disparity, min_disparity, block, n_sub, beta, min_confidence, band_rows, out, png):
    """Disparity of a rectified LEFT/RIGHT pair with ddsgen's ZNCC block matcher.

    Grey or colour images (colour is converted to grey). Pixel u of LEFT matches u - d of
    RIGHT, d in [--min-disparity, --max-disparity]. Writes float32 disparity (px, 0 = invalid).
    """
    if block < 3 or block % 2 == 0:
        raise InputError(f"--block: must be odd and >= 3, got {block}")
    if not 0 <= n_sub <= 6:
        raise InputError(f"--subpixel: must be in 0..6, got {n_sub}")
    if not (math.isfinite(min_disparity) and min_disparity >= 0):
        raise InputError(f"--min-disparity: must be >= 0, got {min_disparity}")
    if not (math.isfinite(max_disparity) and max_disparity >= min_disparity + 1):
        raise InputError(f"--max-disparity: must be >= --min-disparity + 1, got {max_disparity}")
    if not 0 <= min_confidence <= 1:
        raise InputError(f"--min-confidence: must be in [0, 1], got {min_confidence}")
    if band_rows < 1:
        raise InputError(f"--band-rows: must be >= 1, got {band_rows}")
    if not (math.isfinite(beta) and beta > 0):
        raise InputError(f"--beta: must be > 0, got {beta}")
    _check_output("--out", out, ".exr", "the disparity EXR",
                  "the disparity is written as float32 EXR (a picture to look at: --png NAME.png)")  # fmt: skip
    if png:
        _check_output("--png", png, ".png", "the colour-mapped PNG", "the colour-mapped picture is written as PNG")
    image_l, image_r = _read_grey(left), _read_grey(right)
    if image_l.shape != image_r.shape:
        raise InputError(f"{right}: size {image_r.shape[1]}x{image_r.shape[0]} differs from {left} "
                         f"({image_l.shape[1]}x{image_l.shape[0]})")  # fmt: skip
    height, width = image_l.shape
    if height < block or width < 2 * block:
        raise InputError(f"{left}: image {width}x{height} is too small for --block {block}")
    if max_disparity >= width - block:
        raise InputError(f"--max-disparity: must be < image width - block ({width - block}), got {max_disparity}")

    pad = int(math.ceil(max_disparity)) + block
    with torch.no_grad():
        phases = stereo_reference_phases(torch.from_numpy(image_r), n_sub, pad)
        result = match(torch.from_numpy(image_l), phases, pad, min_disparity, max_disparity, block, beta, n_sub,
                       band_rows, min_confidence)  # fmt: skip
    valid = result.valid.numpy()
    disparity = np.where(valid, result.disparity.numpy(), 0.0).astype(np.float32)
    write_exr(out, disparity)
    if png:
        _colour_png(Path(png), disparity, valid, max_disparity)
    shown = disparity[valid]
    span = f", {shown.min():.2f}-{shown.max():.2f} px" if shown.size else ""
    click.echo(f"disparity {width}x{height}: {100.0 * valid.mean():.1f} % valid{span} -> {out}"
               + (f" (+ {png})" if png else ""))  # fmt: skip
