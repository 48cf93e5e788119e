"""Uncertainty of each fitted parameter: the loss curvature with a sandwich over image tiles.

The fit minimises L(theta) = sum_u w_u L_u(theta), a sum over independent pieces of evidence:
the tiles u of every fit frame (squares of :data:`TILE_WINDOWS` x the loss's local window,
weighted by their share w_u of their frame's region, over the number of frames). For one
parameter with stored value x (its log for log-stored parameters), central finite differences
with the same noise draws (common random numbers) give each tile's slope g_u and the curvature
H = sum_u w_u L_u'' (+ the prior's). The M-estimator's standard error is then

    sigma_x = sqrt(U / (U - 1) * sum_u (g_u - mean g)^2) / H

(the "sandwich": how much the minimum would move if the tiles were drawn again, over how
sharply the loss holds it). It needs no gradient, so it also covers the 1-D searches' eta_c /
sigma (evaluated on the search's own terms). One frame is enough: its tiles are the samples.
The baseline found from the disparity lattice gets the half width of the lattice coherence
peak instead (the loss is flat in it, :mod:`ddsgen.fit.fitting`). Each parameter is treated
alone (the diagonal): correlated parameters get an optimistic sigma.

Reported in physical units (``sigma`` of the preset key's value; a log parameter's relative
error times its value); ``inf`` when the curvature is not positive (the data do not hold the
parameter: "not identified").
"""

from __future__ import annotations

import dataclasses
import math

import torch

from ddsgen.fit.device_keys import integer_key, is_device_key, set_key, stored
from ddsgen.fit.parameters import physical_values
from ddsgen.fit.tiles import crop_frame
from ddsgen.realscan.losses import (
    LossWeights,
    frame_loss,
    local_window,
    snr_search_weights,
)
from ddsgen.realscan.simulate import simulate

#: Tile side in loss windows (15 px at 640 x 480 -> 90 px tiles).
TILE_WINDOWS = 6
#: Fewest tiles a sigma is estimated from before the tiles get smaller (TILE_WINDOW_STEPS: their widths in windows).
MIN_TILES = 8
TILE_WINDOW_STEPS = (TILE_WINDOWS, 3, 2, 1)
#: A tile counts when at least this share of it is in the region.
MIN_TILE_SHARE = 0.25
#: Step of unbounded effect raw values.
EFFECT_STEP = 0.1


def tile_masks(frame) -> list[tuple[torch.Tensor, float]]:
    """(mask, weight) of the tiles of ``frame``'s region; the weights sum to 1 over the frame's tiles. Tiles are
    :data:`TILE_WINDOWS` loss windows wide; a region too small for :data:`MIN_TILES` of them (the objects of one
    frame: ``--region objects`` on the cat gives none) gets tiles of fewer windows, down to one (smaller tiles share
    more of their noise, so the sigma they give is a lower estimate)."""
    window = local_window(frame.intrinsics.fx)
    for windows in TILE_WINDOW_STEPS:
        tiles = _tiles(frame.region, windows * window)
        if len(tiles) >= MIN_TILES:
            break
    return tiles


def _tiles(region: torch.Tensor, size: int) -> list[tuple[torch.Tensor, float]]:
    height, width = region.shape
    out = []
    for y in range(0, height, size):
        for x in range(0, width, size):
            mask = torch.zeros_like(region)
            mask[y : y + size, x : x + size] = True
            mask &= region
            n = int(mask.sum())
            if n >= MIN_TILE_SHARE * size * size:
                out.append((mask, n))
    total = max(sum(n for _, n in out), 1)
    return [(mask, n / total) for mask, n in out]


#: Margin (px) around a tile when its loss is computed on a crop: the loss's filters reach 1 px (Sobel) and
#: its local means only average masked pixels, so 2 px give the loss of the tile on the whole frame.
TILE_CROP_MARGIN = 2


def _tile_losses(sensor, frames, tiles, seed, weights, crop: bool = True) -> list[float]:
    """Loss of every tile (weighted), one simulation per frame. ``crop``: each tile's loss on its own
    window (+ :data:`TILE_CROP_MARGIN`) instead of the whole frame masked to it (same value, ~tiles x cheaper)."""
    values = []
    with torch.no_grad():
        for frame, frame_tiles in zip(frames, tiles):
            sim = simulate(sensor, frame, seed)
            for mask, w in frame_tiles:
                piece_sim, piece = sim, dataclasses.replace(frame, region=mask)
                if crop:
                    rows, cols = torch.nonzero(mask, as_tuple=True)
                    y0, x0 = max(int(rows.min()) - TILE_CROP_MARGIN, 0), max(int(cols.min()) - TILE_CROP_MARGIN, 0)
                    y1, x1 = int(rows.max()) + 1 + TILE_CROP_MARGIN, int(cols.max()) + 1 + TILE_CROP_MARGIN
                    piece = crop_frame(frame, (x0, y0, min(x1, frame.shape[1]) - x0, min(y1, frame.shape[0]) - y0))
                    sl = (slice(y0, y0 + piece.shape[0]), slice(x0, x0 + piece.shape[1]))
                    piece = dataclasses.replace(piece, region=mask[sl])
                    piece_sim = dataclasses.replace(sim, **{k: getattr(sim, k)[sl] for k in ("depth", "valid", "valid_soft")})
                loss = frame_loss(piece_sim, piece, weights)["total"]
                values.append(w * float(loss) / len(frames))
    return values


def sandwich_sigma(minus: list[float], centre: list[float], plus: list[float], step: float,
                   extra_curvature: float = 0.0) -> float:  # fmt: skip
    """Standard error of the stored value from per-tile losses at x - h, x, x + h (see the module docstring)."""
    u = len(centre)
    if u < 2:
        return math.inf
    slopes = [(p - m) / (2.0 * step) for m, p in zip(minus, plus)]
    curvature = sum((p - 2.0 * c + m) for m, c, p in zip(minus, centre, plus)) / step**2 + extra_curvature
    if not curvature > 0:
        return math.inf
    mean = sum(slopes) / u
    spread = u / (u - 1) * sum((g - mean) ** 2 for g in slopes)
    return math.sqrt(spread) / curvature


def estimate_uncertainty(sensor, frames, result, table: dict, *, seed: int = 0, weights: LossWeights = LossWeights(),
                         priors=None, names=None) -> dict[str, dict]:  # fmt: skip
    """Uncertainty of every scalar parameter of ``result`` (a FitResult) at the sensor's current values.

    Args:
        sensor: the fitted DepthSensor (restored unchanged on return).
        frames: the fit frames.
        result: :class:`~ddsgen.fit.fitting.FitResult` (its params and searches).
        table: ``SENSOR_PARAMS`` (name -> :class:`~ddsgen.fit.priors.SensorParam`).
        weights: the fit's loss weights; priors: the fit's :class:`~ddsgen.fit.priors.Priors` (its curvature).
        names: only these of ``result.params`` (default all).

    Returns:
        name -> {"key", "value", "sigma", "relative", "method"}; CNN weights are left out.
    """
    tiles = [tile_masks(f) for f in frames]
    cache: dict[LossWeights, list[float]] = {}
    effects = {e.name: e for e in sensor.effects}
    snr = result.searches.get("snr", {}).get("parameter")
    out: dict[str, dict] = {}
    for name in result.params:
        if name == "cnn" or (names is not None and name not in names):
            continue
        if name in table and is_device_key(table[name]):
            out[name] = _device_key_entry(sensor, frames, tiles, name, table[name], result, seed, weights, priors)
            continue
        if name in table:
            spec = table[name]
            tensor, key, step, log = getattr(sensor, spec.attr), spec.key, spec.step, spec.log
        else:
            effect_name, _, raw_key = name[len("effect:"):].partition(".")
            effect = effects[effect_name]
            tensor, key, step, log = effect.raw[raw_key], name, EFFECT_STEP, False
        if tensor.numel() != 1:
            continue
        value = _physical(sensor, name, table)
        if name == "baseline" and "baseline" in result.searches:
            info = result.searches["baseline"]
            sigma = info["hwhm"] if info["accepted"] else math.inf
            out[name] = _entry(key, value, sigma, "half width of the disparity-lattice coherence peak"
                               if info["accepted"] else "not identified: the lattice search did not accept")  # fmt: skip
            continue
        if name in ("emitted_intensity", "read_noise_std") and snr is not None and name != snr:
            out[name] = _entry(key, value, math.nan, f"held: only the ratio eta_c / sigma is identifiable ({snr} fitted)")
            continue
        searched = name == snr
        w = snr_search_weights(weights.plane_nuisance) if searched else weights
        if w not in cache:
            cache[w] = _tile_losses(sensor, frames, tiles, seed, w)
        x0 = float(tensor.detach())
        sides = []
        for delta in (-step, step):
            with torch.no_grad():
                tensor.fill_(x0 + delta)
            sides.append(_tile_losses(sensor, frames, tiles, seed, w))
            if name not in table:
                sides[-1] = (sides[-1], float(effect.value(raw_key).detach()))
        with torch.no_grad():
            tensor.fill_(x0)
        if name not in table:  # effect: convert the raw value's sigma with the finite-difference derivative
            (minus, v_minus), (plus, v_plus) = sides
        else:
            minus, plus = sides
        curvature = 0.0 if (searched or priors is None) else priors.curvature(name)
        sigma_stored = sandwich_sigma(minus, cache[w], plus, step, curvature)
        if name not in table:
            sigma = abs(v_plus - v_minus) / (2.0 * step) * sigma_stored
        elif log:
            sigma = abs(value) * sigma_stored
        else:
            sigma = sigma_stored
        method = "loss curvature, sandwich over tiles" + (" (search terms)" if searched else "")
        out[name] = _entry(key, value, sigma, method)
    return out


def _device_key_entry(sensor, frames, tiles, name, spec, result, seed, weights, priors) -> dict:
    """A device key (:mod:`ddsgen.fit.device_keys`): the same sandwich, the preset value stepped by ``spec.step``
    (at least 1 for integer keys) in stored units; the search's prior adds its curvature."""
    search = result.searches.get(name, {})
    value = float(getattr(sensor.preset, spec.key))
    if search.get("held"):
        return _entry(spec.key, value, math.nan, search["method"])
    if spec.log and value <= 0:
        return _entry(spec.key, value, math.nan, "switched off in the input: not fitted")
    step = max(1.0, round(spec.step)) if integer_key(sensor, spec.key) and not spec.log else spec.step
    x0 = stored(spec, value)
    lo, hi = spec.stored_bounds(stored(spec, float(search.get("start", value))))
    if x0 - step < lo - 1e-9 or x0 + step > hi + 1e-9:  # one-sided at a bound: step inwards twice
        x0 = min(max(x0, lo + step), hi - step)
    sides = []
    for x in (x0 - step, x0, x0 + step):
        set_key(sensor, spec.key, math.exp(x) if spec.log else x)
        sides.append(_tile_losses(sensor, frames, tiles, seed, weights))
    set_key(sensor, spec.key, value)
    curvature = 2.0 * priors.prior_mm / spec.width**2 if priors is not None else 0.0
    sigma_stored = sandwich_sigma(*sides, step, curvature)
    sigma = abs(value) * sigma_stored if spec.log else sigma_stored
    return _entry(spec.key, value, sigma, "loss curvature, sandwich over tiles (1-D grid search)")


def _physical(sensor, name: str, table: dict) -> float:
    values = physical_values(sensor)
    return float(values[table[name].key] if name in table else values[name])


def _entry(key: str, value: float, sigma: float, method: str) -> dict:
    relative = sigma / abs(value) if value and math.isfinite(sigma) else math.nan
    return {"key": key, "value": value, "sigma": sigma, "relative": relative, "method": method}
