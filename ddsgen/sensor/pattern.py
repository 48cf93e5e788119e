"""The projector's dot pattern: generation, loading, and the continuous field the sensor samples.

Three pieces:

* :func:`generate_pattern` makes a Kinect-like pattern (pseudo-random 1-px dots,
  about 11 % lit, a 3x3 layout of identical tiles with a brighter marker dot at
  each tile's centre, like the real device) and repairs every window that is
  ambiguous along its row within the disparity range.
* :func:`row_ambiguity` measures that property: for each w x w window, the best
  ZNCC against the same row shifted by 1..D px (the "second best" match; the true
  match scores 1).
* :class:`PatternField` turns a pattern image (projector pixels) into a blurred,
  super-sampled raster sampled bilinearly -- differentiable in the sampling
  position, so the IR image is differentiable in baseline and focal length -- and
  makes the sub-pixel shifted reference images the matcher needs (cached once per
  sensor, not per frame).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch
import torch.nn.functional as F

from ddsgen.errors import InputError
from ddsgen.io.images import read_image

DOT_VALUE = 220  # 8-bit value of an ordinary dot
MARKER_VALUE = 255  # 8-bit value of a tile's centre marker (brighter, 3x3 px)


def _box_mean(image: np.ndarray, block: int) -> np.ndarray:
    return cv2.boxFilter(image, cv2.CV_32F, (block, block), normalize=True, borderType=cv2.BORDER_REFLECT)


def row_ambiguity(pattern: np.ndarray, block: int, max_shift: int) -> np.ndarray:
    """Worst-case self-similarity of each window along its row.

    Args:
        pattern: (H, W) pattern image (any dtype).
        block: window size w (odd, px).
        max_shift: largest shift D searched (px); shifts 1..D in both directions.

    Returns:
        (H, W) float32: max over 0 < |s| <= D of ZNCC(window at u, window at u + s).
        1 means some other window in range is identical (ambiguous); the matcher's
        confidence margin is 1 minus this. Columns within D of the border only
        compare with shifts that stay inside the image.
    """
    image = pattern.astype(np.float32)
    height, width = image.shape
    mean = _box_mean(image, block)
    var = np.maximum(_box_mean(image * image, block) - mean * mean, 0.0)
    std = np.sqrt(var) + 1e-6
    worst = np.full((height, width), -1.0, np.float32)
    for shift in range(1, max_shift + 1):
        shifted = np.zeros_like(image)
        shifted[:, : width - shift] = image[:, shift:]
        cross = _box_mean(image * shifted, block)
        m2 = np.zeros_like(mean)
        m2[:, : width - shift] = mean[:, shift:]
        s2 = np.full_like(std, np.inf)
        s2[:, : width - shift] = std[:, shift:]
        zncc = (cross - mean * m2) / (std * s2)
        np.maximum(worst, zncc, out=worst)
        # the same pair seen from the other window (shift -s)
        back = np.full_like(zncc, -1.0)
        back[:, shift:] = zncc[:, : width - shift]
        np.maximum(worst, back, out=worst)
    return worst


def _place_dots(tile: np.ndarray, region: np.ndarray, density: float, rng: np.random.Generator) -> int:
    """Add 1-px dots inside ``region`` until it holds ``density`` lit pixels, in place; return how many dots found
    no room (0 when the density was reached).

    Like the real Kinect pattern, dots never touch (not even diagonally): candidates
    are visited in random order and kept only if their 3x3 neighbourhood is dark
    (random sequential adsorption), which spreads the dots evenly (blue noise).
    """
    height, width = tile.shape
    target = int(round(density * region.sum())) - int(tile[region].astype(bool).sum())
    padded = np.zeros((height + 2, width + 2), bool)
    padded[1:-1, 1:-1] = tile > 0
    for flat in rng.permutation(np.flatnonzero(region)):
        if target <= 0:
            break
        y, x = divmod(int(flat), width)
        if not padded[y : y + 3, x : x + 3].any():
            padded[y + 1, x + 1] = True
            tile[y, x] = 1
            target -= 1
    return max(target, 0)


def generate_pattern(
    width: int,
    height: int,
    seed: int = 0,
    density: float = 0.11,
    tiles: tuple[int, int] = (3, 3),
    block: int = 9,
    max_shift: int = 110,
    max_ambiguity: float = 0.7,
    repair_rounds: int = 12,
) -> np.ndarray:
    """A Kinect-like dot pattern, unambiguous along rows within ``max_shift`` px.

    Args:
        width, height: pattern size in projector pixels.
        seed: random seed (the same seed gives the same pattern).
        density: fraction of lit pixels (real Kinect V1: 0.111).
            Dots that never touch jam at about 0.19: a higher density raises ``ValueError``.
        tiles: (columns, rows) of identical tiles, each with a centre marker. The
            tile width must exceed ``max_shift + block`` so that repeats are out of range.
        block: matching window w (px) whose uniqueness is enforced.
        max_shift: disparity range D (px) within which windows must be unique.
        max_ambiguity: windows whose second-best ZNCC exceeds this are re-drawn.
        repair_rounds: how many re-draw passes at most.

    Returns:
        (height, width) uint8: 0 background, DOT_VALUE dots, MARKER_VALUE markers.
        Dots are 1 px and never touch (as in the real pattern); tile seams are ignored
        by that rule, which only matters for tile-edge pixels.
    """
    cols, rows = tiles
    tile_w, tile_h = math.ceil(width / cols), math.ceil(height / rows)
    if tile_w <= max_shift + block:
        raise ValueError(f"tile width {tile_w} px must exceed max_shift + block = {max_shift + block} px")
    if not 0.0 < density < 1.0:
        raise ValueError(f"density must be in (0, 1), got {density}")
    rng = np.random.default_rng(seed)
    tile = np.zeros((tile_h, tile_w), np.uint8)
    if _place_dots(tile, np.ones_like(tile, bool), density, rng):
        # Random sequential adsorption of dots that never touch jams near 0.19 of the pixels.
        raise ValueError(f"density {density}: 1-px dots that never touch fill at most {tile.mean():.3f} of the "
                         f"pattern (real Kinect V1: 0.111)")  # fmt: skip
    # Repair windows that are ambiguous within the tile (wrapped so tile seams are repaired too).
    reach = max_shift + block
    for _ in range(repair_rounds):
        wrapped = np.concatenate([tile, tile, tile], axis=1)[:, tile_w - reach : 2 * tile_w + reach]
        ambiguity = row_ambiguity(wrapped, block, max_shift)[:, reach : reach + tile_w]
        bad = ambiguity > max_ambiguity
        if not bad.any():
            break
        # Re-draw the dots under the centres of bad windows (a small neighbourhood).
        grow = cv2.dilate(bad.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
        tile[grow] = 0
        _place_dots(tile, grow, density, rng)
    tile = tile * DOT_VALUE
    full = np.tile(tile, (rows, cols))[:height, :width].copy()
    for r in range(rows):
        for c in range(cols):
            cy, cx = r * tile_h + tile_h // 2, c * tile_w + tile_w // 2
            full[max(cy - 1, 0) : cy + 2, max(cx - 1, 0) : cx + 2] = MARKER_VALUE
    return full.astype(np.uint8)


def load_pattern(path: str | Path) -> np.ndarray:
    """Read a pattern image as float32 (H, W) in 8-bit units (0..255); colour is averaged."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: pattern file not found")
    image = read_image(path, "pattern image")
    if image.ndim == 3:
        image = image[..., :3].mean(axis=2)
    image = image.astype(np.float32)
    if image.max() <= 0:
        raise InputError(f"{path}: pattern image is all dark")
    if image.max() <= 1.0:
        image = image * 255.0  # a 0/1 binary pattern
    elif image.max() > 255.0:
        image = image * (255.0 / image.max())  # 16-bit
    return image


@dataclass(frozen=True)
class PatternGeometry:
    """Where the pattern sits on the projector's image plane.

    Projector pixel (u_p, v_p) maps to pattern pixel ((u_p - u0) / scale, (v_p - v0) / scale).
    """

    u0: float
    v0: float
    scale: float  # projector px per pattern px


def fit_pattern(pattern_shape: tuple[int, int], width: int, height: int, pad_left: float, margin: float) -> PatternGeometry:
    """Place a pattern so it covers u_p in [-pad_left - margin, width + margin] and v_p in [-margin, height + margin].

    The pattern is centred on that region and scaled up if it is too small to cover it.
    """
    ph, pw = pattern_shape
    need_w = width + pad_left + 2 * margin
    need_h = height + 2 * margin
    scale = max(need_w / pw, need_h / ph, 1.0)
    centre_u = (width - pad_left) / 2.0 - 0.5
    centre_v = (height - 1) / 2.0
    return PatternGeometry(centre_u - scale * (pw - 1) / 2.0, centre_v - scale * (ph - 1) / 2.0, scale)


def _psf_peak(sigma_x: float, sigma_y: float, box_x: int, box_y: int) -> float:
    """Peak of a unit box of box_x x box_y raster pixels blurred by a Gaussian (raster px)."""
    dot = np.zeros((8 * box_y + 1, 8 * box_x + 1), np.float32)
    cy, cx = dot.shape[0] // 2, dot.shape[1] // 2
    dot[cy - box_y // 2 : cy - box_y // 2 + box_y, cx - box_x // 2 : cx - box_x // 2 + box_x] = 1.0
    return float(cv2.GaussianBlur(dot, (0, 0), sigmaX=sigma_x, sigmaY=sigma_y).max())


#: Seed of the dots' fixed offsets from the pattern lattice (PatternField ``dot_jitter_px``).
DOT_JITTER_SEED = 20120917


def unit_seed(base: int, unit: int = 0) -> int | list[int]:
    """numpy seed of a fixed random property of one unit of the device: ``base`` for unit 0 (the unit ddsgen renders
    with, whose draws predate units), ``[base, unit]`` for another."""
    return base if unit == 0 else [base, int(unit)]


def dot_jitter_seed(unit: int = 0) -> int | list[int]:
    """numpy seed of the dots' fixed offsets of one unit of the device (0: the unit ddsgen renders with)."""
    return unit_seed(DOT_JITTER_SEED, unit)


class PatternField:
    """The projected pattern as a continuous, differentiable intensity field.

    Built once per sensor. Each pattern pixel is a square dot of one projector pixel
    (times ``geometry.scale``) convolved with a Gaussian point-spread function of
    sigma ``psf_px`` projector pixels (normalised so a lone dot's peak keeps its value),
    rendered on a raster super-sampled ``supersample`` times in x and ``supersample // 2``
    in y, then sampled bilinearly.

    Args:
        pattern: (Hp, Wp) float32 pattern image in 8-bit units.
        geometry: placement of the pattern on the projector image plane.
        psf_px: point-spread sigma (projector px).
        supersample: super-sampling factor along x (rows are sampled at half that).
        dot_jitter_px: each dot is moved off the pattern's pixel lattice by a fixed random offset,
            uniform in [-j/2, j/2) projector px in x and y (on the raster: steps of 1/supersample px
            in x, 2/supersample in y). A real projector's dots (a diffractive element's) do not sit on
            the camera's pixel lattice; dots that all do see the same sub-pixel phase on a
            fronto-parallel surface, so the matcher's phase-dependent error becomes one bias there
            instead of noise. 0: the lattice (the paper's raster pattern).
        unit: which unit of the device: another unit's dots sit at other fixed offsets
            (:func:`dot_jitter_seed`; only with ``dot_jitter_px`` > 0).
    """

    def __init__(self, pattern: np.ndarray, geometry: PatternGeometry, psf_px: float = 0.5, supersample: int = 4,
                 dot_jitter_px: float = 0.0, unit: int = 0):
        self.geometry = geometry
        self.sx = int(supersample)
        self.sy = max(int(supersample) // 2, 1)
        ph, pw = pattern.shape
        # Raster covering the pattern plus a border for the PSF, in projector px.
        border = 3.0 * psf_px + 1.0
        self.origin_u = geometry.u0 - 0.5 * geometry.scale - border
        self.origin_v = geometry.v0 - 0.5 * geometry.scale - border
        out_w = int(math.ceil((pw * geometry.scale + 2 * border) * self.sx))
        out_h = int(math.ceil((ph * geometry.scale + 2 * border) * self.sy))
        # Nearest-neighbour upsampling of each dot onto the raster (box dot), then the Gaussian PSF.
        us = self.origin_u + (np.arange(out_w) + 0.5) / self.sx
        vs = self.origin_v + (np.arange(out_h) + 0.5) / self.sy
        col = np.floor((us - geometry.u0) / geometry.scale + 0.5).astype(np.int64)
        row = np.floor((vs - geometry.v0) / geometry.scale + 0.5).astype(np.int64)
        inside_c = (col >= 0) & (col < pw)
        inside_r = (row >= 0) & (row < ph)
        raster = np.zeros((out_h, out_w), np.float32)
        if dot_jitter_px > 0:
            raster = self._jittered_raster(pattern, geometry, dot_jitter_px, out_h, out_w, unit)
        else:
            raster[np.ix_(inside_r, inside_c)] = pattern[np.ix_(row[inside_r], col[inside_c])]
        blurred = cv2.GaussianBlur(raster, (0, 0), sigmaX=psf_px * self.sx, sigmaY=psf_px * self.sy)
        # The PSF spreads a dot without dimming it: a lone dot's peak keeps its pattern value
        # (the IR counts of a dot centred on a pixel, as in Landau et al.'s binary-dot model).
        raster = blurred * np.float32(1.0 / _psf_peak(psf_px * self.sx, psf_px * self.sy, self.sx, self.sy))
        self.raster = torch.from_numpy(raster)  # (Hs, Ws), 8-bit units
        self.extent_u = (self.origin_u, self.origin_u + out_w / self.sx)
        self.extent_v = (self.origin_v, self.origin_v + out_h / self.sy)

    def _jittered_raster(self, pattern: np.ndarray, geometry: PatternGeometry, jitter_px: float, out_h: int,
                         out_w: int, unit: int) -> np.ndarray:
        """The box-dot raster with every lit dot moved by its fixed random offset (see ``dot_jitter_px``)."""
        rng = np.random.default_rng(dot_jitter_seed(unit))  # a property of the projector: the same in every process
        offset = (rng.random((2,) + pattern.shape) - 0.5) * jitter_px  # (2, Hp, Wp) projector px
        rows, cols = np.nonzero(pattern > 0)
        values = pattern[rows, cols].astype(np.float32)
        scale = geometry.scale
        # First raster column/row whose centre falls in the moved dot's box [centre - scale/2, centre + scale/2).
        left = geometry.u0 + (cols + offset[0, rows, cols] - 0.5) * scale
        top = geometry.v0 + (rows + offset[1, rows, cols] - 0.5) * scale
        c0 = np.ceil((left - self.origin_u) * self.sx - 0.5).astype(np.int64)
        r0 = np.ceil((top - self.origin_v) * self.sy - 0.5).astype(np.int64)
        box_w, box_h = max(1, int(round(scale * self.sx))), max(1, int(round(scale * self.sy)))
        raster = np.zeros((out_h, out_w), np.float32)
        for dr in range(box_h):
            for dc in range(box_w):
                r, c = r0 + dr, c0 + dc
                inside = (r >= 0) & (r < out_h) & (c >= 0) & (c < out_w)
                np.maximum.at(raster, (r[inside], c[inside]), values[inside])  # touching dots do not add up
        return raster

    def to(self, device) -> "PatternField":
        self.raster = self.raster.to(device)
        return self

    def sample(self, u_p: torch.Tensor, v_p: torch.Tensor) -> torch.Tensor:
        """Pattern intensity (8-bit units) at projector pixel positions; bilinear, differentiable in u_p, v_p.

        Args:
            u_p, v_p: (...) tensors of projector pixel coordinates (same shape).

        Returns:
            (...) tensor; 0 outside the pattern.
        """
        raster = self.raster.to(u_p.dtype)
        hs, ws = raster.shape
        # Continuous raster coordinates of the query (pixel centres at +0.5), normalised to [-1, 1]
        # for grid_sample with align_corners=False.
        x = (u_p - self.origin_u) * self.sx
        y = (v_p - self.origin_v) * self.sy
        # 2 x / ws - 1 and 2 y / hs - 1, in place on the stacked pair (the same operations in the same order)
        grid = torch.stack([x, y], dim=-1).mul_(2.0).div_(torch.tensor([float(ws), float(hs)], dtype=x.dtype,
                                                                          device=x.device)).sub_(1.0)  # fmt: skip
        flat = grid.reshape(1, 1, -1, 2)
        out = F.grid_sample(raster[None, None], flat, mode="bilinear", padding_mode="zeros", align_corners=False)
        return out.reshape(u_p.shape)

    def reference_phases(self, width: int, height: int, pad: int, n_sub: int) -> torch.Tensor:
        """Reference images at infinity, shifted by sub-pixel phases, for the matcher.

        At infinity a camera pixel (u, v) sees projector pixel (u, v) (rectified pair,
        shared intrinsics), so the reference is the field sampled at pixel centres.

        Returns:
            (S, height, width + pad) float32, S = 2^n_sub; column j of phase s holds the
            reference at u = j - pad - s/S (see docs/ARCHITECTURE.md).
        """
        phases = 2 ** n_sub
        u = torch.arange(width + pad, dtype=torch.float32) - pad
        v = torch.arange(height, dtype=torch.float32)
        out = []
        for s in range(phases):
            uu = (u - s / phases)[None, :].expand(height, -1)
            vv = v[:, None].expand(-1, width + pad)
            out.append(self.sample(uu, vv))
        return torch.stack(out).contiguous()


def pattern_requirements(preset) -> dict:
    """Size (px) and uniqueness range a generated pattern needs for a preset.

    The pattern must cover the camera's field of view plus the largest disparity
    (with the 15 % head-room the sensor pads its reference with) on the side it shifts
    from, plus a window-sized margin all round.
    """
    max_shift = int(math.ceil(preset.disparity_max_px * 1.15))
    pad = max_shift + preset.block_size_px
    margin = preset.block_size_px + 2
    width = preset.width_px + pad + 2 * margin
    height = preset.height_px + 2 * margin
    # Round up to multiples of 3 tiles x 10 px for tidy tile sizes.
    width, height = int(math.ceil(width / 30.0) * 30), int(math.ceil(height / 30.0) * 30)
    return {"width": width, "height": height, "block": preset.block_size_px, "max_shift": max_shift}


def pattern_statistics(pattern: np.ndarray, block: int, max_shift: int) -> dict:
    """Dot density and row ambiguity (second-best ZNCC within ``max_shift`` px) of a pattern.

    Windows within ``max_shift + block`` px of the left/right border and ``block`` px of the
    top/bottom are left out (their shifted partners leave the image).
    """
    ambiguity = row_ambiguity(pattern, block, max_shift)
    edge_x, edge_y = max_shift + block, block
    inner = ambiguity[edge_y:-edge_y, edge_x:-edge_x] if ambiguity.shape[1] > 2 * edge_x else ambiguity[edge_y:-edge_y]
    lit = pattern > 0.5 * pattern.max()
    return {
        "height": int(pattern.shape[0]),
        "width": int(pattern.shape[1]),
        "lit_fraction": float(lit.mean()),
        "second_best_zncc_median": float(np.median(inner)),
        "second_best_zncc_p99": float(np.percentile(inner, 99)),
        "second_best_zncc_max": float(inner.max()),
        "ambiguous_fraction": float((inner > 0.9).mean()),
    }
