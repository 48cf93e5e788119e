"""Candidate effects: each library effect added to the model in turn, its parameters searched for the largest
credited fall of the gap (:mod:`ddsgen.diagnose.acceptance`).

Depth effects start from their signature read off the residual (:func:`signature_guess`: a median or a
least-squares fit, no extra simulation), validity effects from a coarse grid (:data:`GRIDS`); a local
search refines either (:func:`fit_candidate`).
"""

from __future__ import annotations

import math

import numpy as np
import torch

from ddsgen.diagnose.acceptance import relative_fall
from ddsgen.diagnose.config import DiagnoseConfig
from ddsgen.diagnose.device_candidates import BEHAVIOURS, fit_behaviour, is_device, sensor_like, with_behaviour
from ddsgen.diagnose.evaluation import Evaluation, evaluate
from ddsgen.diagnose.plane import replaned
from ddsgen.sensor.effects import REGISTRY
from ddsgen.sensor.effects.distortion import GRID_KEYS, fit_distortion_grid
from ddsgen.sensor.effects.features import normalised_coordinates


#: Coarse search grids (first parameter) per library effect; a local search refines the best point.
GRIDS: dict[str, list[dict]] = {
    "lens_distortion": [{"k1": v} for v in (-0.03, -0.015, -0.006, 0.006, 0.015, 0.03)],
    # A warp shows only where depth changes across a pixel or more: at 0.01, 0.6 px in the corners of a Kinect image.
    "lens_warp": [{"k1": v} for v in (-0.08, -0.04, -0.02, -0.01, 0.01, 0.02, 0.04, 0.08)],
    "disparity_offset": [{"offset_px": v} for v in (-1.0, -0.5, -0.25, -0.1, 0.1, 0.25, 0.5, 1.0)],
    "depth_scale": [{"scale_error": v} for v in (-0.04, -0.02, -0.01, -0.004, 0.004, 0.01, 0.02, 0.04)],
    "grazing_dropout": [{"angle_deg": v} for v in (45.0, 55.0, 62.0, 67.0, 71.0, 75.0, 79.0, 83.0, 87.0)],
    "edge_dropout": [{"width_px": v} for v in (1.0, 1.5, 2.0, 3.0, 4.0, 6.0, 8.0)],
    "low_signal_dropout": [{"threshold_counts": v} for v in (0.5, 0.75, 1.0, 1.5, 2.0, 3.0, 4.0, 6.0, 9.0)],
}


#: Validity effects that a lower SNR mimics: their search runs at each of SNR_FACTORS times the fitted emitted
#: intensity (besides 1) and keeps the best pair (see fit_candidate).
CONFOUNDED_WITH_SNR = ("low_signal_dropout",)
SNR_FACTORS = (1.15, 1.3, 1.5, 1.75, 2.0)
#: The factors of a screening search (one frame, :data:`~ddsgen.diagnose.loop.SCREEN_FRACTION`): every other one.
#: The screen asks whether the effect explains anything on held-out frames, not where its optimum lies; each factor
#: costs a front end and the threshold's whole grid (9 trials of two simulations), and with all five the screen was
#: the diagnosis' dearest (8-10 s of the 640 x 480 bench), mostly for candidates crediting nothing.
SCREEN_SNR_FACTORS = (1.3, 1.75)

#: Values tried for the other parameters of an effect, one at a time, after its first parameter is set.
SECONDARY_GRIDS: dict[str, dict[str, tuple]] = {
    "lens_distortion": {"k2": (-0.02, -0.01, 0.01, 0.02)},
}


# ------------------------------------------------------------------------------------------ pieces


def lattice_offset(sensor, frames) -> float:
    """Fractional disparity offset (px, in [0, s)) of the real depth's quantisation lattice, s = 2^-n_sub.

    A quantising sensor reports disparities k s + offset, so the phase of mean exp(2 pi i (f b / z) / s)
    over the real valid pixels is 2 pi offset / s. A disparity offset can only be matched on that lattice
    (off it, every depth step of the simulation sits between the real ones), so its search grid is put there.
    """
    step = 2.0 ** -sensor.preset.subpixel_level
    fb = float(sensor.baseline.detach()) * float(sensor.focal_scale.detach())
    phases = []
    for f in frames:
        sel = f.region & f.real_valid
        z = f.real_depth[sel].double().numpy()
        if z.size:
            phases.append(np.exp(2j * np.pi * (f.intrinsics.fx * fb / z) / step))
    if not phases:
        return 0.0
    phase = float(np.angle(np.concatenate(phases).mean()))
    return (phase / (2.0 * np.pi) % 1.0) * step


def signature_guess(name: str, sensor, frames, sims) -> list[dict] | None:
    """Starting points of an effect's search, read off the current model's residual (no extra simulation).

    The depth effects of the library leave a residual of known shape, so their parameters follow
    from the residual of the model without them by a robust average or a least-squares fit,
    where ``d = f b / z`` is the disparity (px) and ``x, y`` the normalised image coordinates:

    * ``disparity_offset``: delta = median of d_real - d_sim on the objects' pixels (the support
      plane was fitted to the real depth and already carries the offset); put on the real
      depth's quantisation lattice (:func:`lattice_offset`) with its two neighbours;
    * ``depth_scale``: epsilon = median of z_real / z_sim - 1 on the objects' pixels;
    * ``lens_distortion``: a pixel sees the ideal image displaced by du = x f (k1 r^2 + k2 r^4),
      so d_real - d_sim = -du; (k1, k2) by trimmed least squares over every pixel, with an
      affine term per frame on the support plane (its fit absorbed the affine part there);
    * ``disparity_distortion``: d_real - d_sim = D(x, y) exp(-alpha1 d) with alpha1 at its typical
      value; the control grid of D by trimmed least squares (half the pixels kept: on a quantised
      lattice the residual has several peaks), with the same per-frame plane terms.

    * ``grazing_dropout``: the incidence angle beyond which the model's valid pixels are missing in the real frames
      (:func:`grazing_angle_guess`);
    * ``lens_warp``: the k1 whose warp of the model's depth images best matches the real ones (:func:`warp_guess`).

    Returns a few parameter sets around the estimate, or None for effects without a shape
    (the other validity effects: their grids are cheap, the matcher's result being reused).
    """
    if name == "grazing_dropout":
        angle = grazing_angle_guess(frames, sims)
        return None if angle is None else [{"angle_deg": a} for a in (angle - 3.0, angle, angle + 3.0) if a <= 89.0]
    if name == "lens_warp":
        k1 = warp_guess(frames, sims)
        return None if k1 is None else [{"k1": k1 + dk} for dk in (-WARP_STEP, 0.0, WARP_STEP)]
    fb = float(sensor.baseline.detach()) * float(sensor.focal_scale.detach())
    rows, targets, points = [], [], []
    for i, (f, sim) in enumerate(zip(frames, sims)):
        both = f.region & sim.valid & f.real_valid
        if name not in ("lens_distortion", "disparity_distortion"):
            both = both & (f.instance > 0)
        if not bool(both.any()):
            continue
        z_real, z_sim = f.real_depth[both].double(), sim.depth.detach()[both].double()
        if name == "disparity_offset":
            targets.append((f.intrinsics.fx * fb * (1.0 / z_real - 1.0 / z_sim)).numpy())
        elif name == "depth_scale":
            targets.append((z_real / z_sim - 1.0).numpy())
        elif name == "lens_distortion":
            intr = f.intrinsics
            xn, yn = normalised_coordinates(*f.shape, intr.fx, intr.fy, intr.cx, intr.cy)
            x, y = xn[both].double(), yn[both].double()
            plane = (f.instance[both] == 0).double()
            r2 = x * x + y * y
            design = torch.zeros(x.shape[0], 2 + 3 * len(frames), dtype=torch.float64)
            design[:, 0] = -f.intrinsics.fx * x * r2
            design[:, 1] = -f.intrinsics.fx * x * r2 * r2
            design[:, 2 + 3 * i : 5 + 3 * i] = torch.stack([plane, plane * x, plane * y], 1)
            rows.append(design.numpy())
            targets.append((f.intrinsics.fx * fb * (1.0 / z_real - 1.0 / z_sim)).numpy())
        elif name == "disparity_distortion":
            intr = f.intrinsics
            xn, yn = normalised_coordinates(*f.shape, intr.fx, intr.fy, intr.cx, intr.cy)
            x, y = xn[both].double(), yn[both].double()
            plane = (f.instance[both] == 0).double()
            nuisance = torch.zeros(x.shape[0], 3 * len(frames), dtype=torch.float64)
            nuisance[:, 3 * i : 3 * i + 3] = torch.stack([plane, plane * x, plane * y], 1)
            rows.append(nuisance.numpy())
            points.append(torch.stack([x, y, intr.fx * fb / z_sim], 1).numpy())
            targets.append((intr.fx * fb * (1.0 / z_real - 1.0 / z_sim)).numpy())
        else:
            return None
    if not targets:
        return None
    t = np.concatenate(targets)
    if name == "disparity_distortion":
        alpha1 = REGISTRY[name].params["alpha1"].typical * 572.41 / frames[0].intrinsics.fx  # typical at Kinect f
        x, y, d = np.concatenate(points).T
        grid = fit_distortion_grid(x, y, d, t, alpha1=alpha1, nuisance=np.concatenate(rows), keep_quantile=0.5)
        return [{**{k: m * g for k, g in zip(GRID_KEYS, grid)}, "alpha1": alpha1} for m in (0.5, 1.0, 1.5)]
    if name == "lens_distortion":
        a = np.concatenate(rows)
        keep = np.ones(t.shape, bool)
        coef = np.zeros(a.shape[1])
        for _ in range(3):  # trimmed least squares: mismatches and edge pixels are not distortion
            coef = np.linalg.lstsq(a[keep], t[keep], rcond=None)[0]
            dev = np.abs(t - a @ coef)
            keep = dev <= np.quantile(dev, 0.8)
        k1, k2 = (float(np.clip(c, -0.1, 0.1)) for c in coef[:2])
        return [{"k1": m * k1, "k2": m * k2} for m in (0.5, 1.0, 1.5)]
    estimate = float(np.median(t))
    if name == "depth_scale":
        estimate = float(np.clip(estimate, -0.1, 0.1))
        return [{"scale_error": m * estimate} for m in (0.5, 1.0, 1.5)]
    step = 2.0 ** -sensor.preset.subpixel_level
    frac = lattice_offset(sensor, frames)
    k = round((estimate - frac) / step)
    return [{"offset_px": float(np.clip(frac + j * step, -3.0, 3.0))} for j in (k - 1, k, k + 1)]


#: The k1 values :func:`warp_guess` tries, and their spacing (the search's start brackets the guess by one step).
WARP_STEP = 0.01
WARP_K1 = np.round(np.arange(-0.3, 0.3 + WARP_STEP / 2, WARP_STEP), 6)
#: Depth difference (m) at which a pixel counts as a mismatch in :func:`warp_guess` (and what a validity
#: disagreement costs): a robust cost, so that the noise of a far surface does not outweigh a moved edge.
WARP_CAP_M = 0.05


def warp_guess(frames, sims) -> float | None:
    """The k1 of a lens warp read off the model's own depth images: each image warped by every k1 of
    :data:`WARP_K1` (:func:`~ddsgen.sensor.effects.library.warp_index`: no new simulation, the warp is a resampling)
    and compared with the real frame on the objects' pixels in the compared region (an object's pixel in the
    warped image or in the unwarped one) -- |z_real - z_warped| capped at :data:`WARP_CAP_M` where both are valid,
    the cap where one is. The warp moves the objects' depth edges radially, which this cost sees and a mean depth
    bias does not; the support plane is left out, since it was fitted to the real (warped) depth already. None when
    no k1 beats no warp."""
    from ddsgen.sensor.effects.context import EffectContext
    from ddsgen.sensor.effects.library import scene_box, warp_index

    costs = np.zeros(len(WARP_K1))
    for f, sim in zip(frames, sims):
        intr = f.intrinsics
        ctx = EffectContext(fx=intr.fx, fy=intr.fy, cx=intr.cx, cy=intr.cy, baseline=0.0)
        h, w = f.shape
        depth, valid = sim.depth.detach().reshape(-1), sim.valid.reshape(-1)
        objects = f.instance > 0
        real, real_valid = f.real_depth, f.real_valid
        box = scene_box(sim.valid)
        for i, k1 in enumerate(WARP_K1):
            index = warp_index(torch.tensor(float(k1)), torch.tensor(0.0), h, w, ctx, box)
            z, v = depth[index].reshape(h, w), valid[index].reshape(h, w)
            region = f.region & (objects.reshape(-1)[index].reshape(h, w) | objects)
            both = region & v & real_valid
            one = region & (v != real_valid)
            costs[i] += float((real[both] - z[both]).abs().clamp(max=WARP_CAP_M).sum()) + WARP_CAP_M * float(one.sum())
    best = int(np.argmin(costs))
    neutral = int(np.argmin(np.abs(WARP_K1)))
    return None if costs[best] >= costs[neutral] else float(WARP_K1[best])


def grazing_angle_guess(frames, sims, angles=np.arange(30.0, 90.0, 1.0)) -> float | None:
    """The incidence angle (deg) a grazing-angle dropout would have, read off where validity differs.

    Among the pixels the model measures (compared region, simulated valid), a dropout beyond angle a removes those
    seen at more than a. The angle that best separates the real frames' missing pixels from their valid ones there
    -- fewest real-valid pixels removed plus real-missing pixels kept -- is the estimate: a value that would remove
    more valid pixels than the real frames are missing is never chosen. None when no angle separates better than
    removing nothing (no dropout along incidence to find), or without incidence or pixels.
    """
    seen_valid, seen_missing = [], []
    for f, sim in zip(frames, sims):
        incidence = getattr(f, "incidence_deg", None)
        if incidence is None:
            return None
        measured = f.region & sim.valid
        seen_valid.append(incidence[measured & f.real_valid].double().numpy())
        seen_missing.append(incidence[measured & ~f.real_valid].double().numpy())
    valid, missing = np.sort(np.concatenate(seen_valid)), np.sort(np.concatenate(seen_missing))
    if not valid.size or not missing.size:
        return None
    # Errors of "missing beyond a": real-valid pixels beyond a + real-missing pixels at or below a.
    removed_valid = valid.size - np.searchsorted(valid, angles, side="right")
    kept_missing = np.searchsorted(missing, angles, side="right")
    errors = removed_valid + kept_missing
    best = int(np.argmin(errors))
    if errors[best] >= missing.size:  # no better than removing nothing (every missing pixel kept)
        return None
    return float(angles[best])


def default_grid(name: str) -> list[dict]:
    """The search grid of an effect: :data:`GRIDS`, or multiples of each parameter's typical value."""
    if name in GRIDS:
        return GRIDS[name]
    cls = REGISTRY[name]
    grid = []
    for key, spec in cls.params.items():
        typical = spec.typical if spec.typical is not None else 0.5 * (spec.low + spec.high)
        for m in (-2.0, -1.0, -0.5, 0.5, 1.0, 2.0):
            value = spec.neutral + m * (typical - spec.neutral)
            if spec.low <= value <= spec.high and value != spec.neutral:
                grid.append({key: value})
    return grid


def spec(name: str):
    """What the diagnosis reads of a candidate (stage, description, signature, axis, params, generic): the
    library effect's class, or a device behaviour (:mod:`ddsgen.diagnose.device_candidates`)."""
    return BEHAVIOURS[name] if name in BEHAVIOURS else REGISTRY[name]


def changes_depth(name: str) -> bool:
    """Whether an effect changes depth values (then the support plane must be re-estimated under it)."""
    return spec(name).stage != "validity"


def with_candidate(sensor, name: str, values: dict):
    """``sensor`` with candidate ``name`` at ``values``: a library effect added, or a device behaviour switched on."""
    return with_behaviour(sensor, name, values) if is_device(name) else with_effect(sensor, name, values)


def fit_any(sensor, name: str, frames, config: DiagnoseConfig, base: Evaluation, sims=None, screening: bool = False,
            guess_from=None):  # fmt: skip
    """:func:`fit_candidate` for a library effect, :func:`~ddsgen.diagnose.device_candidates.fit_behaviour` for
    a device behaviour; both return (sensor, values, -credited fall). ``screening``: a one-frame screening search
    (:data:`SCREEN_SNR_FACTORS`); ``guess_from``: (frames, sims) the signature guess reads instead of the search's
    (every fit frame: a guess costs no simulation, and the frames a search can afford may not show the effect)."""
    if is_device(name):
        return fit_behaviour(sensor, name, frames, config, base, sims)
    return fit_candidate(sensor, name, frames, config, base, sims, SCREEN_SNR_FACTORS if screening else SNR_FACTORS,
                         guess_from)  # fmt: skip


def copy_of(sensor):
    """A new DepthSensor with ``sensor``'s current parameters and effects (frozen): a snapshot that later
    in-place fitting of ``sensor`` does not change."""
    return sensor_like(sensor, sensor.to_preset())


def with_effect(sensor, name: str, values: dict):
    """A new DepthSensor: ``sensor``'s current parameters plus effect ``name`` at ``values``."""
    preset = sensor.to_preset()
    return sensor_like(sensor, preset.replace(effects=[dict(e) for e in preset.effects] + [{"name": name, **values}]))


def fit_candidate(sensor, name: str, frames, config: DiagnoseConfig, base: Evaluation, sims=None,
                  snr_factors: tuple = SNR_FACTORS, guess_from=None) -> tuple[object, dict, float]:  # fmt: skip
    """Add effect ``name`` to (a copy of) ``sensor`` and fit its parameters on ``frames``.

    ``frames`` are fit frames re-planed under ``sensor`` and ``base`` is ``sensor``'s evaluation on
    them. The objective is the acceptance criterion itself: the credited fall of the gap
    (:func:`frame_falls`), with the support plane re-estimated under every trial value of an
    effect that changes depth. The first parameter is searched on a coarse grid,
    then by ``refine_rounds`` rounds of halving the interval around the best value; the other
    parameters on :data:`SECONDARY_GRIDS`; an effect that a lower SNR mimics (:data:`CONFOUNDED_WITH_SNR`) at
    the fitted SNR and at each of ``snr_factors`` times it. Returns (sensor with the effect, values, -credited fall).
    """
    cls = REGISTRY[name]
    candidate = with_effect(sensor, name, {})
    effect = candidate.effects[-1]
    moves_depth = changes_depth(name)
    tried: dict[tuple, float] = {}

    def objective(values: dict) -> float:
        key = (*(round(values[k], 9) for k in cls.params), round(float(candidate.log_emitted_intensity), 9))
        if key not in tried:
            effect.set_values(**values)
            trial_frames = replaned(candidate, frames, config.seed) if moves_depth else frames
            tried[key] = -relative_fall(base, evaluate(candidate, trial_frames, config.seed))
        return tried[key]

    neutral = {k: spec.neutral for k, spec in cls.params.items()}
    guess_frames, guess_sims = guess_from or (frames, sims)
    points = signature_guess(name, sensor, guess_frames, guess_sims) if guess_sims is not None else None
    guessed = bool(points)
    if not guessed:
        points = default_grid(name)
        if name == "disparity_offset":  # on the real depth's quantisation lattice (see lattice_offset)
            step = 2.0 ** -sensor.preset.subpixel_level
            frac = lattice_offset(sensor, frames)
            points = [{"offset_px": frac + k * step} for k in range(-int(1.0 / step), int(1.0 / step) + 1)
                      if abs(frac + k * step) <= 1.0 and abs(frac + k * step) > 1e-6]  # fmt: skip
    grid = [dict(neutral, **point) for point in points]
    first = next(iter(cls.params))

    def search(refine: bool = True) -> dict:
        """Best grid point, refined by halving the interval around it (first parameter), then the others."""
        scores = [objective(v) for v in grid]
        best = dict(grid[int(np.argmin(scores))])
        if not refine:
            return best
        values = sorted({g[first] for g in grid})
        i = values.index(best[first])
        lo = values[i - 1] if i > 0 else best[first]
        hi = values[i + 1] if i + 1 < len(values) else best[first]
        for _ in range(config.refine_rounds):
            for x in (0.5 * (lo + best[first]), 0.5 * (hi + best[first])):
                trial = dict(best, **{first: x})
                if objective(trial) < objective(best):
                    best = trial
            lo, hi = 0.5 * (lo + best[first]), 0.5 * (hi + best[first])
        for key, options in ({} if guessed else SECONDARY_GRIDS.get(name, {})).items():
            for x in options:
                trial = dict(best, **{key: x})
                if objective(trial) < objective(best):
                    best = trial
        return best

    if name in CONFOUNDED_WITH_SNR:
        # The base fit has lowered the SNR to mimic this dropout (a lower SNR also loses the low-signal pixels
        # first): search SNR and threshold jointly -- the threshold's grid at the fitted SNR and at each
        # SNR_FACTORS multiple of it, then the halving refinement at the best pair only (refining at every
        # factor cost 40 % more trials).
        log_eta = candidate.log_emitted_intensity
        start = float(log_eta.detach())
        scored = []
        for shift in (0.0, *(math.log(f) for f in snr_factors)):
            with torch.no_grad():
                log_eta.fill_(start + shift)
            point = search(refine=False)
            scored.append((objective(point), shift))
        shift = min(scored)[1]
        with torch.no_grad():
            log_eta.fill_(start + shift)
    best = search()
    effect.set_values(**best)
    return candidate, effect.values(), objective(best)
