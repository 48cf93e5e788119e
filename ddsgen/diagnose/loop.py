"""Diagnosis: find where simulation and measurement disagree, name the missing effect, add it, show the gap shrink.

The loop (:func:`diagnose`):

1. **Base fit.** The base sensor parameters are fitted on the fit frames with the fit
   machinery (:func:`ddsgen.fit.fitting.fit_sensor`); the held-out gap (the ``compare``
   metric, :func:`ddsgen.fit.compare.gap`, and its noise floor) of that model is the baseline.
2. **Residual analysis** (:mod:`ddsgen.diagnose.residuals`): bias and validity disagreement
   binned by depth, incidence angle, image radius, row, column, distance to depth edges and
   IR signal; per axis the structure beyond noise (bootstrap over frames).
3. **Candidates.** Every library effect not yet in the model is added in turn and its
   parameters are fitted on the fit frames, maximising the credited fall of the gap (below):
   depth effects start from their signature read off the residual (:func:`signature_guess`:
   a median or a least-squares fit, no extra simulation), validity effects from a coarse
   grid; a local search refines either. Then the held-out gap and noise floor it leaves are
   measured.
4. **Acceptance** (:data:`RULE`). Accepted: named, added, the base parameters refitted with it,
   and the loop repeats with the remaining effects; otherwise it stops.
5. **What remains**: axes whose residual structure is still beyond noise (and at least
   :data:`UNEXPLAINED_MIN_MM`) are reported as unexplained, strongest first, rather than
   naming a wrong effect.

Two things make the comparison fair to every candidate:

* **Credit only what the noise floor does not explain.** Two noise draws of one sensor do not
  score 0: the ``compare`` gap has a noise floor (its ``noise_floor``, measured between two
  draws of the model under test), and a model can lower the gap by *hiding* noise -- a
  dropout effect that removes the noisiest pixels lowers gap and floor alike, even on data
  without such dropout -- while a genuinely missing effect lowers the gap and leaves the
  floor. So a candidate is credited, per frame and with the same noise draws for every model,
  with the fall of its gap minus any fall of its floor (:func:`frame_falls`), and gets
  nothing for making its own draws disagree more.
* **Gaps are reported beyond the noise floor.** ``diagnosis.json``'s gaps are ``compare``'s
  ``excess``: held-out gap minus noise floor (mean over held-out frames), what a better
  model could still remove -- the true sensor scores about 0, so "the gap halves" means half
  of the explainable disagreement is gone. (At 640 x 480 the floor is ~1.5 mm, and a missing
  4-px edge band adds ~0.5 mm to it; in raw gaps no validity effect could ever halve the gap.)
  The raw gaps and floors are printed and in ``report.html``.
* **The support plane is re-estimated under each model** (:func:`replane`). It is fitted to
  the real depth, so it already contains any bias that keeps planes planar (a disparity
  offset, a depth scale error); a model with that effect would apply it twice.

Speed: effects that act after block matching (disparity, depth and validity stages) do not
change the matcher's input, so :func:`reuse_matches` serves the matcher's result from a cache
keyed by the IR image; validity effects do not move the plane either, so their whole search
runs without the matcher and uses every fit frame; depth effects are searched on at most
:attr:`DiagnoseConfig.grid_frames` fit frames.
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import math
from collections.abc import Callable

import numpy as np
import torch

from ddsgen.fit.compare import frame_gap, gap
from ddsgen.fit.fitting import DEFAULT_PARAMS, fit_sensor, split_frames
from ddsgen.diagnose.residuals import AXIS_WORDS, analyse, pixel_residuals
from ddsgen.fit.simulate import simulate
from ddsgen.sensor.effects import REGISTRY
from ddsgen.sensor.effects.features import normalised_coordinates

#: A candidate's credited fall (frame_falls) must be at least this fraction of the held-out gap ...
MIN_RELATIVE_GAIN = 0.05
#: ... and the BOOTSTRAP_QUANTILE-quantile of that gain over resamples of the held-out frames must stay above zero.
BOOTSTRAP_RESAMPLES = 2000
BOOTSTRAP_QUANTILE = 0.05
#: Base parameters fitted first. Not the baseline: fit_sensor estimates it from the disparity quantisation
#: lattice of the real depth, which a depth scale error rescales just like a baseline error would, so a
#: fitted baseline would hide that effect (b itself cancels from z = f b / d).
BASE_PARAMS = tuple(p for p in DEFAULT_PARAMS if p != "baseline")
#: Residual structure below this (mm, beyond noise) is not reported as unexplained.
UNEXPLAINED_MIN_MM = 1.0

RULE = (
    f"Each round, the candidate with the largest credited fall of the held-out gap -- per frame, the fall of the "
    f"gap minus any fall of the model's own noise floor (noise it hides rather than explains), same noise draws "
    f"for every model -- is accepted only if (a) the fall is at least {100 * MIN_RELATIVE_GAIN:.0f} % of the held-out gap "
    f"and (b) it is not carried by a few frames: over {BOOTSTRAP_RESAMPLES} bootstrap resamples of the held-out "
    f"frames (with replacement), the {100 * BOOTSTRAP_QUANTILE:.0f}th percentile of that relative fall stays above "
    f"zero. Residual structure along an axis counts as unexplained when it exceeds twice its bootstrap noise and "
    f"is at least {UNEXPLAINED_MIN_MM:.1f} mm beyond it."
)

#: Coarse search grids (first parameter) per library effect; a local search refines the best point.
GRIDS: dict[str, list[dict]] = {
    "lens_distortion": [{"k1": v} for v in (-0.03, -0.015, -0.006, 0.006, 0.015, 0.03)],
    "disparity_offset": [{"offset_px": v} for v in (-1.0, -0.5, -0.25, -0.1, 0.1, 0.25, 0.5, 1.0)],
    "depth_scale": [{"scale_error": v} for v in (-0.04, -0.02, -0.01, -0.004, 0.004, 0.01, 0.02, 0.04)],
    "grazing_dropout": [{"angle_deg": v} for v in (45.0, 55.0, 62.0, 67.0, 71.0, 75.0, 79.0, 83.0, 87.0)],
    "edge_dropout": [{"width_px": v} for v in (1.0, 1.5, 2.0, 3.0, 4.0, 6.0, 8.0)],
    "low_signal_dropout": [{"threshold_counts": v} for v in (0.5, 0.75, 1.0, 1.5, 2.0, 3.0, 4.0, 6.0, 9.0)],
}


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
      affine term per frame on the support plane (its fit absorbed the affine part there).

    Returns a few parameter sets around the estimate, or None for effects without a shape
    (the validity effects: their grids are cheap, the matcher's result being reused).
    """
    fb = float(sensor.baseline.detach()) * float(sensor.focal_scale.detach())
    rows, targets = [], []
    for i, (f, sim) in enumerate(zip(frames, sims)):
        both = f.region & sim.valid & f.real_valid
        if name != "lens_distortion":
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
        else:
            return None
    if not targets:
        return None
    t = np.concatenate(targets)
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


# ------------------------------------------------------------------------------------------ speed


@contextlib.contextmanager
def reuse_matches():
    """Serve block-matching results from a cache while the matcher's input does not change.

    Inside the context, :func:`ddsgen.sensor.matcher.match` as called by the sensor is wrapped:
    when neither the IR image nor beta needs a gradient, the result for an identical IR image
    (same bytes) and identical settings is computed once and reused. With only post-matching
    effect parameters free, every simulation after the first of a frame skips the matcher.
    """
    import ddsgen.sensor.depth_sensor as depth_sensor

    original = depth_sensor.match
    cache: dict = {}

    def cached_match(observed, reference_phases, pad, d_min, d_max, block, beta, *args, **kwargs):
        needs_grad = observed.requires_grad or (torch.is_tensor(beta) and beta.requires_grad)
        if needs_grad:
            return original(observed, reference_phases, pad, d_min, d_max, block, beta, *args, **kwargs)
        digest = hashlib.blake2b(observed.detach().contiguous().cpu().numpy().tobytes(), digest_size=16).hexdigest()
        key = (digest, tuple(observed.shape), reference_phases.data_ptr(), pad, round(float(d_min), 9),
               round(float(d_max), 9), block, round(float(beta), 9), args, tuple(sorted(kwargs.items())))  # fmt: skip
        if key not in cache:
            cache[key] = original(observed, reference_phases, pad, d_min, d_max, block, beta, *args, **kwargs)
        return cache[key]

    depth_sensor.match = cached_match
    try:
        yield cache
    finally:
        depth_sensor.match = original


# ------------------------------------------------------------------------------------------ support plane


def replane(frame, sim, min_pixels: int = 200, clip_quantile: float = 0.1):
    """``frame`` with its support plane re-estimated under the model that produced ``sim``.

    The support plane of :func:`ddsgen.fit.simulate.prepare_frames` is fitted to the *real*
    depth, so it already contains every bias that keeps a plane a plane (a disparity offset:
    1/z shifts by a constant; a depth scale error) -- simulating a sensor that has the effect
    on that plane would apply it twice. The plane is a nuisance of the comparison, so it is
    re-estimated for each model: one Gauss-Newton step in inverse depth, where a plane is an
    affine function of the normalised pixel coordinates, moves it by the affine fit (trimmed
    least squares) of the inverse-depth residual 1/z_sim - 1/z_real over its pixels valid in
    both. Plane pixels get the new depth, points and normal; objects and masks are unchanged.

    Returns ``frame`` itself when it has no plane or too few plane pixels.
    """
    from ddsgen.fit.simulate import Plane

    if frame.plane is None:
        return frame
    g = frame.geometry
    on_plane = g.hit & (frame.instance == 0)
    use = on_plane & frame.region & sim.valid & frame.real_valid
    if int(use.sum()) < min_pixels:
        return frame
    intr = frame.intrinsics
    h, w = frame.shape
    xn = ((torch.arange(w, dtype=torch.float64) - intr.cx) / intr.fx)[None, :].expand(h, w)
    yn = ((torch.arange(h, dtype=torch.float64) - intr.cy) / intr.fy)[:, None].expand(h, w)
    r = (1.0 / sim.depth.double()[use] - 1.0 / frame.real_depth.double()[use]).numpy()
    a = np.stack([np.ones_like(r), xn[use].numpy(), yn[use].numpy()], 1)
    keep = np.ones(r.shape, bool)
    coef = np.zeros(3)
    for _ in range(3):  # trimmed least squares: drop the largest residuals of the previous fit
        coef = np.linalg.lstsq(a[keep], r[keep], rcond=None)[0]
        dev = np.abs(r - a @ coef)
        keep = dev <= np.quantile(dev, 1.0 - clip_quantile)
    n = np.asarray(frame.plane.normal, np.float64)
    d = float(frame.plane.offset)
    # Plane n.X + d = 0  <=>  1/z = alpha + beta x_n + gamma y_n with (beta, gamma, alpha) = -n / d.
    abc = -n / d - np.array([coef[1], coef[2], coef[0]])
    norm = float(np.linalg.norm(abc))
    new_n, new_d = -abc / norm, 1.0 / norm
    inv = abc[2] + abc[0] * xn + abc[1] * yn
    ok = on_plane & (inv > 1e-6)
    z = torch.where(ok, 1.0 / inv.clamp_min(1e-6), torch.zeros_like(inv)).float()
    points = g.points.clone()
    normals = g.normals.clone()
    xyz = torch.stack([xn.float() * z, yn.float() * z, z], -1)
    points[ok] = xyz[ok]
    normals[ok] = torch.tensor(new_n, dtype=torch.float32)
    clean = torch.where(ok, z, g.clean_depth)
    geometry = dataclasses.replace(g, points=points, normals=normals, clean_depth=clean,
                                   hit=g.hit & (ok | ~on_plane))  # fmt: skip
    ray = -points / torch.linalg.vector_norm(points, dim=-1, keepdim=True).clamp_min(1e-9)
    cos = (ray * normals).sum(-1).clamp(-1.0, 1.0).abs()
    incidence = torch.where(geometry.hit, torch.rad2deg(torch.acos(cos)), torch.full_like(cos, 90.0))
    plane = Plane(normal=new_n, offset=new_d, inliers=frame.plane.inliers, candidates=frame.plane.candidates)
    return dataclasses.replace(frame, geometry=geometry, incidence_deg=incidence.float(), plane=plane)


def replane_all(sensor, frames, seed: int) -> list:
    """Every frame re-planed under ``sensor`` (see :func:`replane`)."""
    out = []
    with torch.no_grad():
        for f in frames:
            out.append(replane(f, simulate(sensor, f, seed)) if f.plane is not None else f)
    return out


#: Validity effects that a lower SNR mimics (both drop the pixels of low signal first): the base fit lowers
#: the SNR to explain such dropout, so their search refits the SNR with the effect in (fit_candidate).
CONFOUNDED_WITH_SNR = ("low_signal_dropout",)

#: Values tried for the other parameters of an effect, one at a time, after its first parameter is set.
SECONDARY_GRIDS: dict[str, dict[str, tuple]] = {
    "lens_distortion": {"k2": (-0.02, -0.01, 0.01, 0.02)},
}


# ------------------------------------------------------------------------------------------ pieces


@dataclasses.dataclass
class DiagnoseConfig:
    """Settings of :func:`diagnose` (defaults sized for a dozen 640x480 frames on 2 cores)."""

    holdout: float = 1.0 / 3.0
    base_params: tuple = BASE_PARAMS
    base_steps: int = 15  # Adam steps of the base fit (after its 1-D searches)
    refit_steps: int = 10  # Adam steps of the refit after accepting an effect
    refine_rounds: int = 2  # halving rounds of the local search around a candidate's best grid point
    lr: float = 1e-3
    batch_frames: int | None = 2
    candidates: tuple | None = None  # effect names; default: the whole library
    max_steps: int = 4
    seed: int = 0
    grid_frames: int = 4  # fit frames used by the candidates' searches
    min_relative_gain: float = MIN_RELATIVE_GAIN


@dataclasses.dataclass
class Evaluation:
    """Gap and noise floor of one model on some frames (per frame and mean, mm)."""

    frame_gaps: list[float]
    frame_floors: list[float]

    @property
    def frame_excess(self) -> np.ndarray:
        return np.asarray(self.frame_gaps) - np.asarray(self.frame_floors)

    @property
    def gap(self) -> float:
        return float(np.mean(self.frame_gaps)) if self.frame_gaps else float("nan")

    @property
    def floor(self) -> float:
        return float(np.mean(self.frame_floors)) if self.frame_floors else float("nan")

    @property
    def excess(self) -> float:
        return self.gap - self.floor


@dataclasses.dataclass
class Candidate:
    effect: str
    params: dict
    fit_score: float
    held: Evaluation
    gain: float = 0.0
    gain_low: float = 0.0
    sensor: object = None


@dataclasses.dataclass
class Step:
    """One accepted effect. ``gap_before``/``gap_after``: held-out gap beyond the noise floor (mm);
    ``before``/``after``: the evaluations (compare gap and floor per frame)."""

    effect: str
    params: dict
    before: Evaluation
    after: Evaluation
    axis: str
    sentence: str
    analysis_before: dict
    analysis_after: dict

    @property
    def gap_before(self) -> float:
        return self.before.excess

    @property
    def gap_after(self) -> float:
        return self.after.excess


@dataclasses.dataclass
class Diagnosis:
    baseline: Evaluation
    steps: list[Step]
    final: Evaluation
    unexplained: list[dict]
    sensor: object
    fit_frames: list
    held_frames: list
    analysis_baseline: dict
    analysis_final: dict
    rounds: list[list[Candidate]]

    @property
    def baseline_gap(self) -> float:
        """Held-out gap of the fitted base sensor beyond the noise floor (mm)."""
        return self.baseline.excess

    @property
    def final_gap(self) -> float:
        """Held-out gap of the final model beyond the noise floor (mm)."""
        return self.final.excess

    def to_dict(self) -> dict:
        """The ``diagnosis.json`` document (exactly this shape; gaps beyond the noise floor, mm)."""
        return {
            "baseline_gap": _f(self.baseline_gap),
            "steps": [{"effect": s.effect, "params": {k: _f(v) for k, v in s.params.items()},
                       "gap_before": _f(s.gap_before), "gap_after": _f(s.gap_after)} for s in self.steps],  # fmt: skip
            "final_gap": _f(self.final_gap),
            "unexplained": [{"axis": u["axis"], "strength": _f(u["strength"])} for u in self.unexplained],
        }


def _f(x) -> float:
    x = float(x)
    return round(x, 6) if math.isfinite(x) else 0.0


def replaned(sensor, frames, seed: int, steps: int = 1) -> list:
    """``frames`` with their support planes re-estimated under ``sensor`` (``steps`` Gauss-Newton steps)."""
    for _ in range(steps):
        frames = replane_all(sensor, frames, seed)
    return frames


def frame_evaluation(sensor, frame, seed: int) -> tuple[float, float]:
    """(gap, noise floor) of one frame, exactly as ``compare`` measures them: the gap between the
    simulation (noise draw ``seed``) and the real scan, and between that simulation and a second
    draw (``seed + 1000``) of the same sensor."""
    sim = simulate(sensor, frame, seed)
    other = simulate(sensor, frame, seed + 1000)
    g = frame_gap(sim, frame)
    twin = dataclasses.replace(frame, real_depth=other.depth, real_valid=other.valid)
    return float(g["gap"] or 0.0), float(frame_gap(sim, twin)["gap"] or 0.0)


def evaluate(sensor, frames, seed: int, replane_steps: int = 0) -> Evaluation:
    """Per-frame gap and noise floor (:func:`frame_evaluation`) of ``sensor``, planes re-estimated first if asked."""
    if replane_steps:
        frames = replaned(sensor, frames, seed, replane_steps)
    gaps, floors = [], []
    with torch.no_grad():
        for f in frames:
            g, fl = frame_evaluation(sensor, f, seed)
            gaps.append(g)
            floors.append(fl)
    return Evaluation(gaps, floors)


def changes_depth(name: str) -> bool:
    """Whether an effect changes depth values (then the support plane must be re-estimated under it)."""
    return REGISTRY[name].stage != "validity"


def with_effect(sensor, name: str, values: dict):
    """A new DepthSensor: ``sensor``'s current parameters plus effect ``name`` at ``values``."""
    from ddsgen.sensor.depth_sensor import DepthSensor

    preset = sensor.to_preset()
    entries = [dict(e) for e in preset.effects] + [{"name": name, **values}]
    new = DepthSensor(preset.replace(effects=entries), intrinsics=sensor.intr, device=sensor.device_)
    for p in new.parameters():
        p.requires_grad_(False)
    return new


def frame_falls(before: Evaluation, after: Evaluation) -> np.ndarray:
    """Per-frame credited fall of the gap: ``(gap_before - gap_after) - max(0, floor_before - floor_after)``.

    A candidate gets no credit for the part of its gap fall that its own noise floor falls too (noise it
    hides, e.g. by dropping the noisiest pixels), and no credit either for making its own draws noisier.
    """
    gb, ga = np.asarray(before.frame_gaps), np.asarray(after.frame_gaps)
    fb, fa = np.asarray(before.frame_floors), np.asarray(after.frame_floors)
    return (gb - ga) - np.maximum(0.0, fb - fa)


def relative_fall(before: Evaluation, after: Evaluation) -> float:
    """Credited fall (:func:`frame_falls`) summed over frames, as a fraction of the gap before."""
    return float(frame_falls(before, after).sum() / max(float(np.sum(before.frame_gaps)), 1e-12))


def bootstrap_fall(before: Evaluation, after: Evaluation, rng: np.random.Generator,
                   resamples: int = BOOTSTRAP_RESAMPLES) -> float:  # fmt: skip
    """The BOOTSTRAP_QUANTILE-quantile of :func:`relative_fall` over resamples of the frames."""
    gb = np.asarray(before.frame_gaps)
    d = frame_falls(before, after)
    n = len(d)
    if n == 0:
        return 0.0
    idx = rng.integers(0, n, size=(resamples, n))
    falls = d[idx].sum(1) / np.maximum(gb[idx].sum(1), 1e-12)
    return float(np.quantile(falls, BOOTSTRAP_QUANTILE))


def fit_candidate(sensor, name: str, frames, config: DiagnoseConfig, base: Evaluation,
                  sims=None) -> tuple[object, dict, float]:  # fmt: skip
    """Add effect ``name`` to (a copy of) ``sensor`` and fit its parameters on ``frames``.

    ``frames`` are fit frames re-planed under ``sensor`` and ``base`` is ``sensor``'s evaluation on
    them. The objective is the acceptance criterion itself: the credited fall of the gap
    (:func:`frame_falls`), with the support plane re-estimated under every trial value of an
    effect that changes depth. The first parameter is searched on a coarse grid,
    then by ``refine_rounds`` rounds of halving the interval around the best value; the other
    parameters on :data:`SECONDARY_GRIDS`. Returns (sensor with the effect, values, -credited fall).
    """
    cls = REGISTRY[name]
    candidate = with_effect(sensor, name, {})
    effect = candidate.effects[-1]
    moves_depth = changes_depth(name)
    tried: dict[tuple, float] = {}

    def objective(values: dict) -> float:
        key = tuple(round(values[k], 9) for k in cls.params)
        if key not in tried:
            effect.set_values(**values)
            trial_frames = replaned(candidate, frames, config.seed) if moves_depth else frames
            tried[key] = -relative_fall(base, evaluate(candidate, trial_frames, config.seed))
        return tried[key]

    neutral = {k: spec.neutral for k, spec in cls.params.items()}
    points = signature_guess(name, sensor, frames, sims) if sims is not None else None
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

    def search() -> dict:
        """Best grid point, refined by halving the interval around it (first parameter), then the others."""
        scores = [objective(v) for v in grid]
        best = dict(grid[int(np.argmin(scores))])
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

    best = search()
    if name in CONFOUNDED_WITH_SNR:
        # The base fit has lowered the SNR to mimic this dropout: search the SNR again with the effect
        # in (the fit machinery's 1-D search), then the effect again at that SNR.
        from ddsgen.fit.fitting import search_snr

        effect.set_values(**best)
        search_snr(candidate, frames[: config.grid_frames or None], "emitted_intensity", config.seed)
        tried.clear()
        best = search()
    effect.set_values(**best)
    return candidate, effect.values(), objective(best)


def analysis_of(sensor, frames, seed: int, edges: dict | None = None, stride: int = 1) -> dict:
    """Residual analysis (stats and structure per axis) of ``sensor`` on ``frames`` (re-planed under it)."""
    frames = replaned(sensor, frames, seed, 1)
    with torch.no_grad():
        sims = [simulate(sensor, f, seed) for f in frames]
    res = pixel_residuals(frames, sims, stride=stride)
    return analyse(res, seed=seed, edges=edges)


def structure_summary(analysis: dict, top: int = 3) -> str:
    items = sorted(analysis.items(), key=lambda kv: -kv[1][1].excess_mm)[:top]
    return ", ".join(f"{axis} {s.excess_mm:.1f} mm (noise {s.noise_mm:.1f})" for axis, (_, s) in items)


def unexplained_axes(analysis: dict) -> list[dict]:
    out = []
    for axis, (_, s) in analysis.items():
        if s.significant and s.excess_mm >= UNEXPLAINED_MIN_MM:
            out.append({"axis": axis, "strength": s.excess_mm})
    return sorted(out, key=lambda u: -u["strength"])


def step_sentence(name: str, params: dict, before: Evaluation, after: Evaluation) -> str:
    cls = REGISTRY[name]
    pct = 100.0 * (1.0 - after.excess / before.excess) if before.excess > 0 else 0.0
    values = ", ".join(f"{k} = {v:.3g} {cls.params[k].unit}".rstrip() for k, v in params.items())
    return (
        f"Missing effect: {name}. {cls.description} With it ({values}) the held-out gap beyond the noise floor "
        f"falls from {before.excess:.2f} mm to {after.excess:.2f} mm ({pct:.0f} % less; compare gap {before.gap:.2f} "
        f"-> {after.gap:.2f} mm, noise floor {after.floor:.2f} mm); the disagreement it removes varied "
        f"{AXIS_WORDS.get(cls.axis, cls.axis)} ({cls.signature})."
    )


def refit(sensor, frames, config: DiagnoseConfig, progress: bool) -> None:
    """Refit the base parameters (and, by Adam, the parameters of accepted effects that change depth) in place.

    Dropout thresholds are left where their search put them: the fit loss, unlike the credited
    fall, rewards dropping noisy pixels.
    """
    names = list(config.base_params) + [f"effect:{e.name}" for e in sensor.effects if changes_depth(e.name)]
    fit_sensor(sensor, frames, names, steps=config.refit_steps, lr=config.lr, progress=progress, seed=config.seed,
               batch_frames=config.batch_frames)  # fmt: skip


# ------------------------------------------------------------------------------------------ the loop


def diagnose(preset, frames, config: DiagnoseConfig | None = None, echo: Callable[[str], None] = print,
             progress: bool = False, analysis_stride: int = 1) -> Diagnosis:  # fmt: skip
    """Run the diagnosis loop (see the module docstring) on prepared frames.

    Args:
        preset: the starting sensor preset (with the scans' camera).
        frames: :func:`ddsgen.fit.simulate.prepare_frames` output (split into fit / held-out here).
        config: settings.
        echo: receives one line per stage (progress output).
        progress: tqdm bars of the fits.
        analysis_stride: pixel subsampling of the residual analysis (1 = every pixel).
    """
    from ddsgen.sensor.depth_sensor import DepthSensor

    config = config or DiagnoseConfig()
    names = list(config.candidates) if config.candidates else sorted(REGISTRY)
    unknown = [n for n in names if n not in REGISTRY]
    if unknown:
        raise ValueError(f"unknown candidate effect(s) {unknown}")
    fit_frames, held = split_frames(frames, config.holdout, config.seed)
    held_seed = config.seed + 1  # held-out gaps use other noise draws than the fit
    rng = np.random.default_rng([config.seed, 77])

    echo(f"[1/5] base fit of {', '.join(config.base_params)} on {len(fit_frames)} fit frame(s) "
         f"({len(held)} held out)")  # fmt: skip
    sensor = DepthSensor(preset)
    fit_sensor(sensor, fit_frames, list(config.base_params), steps=config.base_steps, lr=config.lr, progress=progress,
               seed=config.seed, batch_frames=config.batch_frames)  # fmt: skip
    current = evaluate(sensor, held, held_seed, replane_steps=2)
    baseline = current
    echo(f"      held-out gap {current.gap:.2f} mm, noise floor {current.floor:.2f} mm: "
         f"{current.excess:.2f} mm beyond it")  # fmt: skip

    echo("[2/5] residual analysis (depth, incidence, radius, row, column, edge distance, IR signal) "
         "on the held-out and search frames")
    analysis_frames = held + fit_frames[: config.grid_frames or None]
    analysis = analysis_of(sensor, analysis_frames, held_seed, stride=analysis_stride)
    edges = {axis: stats.edges for axis, (stats, _) in analysis.items()}
    analysis_baseline = analysis
    echo(f"      strongest structure: {structure_summary(analysis)}")

    steps: list[Step] = []
    rounds: list[list[Candidate]] = []
    in_model = {e.name for e in sensor.effects}
    with reuse_matches():
        while len(steps) < config.max_steps:
            todo = [n for n in names if n not in in_model]
            if not todo:
                break
            echo(f"[3/5] round {len(rounds) + 1}: fitting {len(todo)} candidate effect(s) on the fit frames")
            # Depth-changing effects are searched on grid_frames (each trial re-planes and re-matches);
            # validity effects on every fit frame (their trials reuse the matcher's results: cheap).
            all_fit = replaned(sensor, fit_frames, config.seed)
            all_base = evaluate(sensor, all_fit, config.seed)
            with torch.no_grad():
                all_sims = [simulate(sensor, f, config.seed) for f in all_fit]
            n_grid = len(all_fit[: config.grid_frames or None])  # grid frames: the first n_grid fit frames
            grid_frames = all_fit[:n_grid]
            search_sets = {
                True: (grid_frames, Evaluation(all_base.frame_gaps[:n_grid], all_base.frame_floors[:n_grid]),
                       all_sims[:n_grid]),
                False: (all_fit, all_base, all_sims),
            }  # fmt: skip
            results = []
            for name in todo:
                search_frames, search_base, search_sims = search_sets[changes_depth(name)]
                cand_sensor, values, fit_score = fit_candidate(sensor, name, search_frames, config, search_base,
                                                               search_sims)  # fmt: skip
                held_eval = evaluate(cand_sensor, held, held_seed, replane_steps=2)
                c = Candidate(name, values, fit_score, held_eval, sensor=cand_sensor)
                c.gain = relative_fall(current, held_eval)
                c.gain_low = bootstrap_fall(current, held_eval, rng)
                results.append(c)
                echo(f"      {name:20s} held-out gap {held_eval.gap:6.2f} mm (floor {held_eval.floor:5.2f}, beyond it "
                     f"{held_eval.excess:5.2f})  "
                     f"credited fall {100 * c.gain:+6.1f} % (bootstrap 5 %: {100 * c.gain_low:+6.1f} %)"
                     f"  {_fmt(values)}")  # fmt: skip
            rounds.append(results)
            best = max(results, key=lambda c: c.gain)
            if not (best.gain >= config.min_relative_gain and best.gain_low > 0.0):
                echo(f"[4/5] no candidate clears the rule (best: {best.effect}, {100 * best.gain:.1f} %, "
                     f"bootstrap 5 % {100 * best.gain_low:.1f} %): stop")  # fmt: skip
                break
            echo(f"[4/5] accepted {best.effect}; refitting the base parameters with it")
            new = best.sensor
            fit_before = evaluate(new, grid_frames, config.seed, replane_steps=1)
            refit(new, replaned(new, fit_frames, config.seed), config, progress)
            if relative_fall(fit_before, evaluate(new, grid_frames, config.seed, replane_steps=1)) < 0.0:
                new = with_effect(sensor, best.effect, best.params)  # the refit did not help: undo it
                after = best.held
            else:
                after = evaluate(new, held, held_seed, replane_steps=2)
            params = next(e for e in new.effects if e.name == best.effect).values()
            after_analysis = analysis_of(new, analysis_frames, held_seed, edges=edges, stride=analysis_stride)
            steps.append(Step(best.effect, params, current, after,
                              REGISTRY[best.effect].axis, step_sentence(best.effect, params, current, after),
                              analysis, after_analysis))  # fmt: skip
            echo(f"      {best.effect}: held-out gap beyond the noise floor {current.excess:.2f} -> {after.excess:.2f} mm "
                 f"(compare gap {current.gap:.2f} -> {after.gap:.2f} mm; {_fmt(params)})")  # fmt: skip
            sensor, current, analysis = new, after, after_analysis
            in_model.add(best.effect)

    unexplained = unexplained_axes(analysis)
    if unexplained:
        echo("[5/5] unexplained structure: " + ", ".join(f"{u['axis']} {u['strength']:.1f} mm" for u in unexplained))
    else:
        echo("[5/5] no residual structure beyond noise remains")
    return Diagnosis(baseline, steps, current, unexplained, sensor, fit_frames, held, analysis_baseline, analysis,
                     rounds)  # fmt: skip


def _fmt(values: dict) -> str:
    return ", ".join(f"{k}={v:.4g}" for k, v in values.items())
