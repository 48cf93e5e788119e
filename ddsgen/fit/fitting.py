"""Fit the sensor's parameters to real scans: what is identifiable, and how.

:func:`fit_sensor` fits the parameters named in ``params`` on the prepared fit frames:

* **Adam** (default lr 1e-3, the paper's) on the loss of :mod:`ddsgen.realscan.losses` for every
  parameter that the depth images constrain through a usable gradient: the soft-argmax
  temperature beta, focal length, effect parameters, the post-processing CNN. Parameters
  stored as logarithms (eta_c, noise, beta, baseline, focal scale) and effects' unbounded
  raw values get ``lr * LOG_LR_SCALE``: a step of lr in log space is a relative change of lr,
  so lr = 1e-3 alone would need ~1,100 steps to move eta_c by x3; with the scale
  (30 -> 3 % per step at most) a factor of 3 takes tens of steps. The CNN's weights use lr.
* Two parameters are found by a **1-D search** instead (``search=True``, the default),
  because their effect on depth has no useful gradient:

  - **eta_c / read-noise std (the IR signal-to-noise ratio).** ZNCC is invariant to an affine
    change of the IR image, so depth depends on eta_c and the read-noise std only through
    their ratio (up to 10-bit clipping and rounding): only eta_c / sigma is identifiable. It
    shows in the *validity rate* (low SNR -> low matching confidence -> dropped pixels) and
    in the noise texture; the matcher's confidence carries no gradient, and a per-pixel
    depth loss against an independently noisy scan is minimised by a noise-free simulation.
    So the SNR is set by a golden-section search on log(eta_c) (sigma held; or on log(sigma)
    if only it is fitted) minimising the validity term plus the noise-texture term.
  - **baseline b.** The sensor converts its own disparity with its own baseline, z = f b / d,
    so b cancels from depth except through the disparity quantisation: depth values lie on
    the lattice z = f b / (k s) (s = 2^-n_sub px). b is estimated from the real depth alone by
    maximising the lattice coherence |mean exp(2 pi i f b / (s z))| (a constant disparity
    offset only shifts the phase). The estimate is used only when its coherence is high
    (>= 0.3 and twice that of the start value); a real sensor quantising on another lattice
    (e.g. Kinect's 1/8 px with a 1/4 px preset) leaves b unchanged and says so.

  Searched parameters are not moved by Adam afterwards (their gradients are noise).

Every sensor parameter stays within its bounds (:data:`SENSOR_PARAMS`, :mod:`ddsgen.fit.priors`:
projected after each Adam step, the searches' ranges) and a prior pulls it toward the input
preset (``prior_mm``). With ``start_effects``, a ``disparity_distortion`` grid in the fit starts from the
least-squares solve of :mod:`ddsgen.fit.starts`. What transfers to other scenes is decided by the
caller on held-out frames (:mod:`ddsgen.fit.split`, :mod:`ddsgen.fit.revert`).
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable

import numpy as np
import torch

from ddsgen.errors import InputError
from ddsgen.fit.device_keys import is_device_key, search_device_keys
from ddsgen.fit.parameters import (
    DEFAULT_PARAMS,
    SENSOR_PARAMS,
    physical_values,
    resolve_params,
)
from ddsgen.fit.priors import DEFAULT_PRIOR_MM, Priors
from ddsgen.fit.starts import start_distortion_grid
from ddsgen.fit.tiles import step_tiles
from ddsgen.realscan.losses import LossWeights, frame_loss, snr_search_weights
from ddsgen.realscan.simulate import FrameData, prepare_frames, simulate
from ddsgen.scene_gradients.refine import RefineSettings
from ddsgen.scene_gradients.scan import (
    object_changes,
    refine_scan_frame,
    refine_static_scan,
    static_scenes,
)

LOG_LR_SCALE = 30.0
LATTICE_MIN_COHERENCE = 0.3


@dataclasses.dataclass
class FitResult:
    """Outcome of :func:`fit_sensor`.

    params: the names fitted; before/after: physical values (preset keys) before and after;
    history: one dict per Adam step (step, loss and its terms, mean over the fit frames);
    searches: what the 1-D searches found (see the module docstring); seconds: wall time;
    trainable: number of scalars fitted (sensor parameters + effect parameters + CNN weights);
    bounds: the bounds/prior table of the fitted sensor parameters; at_bound: those that ended on a bound.
    """

    params: list[str]
    before: dict
    after: dict
    history: list[dict]
    searches: dict
    seconds: float
    trainable: int
    bounds: list[dict] = dataclasses.field(default_factory=list)
    at_bound: list[str] = dataclasses.field(default_factory=list)

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


# ------------------------------------------------------------------------------------------ searches


def lattice_coherence(frames: list[FrameData], fb_over_s: np.ndarray, fx_scale: float = 1.0,
                      max_pixels: int = 20000) -> np.ndarray:  # fmt: skip
    """|mean exp(2 pi i * (f b / s) / z)| over the real valid region pixels, for each candidate f b / s."""
    inv_z = []
    for f in frames:
        sel = f.region & f.real_valid
        z = f.real_depth[sel].double().numpy()
        fx = (f.full_intrinsics or f.intrinsics).fx * fx_scale
        inv_z.append(fx / z)  # f / z; times b / s gives the disparity in steps
    x = np.concatenate(inv_z) if inv_z else np.zeros(0)
    if x.size > max_pixels:
        x = x[np.random.default_rng(0).choice(x.size, max_pixels, replace=False)]
    if x.size == 0:
        return np.zeros(len(fb_over_s))
    out = np.empty(len(fb_over_s))
    for i in range(0, len(fb_over_s), 64):
        phase = 2.0 * np.pi * np.outer(fb_over_s[i : i + 64], x)
        out[i : i + 64] = np.abs(np.exp(1j * phase).mean(axis=1))
    return out


def baseline_grid(frames: list[FrameData], baseline_m: float, step_px: float,
                  focal_scale: float = 1.0) -> tuple[np.ndarray, float]:  # fmt: skip
    """(baselines over the fit bounds of ``baseline_m``, the lattice period in b): the period is the change of b
    that moves the nearest real pixel's disparity by one ``step_px``; the grid resolves an eighth of it, so a
    coherent lattice is not missed between grid points."""
    zs = [f.real_depth[f.region & f.real_valid] for f in frames]
    z_min = min((float(z.min()) for z in zs if z.numel()), default=1.0)
    fx = max((f.full_intrinsics or f.intrinsics).fx for f in frames) * focal_scale
    period = step_px * z_min / fx
    _, low, high = SENSOR_PARAMS["baseline"].bound  # factors of the start value
    return np.arange(low * baseline_m, high * baseline_m, period / 8.0), period


def estimate_baseline(sensor, frames: list[FrameData]) -> dict:
    """Baseline from the disparity quantisation lattice of the real depth (see the module docstring).

    Returns a dict: start, estimate, coherence_start, coherence, accepted (bool). Sets the
    sensor's baseline when accepted.
    """
    step = 2.0 ** -sensor.preset.subpixel_level
    b0 = float(sensor.baseline)
    scale = float(sensor.focal_scale)
    grid, period = baseline_grid(frames, b0, step, scale)
    coherence = lattice_coherence(frames, grid / step, scale)
    best = grid[int(np.argmax(coherence))]
    fine = np.linspace(best - period / 8.0, best + period / 8.0, 33)
    fine_coherence = lattice_coherence(frames, fine / step, scale)
    best = float(fine[int(np.argmax(fine_coherence))])
    c_best = float(fine_coherence.max())
    c_start = float(lattice_coherence(frames, np.array([b0 / step]), scale)[0])
    # Uncertainty: the half width at half maximum of the coherence peak (the lattice step it resolves).
    above = fine[fine_coherence >= 0.5 * c_best]
    hwhm = float(max(above.max() - above.min(), fine[1] - fine[0]) / 2.0)
    accepted = c_best >= LATTICE_MIN_COHERENCE and c_best >= 2.0 * c_start and abs(best - b0) > 1e-9
    if accepted:
        with torch.no_grad():
            sensor.log_baseline.fill_(math.log(best))
    return {"method": "disparity quantisation lattice", "start": b0, "estimate": best, "coherence_start": c_start,
            "coherence": c_best, "accepted": bool(accepted), "hwhm": hwhm}  # fmt: skip


def _mean_terms(sensor, frames, seed, weights, grad=False) -> dict:
    totals: dict[str, float] = {}
    context = torch.enable_grad() if grad else torch.no_grad()
    with context:
        for f in frames:
            terms = frame_loss(simulate(sensor, f, seed), f, weights)
            for k, v in terms.items():
                totals[k] = totals.get(k, 0.0) + float(v.detach()) / len(frames)
    return totals


#: Points of the SNR search's coarse grid over the parameter's whole bounds; a search within a span keeps their spacing.
SNR_COARSE_POINTS = 9


def search_snr(sensor, frames: list[FrameData], which: str, seed: int = 0, evaluations: int = 16,
               plane_nuisance: bool = False, span: float | None = None) -> dict:  # fmt: skip
    """Golden-section search of log(eta_c) (``which="emitted_intensity"``) or log(sigma)
    (``"read_noise_std"``) minimising the validity + noise-texture terms on ``frames`` (with
    ``plane_nuisance``, the texture on the objects: :func:`ddsgen.realscan.losses.texture_pixels`).

    ``span``: search only within this factor of the current value (a refit near a fitted optimum), on a
    coarse grid of the same spacing (:data:`SNR_COARSE_POINTS`) and with the same golden-section steps after it;
    None: the parameter's whole bounds."""
    spec = SENSOR_PARAMS[which]
    param = getattr(sensor, spec.attr)
    start = float(param)
    weights = snr_search_weights(plane_nuisance)
    cache: dict[float, float] = {}

    def objective(x: float) -> float:
        if x not in cache:
            with torch.no_grad():
                param.fill_(start + x)
            cache[x] = _mean_terms(sensor, frames, seed, weights)["total"]
        return cache[x]

    start_value = objective(0.0)
    _, lo, hi = spec.bound  # a factor of the start value: the search stays within the bounds
    a, b = math.log(lo), math.log(hi)
    spacing = (b - a) / (SNR_COARSE_POINTS - 1)
    if span is not None:
        a, b = max(a, -math.log(span)), min(b, math.log(span))
    # Coarse grid first (the objective is noisy and may be flat far from the optimum), then golden section.
    grid = np.linspace(a, b, max(3, round((b - a) / spacing) + 1))
    values = [objective(float(x)) for x in grid]
    i = int(np.argmin(values))
    a, b = float(grid[max(i - 1, 0)]), float(grid[min(i + 1, len(grid) - 1)])
    g = (math.sqrt(5.0) - 1.0) / 2.0
    c, d = b - g * (b - a), a + g * (b - a)
    for _ in range(max(evaluations - SNR_COARSE_POINTS - 1, 0)):  # as many steps as after the whole bounds' grid
        if objective(c) < objective(d):
            b, d = d, c
            c = b - g * (b - a)
        else:
            a, c = c, d
            d = a + g * (b - a)
    best = min(cache, key=cache.get)
    with torch.no_grad():
        param.fill_(start + best)
    return {"method": "golden-section search on validity + noise texture", "parameter": which,
            "multiplier": math.exp(best), "objective_start": start_value,
            "objective": cache[best], "evaluations": len(cache)}  # fmt: skip


# ------------------------------------------------------------------------------------------ fit


def fit_sensor(sensor, frames: list[FrameData], params=DEFAULT_PARAMS, steps: int = 100, lr: float = 1e-3,
               progress: bool = True, *, seed: int = 0, weights: LossWeights = LossWeights(), search: bool = True,
               batch_frames: int | None = None, callback: Callable[[int, dict], None] | None = None,
               prior_mm: float = DEFAULT_PRIOR_MM, start_effects: bool = False,
               tile_px: int | None = None, snr_span: float | None = None) -> FitResult:  # fmt: skip
    """Fit ``params`` of ``sensor`` (in place) to the real scans of ``frames``.

    Args:
        sensor: :class:`~ddsgen.sensor.depth_sensor.DepthSensor` built from the preset to start from.
        frames: fit frames from :func:`ddsgen.realscan.simulate.prepare_frames` (keep held-out frames apart).
        params: names (see :func:`resolve_params`); default: the paper's four sensor parameters
            eta_c (``emitted_intensity``), IR read-noise std, soft-argmax beta, baseline.
        steps: Adam steps (0: searches only).
        lr: Adam learning rate (CNN weights; log-space parameters get ``lr * LOG_LR_SCALE``).
        progress: tqdm progress bar with the current loss.
        seed: IR noise seed of the simulations (same draws at every step).
        weights: loss term weights.
        search: find eta_c/sigma and the baseline by the 1-D searches (else Adam moves them too).
        batch_frames: frames per Adam step (cycling through ``frames``); default all.
        callback: called after every step with (step, terms).
        prior_mm: weight of the regulariser toward the start values (:mod:`ddsgen.fit.priors`);
            every table parameter is also kept within its bounds (searches included).
        start_effects: start a fitted ``disparity_distortion`` grid from least squares (:mod:`ddsgen.fit.starts`).
        tile_px: each Adam step simulates a random ``tile_px``-px window of each chosen frame
            (:mod:`ddsgen.fit.tiles`; a stochastic gradient at a fraction of the price); None: whole frames.
        snr_span: the SNR search stays within this factor of the current value (:func:`search_snr`; a refit
            from fitted values); None: the whole bounds.

    Returns:
        :class:`FitResult`.
    """
    from tqdm import tqdm

    start_time = time.perf_counter()
    params = list(dict.fromkeys(params))
    resolved = resolve_params(sensor, params)
    for p in sensor.parameters():
        p.requires_grad_(False)
    before = physical_values(sensor)
    searches: dict = {}
    searched: set[str] = set()
    # The distortion first: the SNR search's validity and texture terms are judged with it in place.
    if start_effects and any(n.startswith("effect:disparity_distortion.d_r") for n in resolved):
        searches["distortion"] = start_distortion_grid(sensor, frames, seed)
    if search and "baseline" in resolved:
        searches["baseline"] = estimate_baseline(sensor, frames)
        searched.add("baseline")
    snr = [n for n in ("emitted_intensity", "read_noise_std") if n in resolved]
    if search and snr:
        searches["snr"] = search_snr(sensor, frames, snr[0], seed, plane_nuisance=weights.plane_nuisance,
                                     span=snr_span)
        searched.update(snr)  # the other one is not identifiable separately: held
    device_keys = [n for n in resolved if n in SENSOR_PARAMS and is_device_key(SENSOR_PARAMS[n])]
    if device_keys:  # always searched: they have no usable gradient (ddsgen.fit.device_keys)
        searches.update(search_device_keys(sensor, device_keys, SENSOR_PARAMS,
                                           lambda: _mean_terms(sensor, frames, seed, weights)["total"], prior_mm))
        searched.update(device_keys)
    groups = []
    for name, tensors in resolved.items():
        if name in searched:
            continue
        for t in tensors:
            t.requires_grad_(True)
        groups.append({"params": tensors, "lr": lr if name == "cnn" else lr * LOG_LR_SCALE, "name": name})
    priors = Priors(sensor, {n: SENSOR_PARAMS[n] for n in resolved if n in SENSOR_PARAMS and n not in searched},
                    prior_mm)  # fmt: skip
    history: list[dict] = []
    if groups and steps > 0:
        optimiser = torch.optim.Adam(groups)
        batch = len(frames) if not batch_frames else min(batch_frames, len(frames))
        bar = tqdm(range(steps), desc="fit", unit="step", disable=not progress, dynamic_ncols=True)
        for step in bar:
            chosen = [frames[(step * batch + i) % len(frames)] for i in range(batch)]
            chosen = step_tiles(chosen, tile_px, step, seed, sensor)
            optimiser.zero_grad(set_to_none=True)
            totals: dict[str, float] = {}
            for f in chosen:
                terms = frame_loss(simulate(sensor, f, seed), f, weights)
                (terms["total"] / len(chosen)).backward()
                for k, v in terms.items():
                    totals[k] = totals.get(k, 0.0) + float(v.detach()) / len(chosen)
            penalty = priors.penalty()
            if penalty.requires_grad:
                penalty.backward()
            totals["prior"] = float(penalty.detach())
            for group in groups:
                for t in group["params"]:
                    if t.grad is not None:
                        t.grad.nan_to_num_(0.0, 0.0, 0.0)
            optimiser.step()
            priors.project()
            totals["step"] = step
            history.append({k: round(v, 5) if isinstance(v, float) else v for k, v in totals.items()})
            bar.set_postfix(loss=f"{totals['total']:.3f}")
            if callback is not None:
                callback(step, totals)
        bar.close()
    for p in sensor.parameters():
        p.requires_grad_(False)
    trainable = sum(t.numel() for tensors in resolved.values() for t in tensors)
    bounded = Priors(sensor, {n: SENSOR_PARAMS[n] for n in resolved if n in SENSOR_PARAMS}, 0.0)
    bounds = bounded.table() + [{"param": n, "key": SENSOR_PARAMS[n].key, "bound": list(SENSOR_PARAMS[n].bound),
                                 "prior_width": SENSOR_PARAMS[n].width, "log": SENSOR_PARAMS[n].log,
                                 "group": SENSOR_PARAMS[n].group} for n in device_keys]  # fmt: skip
    return FitResult(params=list(resolved), before=before, after=physical_values(sensor), history=history,
                     searches=searches, seconds=time.perf_counter() - start_time, trainable=int(trainable),
                     bounds=bounds, at_bound=[n for n in priors.at_bound()])  # fmt: skip


def split_frames(frames: list, holdout: float, seed: int = 0) -> tuple[list, list]:
    """Split into (fit, held-out) frames; held-out gets round(holdout * n) frames (>= 1 when holdout > 0
    and n >= 2), chosen by a seeded permutation. With one frame, both sets are that frame."""
    if not 0.0 <= holdout < 1.0:
        raise InputError(f"--holdout: must be in [0, 1), got {holdout}")
    n = len(frames)
    k = int(round(holdout * n))
    if holdout > 0 and n >= 2:
        k = min(max(k, 1), n - 1)
    if k == 0 or n < 2:
        return list(frames), list(frames)
    order = np.random.default_rng(seed).permutation(n)
    held = sorted(order[:k].tolist())
    return [frames[i] for i in range(n) if i not in held], [frames[i] for i in held]


def fitted_preset(sensor, postprocess_path: str | None = None):
    """The fitted preset: the sensor's preset with the fitted values (``DepthSensor.to_preset``),
    naming ``postprocess_path`` as its CNN weights when given."""
    preset = sensor.to_preset()
    if postprocess_path is not None:
        preset = preset.replace(postprocess=str(postprocess_path))
    return preset


def refine_frame_poses(sensor, preset, scans: list, steps: int, progress: bool = False, seed: int = 0,
                       static_views: int = 0, **prepare_options) -> tuple[list[FrameData], list[dict]]:  # fmt: skip
    """Poses as nuisance parameters (``fit --refine-poses``): refine every scan frame's object poses
    with the current ``sensor`` (:mod:`ddsgen.scene_gradients`), then prepare the frames again at the
    refined poses.

    Args:
        sensor: the sensor being fitted (its current parameters simulate the refinement).
        preset: the preset with the scans' camera; scans: the ScanFrame list (poses replaced in place).
        steps: refinement steps per frame (per static scene); seed: noise seed.
        static_views: 0 refines every frame alone; K > 0 refines the frames of each static scene
            (:func:`ddsgen.scene_gradients.scan.static_scenes`) together, one correction per object
            found on at most K of its frames and applied to all of them (``fit --static-scene``).
        prepare_options: passed to :func:`ddsgen.realscan.simulate.prepare_frames` (support_plane, crop, ...).

    Returns:
        (the new FrameData list, per frame {frame, objects: [{id, rotation_deg, translation_mm}]}).
    """
    settings, plane = RefineSettings(steps=steps, seed=seed), prepare_options.get("support_plane", True)
    refined = {}  # frame name -> {object id: refined cam_T_obj}
    if static_views > 0:
        for first, frames in static_scenes(scans):
            refined.update(refine_static_scan(preset, frames, settings, support_plane=plane, first_index=first,
                                              max_views=static_views, sensor=sensor)[1])  # fmt: skip
    else:
        for index, scan in enumerate(scans):
            refined[scan.name] = refine_scan_frame(preset, scan, index, settings, support_plane=plane,
                                                   sensor=sensor).refined_poses()  # fmt: skip
    changes = []
    for scan in scans:
        ids = [obj.id for obj in scan.objects]
        poses = [refined[scan.name][i] for i in ids]
        changes.append({"frame": scan.name, "objects": object_changes(ids, [o.cam_T_obj for o in scan.objects], poses)})
        for obj, T in zip(scan.objects, poses):
            obj.cam_T_obj = T
    return prepare_frames(preset, scans, seed=seed, progress=progress, **prepare_options), changes

