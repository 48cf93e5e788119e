"""The unpaired fitting loop: render scenes once, then 1-D searches on a feature distance.

1. The fit's scenes: ``sim_frames`` frames sampled from the scene list, ray cast once with the
   preset's camera scaled to the real image size (no calibration: the preset's intrinsics are
   assumed) -- the constant geometry the sensor renders.
2. One evaluation = build the sensor from ``preset.replace(**values)``, render every frame with
   the same noise seeds (common random numbers: the distance is a smooth-ish function of the
   values, not re-drawn noise), round depth like the real files, pool the patch features
   (:mod:`.features`) and measure the distance to the real frames' features.
3. Coordinate search over the table's parameters (:mod:`.parameters`), each on the distance
   terms that identify it (fall-off: validity by radius; clean-up sizes: hole sizes; the others:
   the total): a coarse grid over each parameter's bounds on half the frames; a local walk on
   all frames (+-1 coarse step, moving while it improves: the parameters interact, e.g. a
   lower SNR and a higher confidence threshold both make holes); then a profile of 5 points
   (+-1/2 coarse step) around the best value, and the key's whole coarse grid, all on every
   frame with the other keys at their fitted values: the parabola vertex around the lowest
   point is the fitted value -- unless the input preset's value fits as well (its distance within
   the scene-content scale of the lowest, :mod:`.spread`): then the input's value is kept, as a
   move the frames cannot tell from scene content is not evidence (measured on hidden devices:
   the fall-off went to a bound, 0 or 16, wherever its profile was flat).
4. Uncertainty: a bootstrap over real *and* simulated frames re-sums the cached per-frame
   features of those points (no new rendering) and takes the lowest point and its vertex
   again; the standard deviation of the vertices is the reported uncertainty (conditional on
   the other parameters at their fitted values). The whole range enters because a key that
   barely changes the frames has a distance that is flat next to the real frames' own
   scatter, and a resample of other real frames then puts its minimum anywhere: measured on
   hidden devices, a profile of +-1/2 step reported the fall-off as 16 +- 2 for a hidden 7
   whose fall-off moved the corner validity by 0.003 (docs/validation.md). When more than
   20 % of the vertices sit on the search bounds, the spread is flagged as a lower bound
   (``bootstrap[key]["lower_bound"]``). The continuous keys are then bootstrapped
   together on a quadratic response surface (:mod:`.joint`: trade-offs between keys widen it).
   The reported uncertainty is the largest of the two spreads and the scene-content interval's
   (:mod:`.spread`: the values that fit as well against two halves of the fit scenes).
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np
import torch

from ddsgen.fit.unpaired.features import distance_terms, frame_features, pool
from ddsgen.fit.unpaired.joint import design_offsets, joint_uncertainty
from ddsgen.fit.unpaired.parameters import UnpairedParameter, parameters_for
from ddsgen.fit.unpaired.spread import (
    scene_content_interval,
    scene_content_scale,
    search_std,
)
from ddsgen.realscan.realfolder import RealDepthFrame, round_like
from ddsgen.scene.sampling import sample_frame
from ddsgen.sensor.depth_sensor import DepthSensor
from ddsgen.sensor.sensor_cast import cast_for_sensor

#: Noise stream of the fit's renders (never render's 1 or simulate's 7919).
UNPAIRED_STREAM = 6143
PROFILE_OFFSETS = (-1.0, -0.5, 0.0, 0.5, 1.0)


@dataclasses.dataclass
class UnpairedResult:
    """Outcome of :func:`fit_unpaired`.

    before/after: fitted keys' values; uncertainty: std per key in the value's own unit, the
    largest of the bootstrap's, the joint bootstrap's and the scene-content interval's
    (:mod:`.spread`); uncertainty_search: the same in the search coordinate (natural log of the
    value for log-scale keys: the value is known within a factor exp(std));
    distance_before/after: distance terms; evaluations: number of value sets rendered;
    frames_rendered: frames rendered in all; history: one dict per evaluation (values, frames, terms);
    profiles: per key the profile points, their objective and its terms; seconds: wall time.
    """

    before: dict
    after: dict
    uncertainty: dict
    uncertainty_search: dict
    bootstrap: dict
    distance_before: dict
    distance_after: dict
    evaluations: int
    frames_rendered: int
    history: list
    profiles: dict
    seconds: float

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


def camera_for(preset, width: int, height: int):
    """The preset with its camera scaled to a ``width`` x ``height`` image (same field of view)."""
    if (width, height) == (preset.width_px, preset.height_px):
        return preset
    sx, sy = width / preset.width_px, height / preset.height_px
    # The registration's principal-point shift is in pixels: it scales with the image, as the focal length does.
    return preset.replace(width_px=width, height_px=height, focal_px=preset.focal_px * sx,
                          focal_y_px=preset.focal_y_px * sy, cx_px=(preset.cx_px + 0.5) * sx - 0.5,
                          cy_px=(preset.cy_px + 0.5) * sy - 0.5,
                          registration_shift_px=preset.registration_shift_px * sx)  # fmt: skip


def cast_scenes(preset, scene_list, n_frames: int, seed: int, progress: bool = False) -> list:
    """Sample and ray cast ``n_frames`` frames of the scene list with the preset's camera ->
    list of :class:`~ddsgen.sensor.geometry.SensorGeometry`."""
    from tqdm import tqdm

    out = []
    for i in tqdm(range(n_frames), desc="ray cast", unit="frame", disable=not progress, leave=False):
        scene = sample_frame(scene_list, i, seed)
        out.append(cast_for_sensor(scene, preset.intrinsics, preset, output_shadows=False)[1])
    return out


def render_depths(preset, geometries: list, seed: int, first_index: int = 0) -> list[np.ndarray]:
    """Depth (H, W) m of every geometry rendered by the preset's sensor (no gradients).

    Frame ``k`` of the list is drawn with noise seed ``[seed, first_index + k, UNPAIRED_STREAM]``,
    so rendering frames one slice at a time gives the same bytes as all at once."""
    sensor = DepthSensor(preset).eval()
    with torch.no_grad():
        return [sensor(g, seed=[seed, first_index + i, UNPAIRED_STREAM]).depth.numpy()
                for i, g in enumerate(geometries)]  # fmt: skip


class _Evaluator:
    """Renders the fit scenes for a set of values and measures the distance.

    Per-frame features are cached per set of values and rendered lazily: an evaluation on the
    first ``n`` frames renders only those, and a later one on all frames renders only the rest
    (the coarse pass looks at fewer frames than the profiles; see :func:`fit_unpaired`).
    """

    def __init__(self, preset, geometries, real_features, resolution_m, seed, progress_bar):
        self.preset, self.geometries, self.real = preset, geometries, real_features
        self.resolution_m, self.seed, self.bar = resolution_m, seed, progress_bar
        self.fb = preset.focal_px * preset.baseline_m
        self.cache: dict[tuple, list] = {}
        self.history: list[dict] = []
        self.frames_rendered = 0

    def features(self, values: dict, n_frames: int | None = None) -> list[dict]:
        n_frames = len(self.geometries) if n_frames is None else n_frames
        cached = self.cache.setdefault(tuple(sorted(values.items())), [])
        if len(cached) < n_frames:
            todo = range(len(cached), n_frames)
            depths = render_depths(self.preset.replace(**values), [self.geometries[i] for i in todo], self.seed,
                                   first_index=todo.start)  # fmt: skip
            cached.extend(frame_features(round_like(d, self.resolution_m), self.fb) for d in depths)
            self.frames_rendered += len(todo)
            if self.bar is not None:
                self.bar.update(len(todo))
        return cached[:n_frames]

    def distance(self, values: dict, real_idx=None, sim_idx=None, n_frames: int | None = None) -> dict:
        terms = distance_terms(pool(self.features(values, n_frames), sim_idx), pool(self.real, real_idx))
        if real_idx is None and sim_idx is None:
            self.history.append({"values": dict(values), "frames": n_frames or len(self.geometries), **terms})
        return terms


def _vertex(xs: np.ndarray, ys: np.ndarray) -> float:
    """Argmin of the parabola through (xs, ys) (least squares), kept inside [xs.min(), xs.max()];
    the best point when the parabola opens downwards or there are fewer than 3 points."""
    if len(xs) < 3:
        return float(xs[np.argmin(ys)])
    a, b, _ = np.polyfit(xs, ys, 2)
    if a <= 0:
        return float(xs[np.argmin(ys)])
    return float(np.clip(-b / (2 * a), xs.min(), xs.max()))


def _lowest_vertex(xs: np.ndarray, ys: np.ndarray, span: float) -> float:
    """Vertex of the parabola through the points (xs, ys) within ``span`` of the lowest one
    (least squares: a grid point next to a profile point is harmless)."""
    near = np.abs(xs - xs[int(np.argmin(ys))]) <= span * (1 + 1e-9)
    return _vertex(xs[near], ys[near])


def _scan_points(param: UnpairedParameter, value: float, stock: float) -> list:
    """The key's profile around ``value`` merged with its whole coarse grid and the ``stock`` value, sorted."""
    return sorted(set(_profile_points(param, value, 0.5 * param.step())) | set(param.coarse_grid()) | {stock})


def _profile_points(param: UnpairedParameter, value: float, width: float) -> list:
    if param.choices:
        return param.neighbours(value)
    if param.integer:
        return sorted({param.from_unit(value + d) for d in (-1, 0, 1)})
    centre = param.to_unit(value)
    # distinct points only: near a bound several offsets clip to the bound
    return sorted({param.from_unit(centre + o * width) for o in PROFILE_OFFSETS})


def _walk(param: UnpairedParameter, values: dict, objective, max_moves: int = 4):
    """Local pass of one key: compare the value with its neighbours one coarse step away and move
    to the best, again while it improves (at most ``max_moves``): the coarse pass looked at fewer
    frames and other values of the other keys, so its cell may be a few steps off."""
    current = values[param.key]
    best = objective({**values, param.key: current})
    for _ in range(max_moves):
        points = [v for v in _profile_points(param, current, param.step()) if v != current]
        scores = [objective({**values, param.key: v}) for v in points]
        if not scores or min(scores) >= best:
            break
        current, best = points[int(np.argmin(scores))], min(scores)
    return current


def fit_unpaired(preset, real: list[RealDepthFrame], geometries: list, *, seed: int = 0, bootstrap: int = 200,
                 keys=None, coarse_frames: int | None = None, real_features: list | None = None,
                 progress: bool = True) -> UnpairedResult:  # fmt: skip
    """Fit the table's parameters of ``preset`` to the real frames' feature distribution.

    Args:
        preset: the sensor preset with the real frames' camera (:func:`camera_for`).
        real: the real frames (:func:`~.realfolder.read_depth_folder`).
        geometries: the fit scenes (:func:`cast_scenes`), resembling the real scenes.
        seed: noise seed of the renders; bootstrap: resamples for the uncertainties.
        keys: fit only these table keys (default: every table key the preset has).
        coarse_frames: frames rendered per candidate of the coarse pass (default half of the
            geometries, at least 2): it only has to find the right grid cell; the local pass and
            the profiles (whose values are reported) use every frame.
        real_features: :func:`.features.frame_features` of ``real`` with the preset's f b, when the caller
            has them already (computed here otherwise).

    Returns:
        :class:`UnpairedResult` (``after``: the fitted values as preset keys).
    """
    from tqdm import tqdm

    start = time.time()
    params = parameters_for(preset, keys)
    sim_frames = len(geometries)
    coarse_frames = min(max(2, sim_frames // 2) if coarse_frames is None else coarse_frames, sim_frames)
    fb = preset.focal_px * preset.baseline_m
    if real_features is None:
        real_features = [frame_features(f.depth, fb) for f in real]
    resolution = max(f.resolution_m for f in real)
    coarse = sum(len(p.coarse_grid()) for p in params)
    walk = 2 * len(params)  # a typical walk: one move, two neighbours (the total is reset after the walk)
    profile = sum(len(_scan_points(p, getattr(preset, p.key), getattr(preset, p.key))) for p in params)
    continuous = sum(not (p.integer or p.choices) for p in params)
    design = len(design_offsets(continuous)) if continuous >= 2 else 0
    bar = tqdm(total=coarse * coarse_frames + (1 + walk + profile + design) * sim_frames, desc="unpaired fit",
               unit="frame", disable=not progress)  # fmt: skip
    ev = _Evaluator(preset, geometries, real_features, resolution, seed, bar)
    values = {p.key: getattr(preset, p.key) for p in params}
    before = dict(values)
    distance_before = ev.distance(values)

    for p in params:  # coarse: each parameter over its whole range, the others held
        grid = p.coarse_grid()
        totals = [p.objective(ev.distance({**values, p.key: v}, n_frames=coarse_frames)) for v in grid]
        values[p.key] = grid[int(np.argmin(totals))]
    for p in params:  # local: the parameters interact (SNR and threshold both make holes)
        values[p.key] = _walk(p, values, lambda v: p.objective(ev.distance(v)))

    # What is left, at most (a profile point or design point may be cached already): the bar's end.
    bar.total = bar.n + (sum(len(_scan_points(p, values[p.key], before[p.key])) for p in params) + design) * sim_frames
    bar.refresh()
    profiles, uncertainty, spread_search, boots = {}, {}, {}, {}
    rng = np.random.default_rng(seed)
    resamples = [(rng.integers(0, len(real), len(real)), rng.integers(0, sim_frames, sim_frames))
                 for _ in range(bootstrap)]  # fmt: skip
    for p in params:  # fine: a profile around the walk's value plus the whole grid; the vertex is the value
        points = _scan_points(p, values[p.key], before[p.key])
        xs = np.array([p.to_unit(v) for v in points])

        def lowest(ys, p=p, points=points, xs=xs):  # +-1 coarse step: the neighbouring grid points and the profile
            return points[int(np.argmin(ys))] if p.integer else p.from_unit(_lowest_vertex(xs, ys, p.step()))

        totals = np.array([p.objective(ev.distance({**values, p.key: v})) for v in points])
        best = lowest(totals)
        draws = [lowest(np.array([p.objective(ev.distance({**values, p.key: v}, real_idx, sim_idx)) for v in points]))
                 for real_idx, sim_idx in resamples]  # fmt: skip
        scale = scene_content_scale(p, ev.features({**values, p.key: points[int(np.argmin(totals))]}), len(real))
        # The input's value where it fits as well: a move the frames cannot tell from scene content is not made.
        kept = bool(totals[points.index(before[p.key])] - totals.min() <= scale)
        best = before[p.key] if kept else best
        values[p.key] = best
        profiles[p.key] = {"points": [float(v) for v in points], "distance": totals.tolist(), "terms": list(p.terms)}
        draws = np.array(draws, float)
        scene = {**scene_content_interval(p, points, totals, best, scale), "kept_input_value": kept}
        uncertainty[p.key] = max(float(draws.std()), scene["std"])
        spread_search[p.key] = max(search_std(p, draws), scene["std_search"])
        # Vertices on the search bounds: the distance is flat or still falling there, so the
        # spread is a lower bound (e.g. eta_c at high SNR, where speckle, not read noise, rules).
        at_end = np.isclose(draws, p.low) | np.isclose(draws, p.high)
        boots[p.key] = {"p05": float(np.percentile(draws, 5)), "p95": float(np.percentile(draws, 95)),
                        "std": float(draws.std()), "at_bound": float(at_end.mean()), "scene_content": scene,
                        "lower_bound": bool(at_end.mean() > 0.2 or scene["at_bound"])}  # fmt: skip
    # Joint: the continuous keys together (their profiles above are conditional on each other).
    joint = joint_uncertainty(params, values, lambda v, r: ev.distance(v, *r)["total"], resamples)
    for key, spread in joint.items():
        boots[key]["joint"] = spread
        uncertainty[key] = max(uncertainty[key], spread["std"])
        spread_search[key] = max(spread_search[key], spread["std_search"])
        boots[key]["lower_bound"] = boots[key]["lower_bound"] or spread["lower_bound"]
    distance_after = ev.distance(values)
    bar.close()
    return UnpairedResult(
        before=before, after=dict(values), uncertainty=uncertainty, uncertainty_search=spread_search,
        bootstrap=boots,
        distance_before=distance_before, distance_after=distance_after, evaluations=len(ev.cache),
        frames_rendered=ev.frames_rendered,
        history=ev.history, profiles=profiles, seconds=time.time() - start,
    )  # fmt: skip
