"""Analysis-by-synthesis pose refinement: move the scene's parts until the simulated depth matches a real one.

Each step: posed hits (torch) -> DepthSensor -> robust loss against the real depth (+ the depth-edge
term of :mod:`.edges`: the objects' outlines onto the real depth discontinuities) -> Adam on the
parts' pose corrections (and optionally albedos). Every ``recast_every`` steps the scene is ray-cast
again at the current poses, so visibility, silhouettes and projector shadows follow. The result is the
mean of the last ``average_last`` share of the iterates (the fresh noise of each step jitters them).

Robustness to what the scene does not model (clutter, hands, occluders, a wall): a pixel counts only
where the real depth lies within ``band_m`` behind the rendered clean depth and at most ``occluder_m`` in front
of it (a real surface nearer than that is something the scene lacks in front of the object: it pulls
nothing), and the residual goes through a Huber loss of width ``huber_m`` (mixed pixels at edges
and the sensor's outliers pull linearly, not quadratically). Pixels whose rendered depth is beyond the depth the
sensor resolves (:func:`ddsgen.realscan.losses.resolved_depth_m`: one disparity quantum is a depth step of more than 50
mm, 4.14 m for the Kinect V1) do not count, as in ``fit``: there the residual is 0 or a whole step, whatever the pose.

Nothing worse is written (:mod:`.acceptance`): the optimiser sees one colour of a checkerboard of pixel blocks;
each part keeps its refined pose only if that lowers its cost on the other colour beyond the noise, and a view whose
held-out gap at the kept poses (over the pixels its objects own at either pose) is not lower than at the start keeps
its start poses.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import torch

from ddsgen.realscan.losses import resolved_depth_m
from ddsgen.realscan.simulate import frame_camera
from ddsgen.scene_gradients.acceptance import (accept_parts, block_cells, frame_heldout_gaps, heldout_blocks,
                                               owner_image, start_costs)
from ddsgen.scene_gradients.edges import edge_loss, outline_points, real_edge_distance
from ddsgen.scene_gradients.hits import posed_geometry
from ddsgen.scene_gradients.identifiability import object_identifiability
from ddsgen.scene_gradients.scene import RefinableScene

#: Simulated-noise stream of refinement: step k draws rng([seed, REFINE_STREAM, k]); the evaluations rng([seed, REFINE_STREAM]).
REFINE_STREAM = 16016


#: The rotation's default step: 1e-2 rad at most, and 0.6 rad of travel per run (120 steps: 5e-3). With 1e-2 over
#: 120 steps the noisy steps let the real cat's rotation wander 3-6 deg into a pose of higher expected loss, and
#: the decayed steps did not bring it back (20 starts 3 deg / 8 mm off: worst 6.99 and 2.67 deg, median 1.16;
#: at 5e-3 the worst is 1.51, median 1.16). Short runs keep 1e-2 (40 steps: 0.26 deg from 3 deg / 10 mm on a
#: synthetic box, 0.92 at 5e-3: too slow to arrive).
MAX_ROTATION_STEP_RAD = 1e-2
ROTATION_TRAVEL_RAD = 0.6


@dataclasses.dataclass
class RefineSettings:
    """Optimiser settings of :func:`refine_poses` (units: steps, rad, m)."""

    steps: int = 120
    recast_every: int = 5
    # rad per Adam step at the start (cosine decay to 2 % at the end); None: ROTATION_TRAVEL_RAD / steps, at most
    # 1e-2 (:meth:`rotation_step`).
    lr_rotation: float | None = None
    lr_translation: float = 1e-3  # m per Adam step at the start
    lr_albedo: float = 0.0  # log-albedo per step; 0 keeps the albedos fixed
    band_m: float = 0.025  # compare where the real depth is less than this behind the rendered clean depth ...
    occluder_m: float = 0.015  # ... and less than this in front of it (nearer: an occluder the scene lacks)
    huber_m: float = 0.003  # Huber width of the depth residual
    seed: int = 0
    # Depth-edge term (:mod:`.edges`): weight of the outline-to-real-edge distance (m) against the depth
    # loss (m); 0 leaves it out. An edge is a depth jump of more than edge_jump_m; edges farther than
    # edge_max_px from the simulated outline do not pull.
    edge_weight: float = 1.0
    edge_jump_m: float = 0.015
    edge_max_px: float = 6.0
    # The result is the mean of the pose corrections over this last share of the steps (Polyak
    # averaging: each step's fresh IR noise jitters the iterates; their mean is the steadier estimate).
    # 120 steps averaged over the last half vs 80 over the last 30 %: synthetic 0.55 -> 0.50 deg median
    # (32 objects; the noise floor is 0.48), LineMOD cat 1.37 -> 1.31 deg (bench/bench_refine.py).
    average_last: float = 0.5
    # "sensor": d(simulated depth)/d(pose) through the IR image and the matcher (the dots move);
    # "geometry": the simulated depth's value, the clean depth's gradient (straight-through; ~4x faster)
    gradient: str = "sensor"
    # Acceptance (:mod:`.acceptance`): blocks of this many pixels, every other one held out of the optimiser and used
    # to judge each part's refined pose; 0: no hold-out (the parts keep their refined poses unless the view's gap rises).
    holdout_block_px: int = 6
    # Identifiability (:mod:`.identifiability`): an object's pose directions whose standard deviation from the
    # curvature of its data term at the start exceeds this (m; rotations x the object's radius) stay at the start.
    # 0: every direction is free. Views sharing corrections (static scenes) are not restricted.
    identify_max_sigma_m: float = 0.001

    def rotation_step(self) -> float:
        """The rotations' Adam step at the start (rad): ``lr_rotation``, or by default a travel of
        ROTATION_TRAVEL_RAD over the run, at most MAX_ROTATION_STEP_RAD per step."""
        if self.lr_rotation is not None:
            return float(self.lr_rotation)
        return min(MAX_ROTATION_STEP_RAD, ROTATION_TRAVEL_RAD / max(int(self.steps), 1))


@dataclasses.dataclass
class RefineResult:
    """What :func:`refine_poses` did.

    initial, refined: (N, 4, 4) ``cam_T_obj`` of every part (objects first, then background), m.
    albedo: (N,) final albedos. history: per step {step, loss_mm, pixels}.
    gap_before_mm, gap_after_mm: mean |simulated - real| depth (mm) on the object pixels where both are valid
        and the real depth is within the band of the rendered one (a median is often 0: both are quantised).
    depth_before, depth_after: (H, W) float32 simulated depth (m, 0 invalid) at the initial / refined poses.
    decisions: per part, the :class:`~ddsgen.scene_gradients.acceptance.PartDecision` (None: the part does not
        move, or no acceptance); ``refined`` holds the start pose of a part whose refined pose was not kept.
    kept_start: True if the view's gap at the kept poses was not lower than at the start: ``refined`` = ``initial``.
        With the hold-out on, the gap that decides is the held-out one (``heldout_gap_*``), else ``gap_*``.
    heldout_gap_before_mm, heldout_gap_after_mm: the mean per-pixel cost (:func:`.acceptance.pixel_cost`, mm) over the
        held-out pixels an object owns at the start or at the kept poses, at each (nan without the hold-out).
    heldout_gap_refined_mm: the same at the poses the acceptance kept, before the frame's own rule (equal to
        ``heldout_gap_after_mm`` unless ``kept_start``).
    gap_optimised_mm: the gap at the optimiser's poses, before any was reverted.
    identifiability: per object, its :class:`~ddsgen.scene_gradients.identifiability.Identifiability` (empty: not
        assessed); its undetermined directions stayed at the start.
    visible_fraction: per object, the share of its modelled pixels at the start (with a real depth) where the real
        surface is not more than ``occluder_m`` nearer: the visibility estimated from the data.
    """

    initial: np.ndarray
    refined: np.ndarray
    albedo: np.ndarray
    history: list
    gap_before_mm: float
    gap_after_mm: float
    depth_before: np.ndarray
    depth_after: np.ndarray
    decisions: list = dataclasses.field(default_factory=list)
    kept_start: bool = False
    gap_optimised_mm: float = float("nan")
    identifiability: list = dataclasses.field(default_factory=list)
    visible_fraction: list = dataclasses.field(default_factory=list)
    heldout_gap_before_mm: float = float("nan")
    heldout_gap_after_mm: float = float("nan")
    heldout_gap_refined_mm: float = float("nan")


def compared_pixels(valid, clean_depth, real_depth, band_m: float, max_depth_m: float = math.inf,
                    occluder_m: float | None = None) -> torch.Tensor:  # fmt: skip
    """(H, W) bool: where simulated (``valid``) and real depth are both valid, the real one lies less than ``band_m``
    behind the rendered clean depth (m, 0 = no hit) and less than ``occluder_m`` (default ``band_m``) in front of it,
    and that depth is at most ``max_depth_m``."""
    clean = clean_depth.detach()
    near = band_m if occluder_m is None else occluder_m
    offset = real_depth - clean
    return valid & (real_depth > 0) & (clean > 0) & (clean <= max_depth_m) & (offset < band_m) & (offset > -near)


def robust_depth_loss(depth, valid, clean_depth, real_depth, band_m: float, huber_m: float,
                      max_depth_m: float = math.inf, occluder_m: float | None = None):  # fmt: skip
    """Huber loss (m) of simulated vs real depth where both are valid and the real one is within the band
    (:func:`compared_pixels`: up to ``band_m`` behind the clean depth, ``occluder_m`` in front).

    Args:
        depth, valid: (H, W) simulated depth (m) and its validity.
        clean_depth: (H, W) rendered noise-free depth (m, 0 = no hit): decides the band (not differentiated).
        real_depth: (H, W) real depth (m, 0 = invalid).
        max_depth_m: pixels whose clean depth is farther do not count (the resolved depth; inf: all count).

    Returns:
        (loss scalar (m), mask (H, W) bool of the pixels that counted).
    """
    mask = compared_pixels(valid, clean_depth, real_depth, band_m, max_depth_m, occluder_m)
    if not bool(mask.any()):
        return depth.sum() * 0.0, mask
    residual = depth[mask] - real_depth[mask]
    loss = torch.nn.functional.huber_loss(residual, torch.zeros_like(residual), delta=huber_m, reduction="mean")
    return loss / huber_m, mask  # in m: ~|r| for large r, r^2 / (2 huber) for small


def simulate_depth(sensor, tensors, rotations, translations, albedo, noise, gradient: str = "sensor"):
    """Simulated depth at the given poses -> (depth (H, W) m, valid (H, W) bool, posed SensorGeometry).

    ``gradient="sensor"``: the depth's gradient w.r.t. the poses flows through the IR image and the
    matcher. ``"geometry"``: the forward value is the same simulated depth, but its pose gradient is the
    clean depth's (straight-through estimator: the sensor runs on a detached geometry, so its own
    parameters still get their gradients).
    """
    geometry = posed_geometry(tensors, rotations, translations, albedo)
    if gradient == "sensor":
        out = sensor(geometry, noise=noise)
        return out.depth, out.valid, geometry
    if gradient != "geometry":
        raise ValueError(f"gradient must be 'sensor' or 'geometry', got {gradient!r}")
    detached = dataclasses.replace(geometry, points=geometry.points.detach(), normals=geometry.normals.detach(),
                                   albedo=geometry.albedo.detach(), clean_depth=geometry.clean_depth.detach())  # fmt: skip
    out = sensor(detached, noise=noise)
    clean = geometry.clean_depth
    return out.depth + (clean - clean.detach()) * out.valid, out.valid, geometry


def _gap_mm(depth, valid, clean, real, instance, band_m, max_depth_m) -> float:
    mask = compared_pixels(valid, clean, real, band_m, max_depth_m) & (instance > 0)
    if not bool(mask.any()):
        return float("nan")
    return float((depth[mask] - real[mask]).abs().mean() * 1000.0)


def refine_poses(sensor, scene: RefinableScene, real_depth: torch.Tensor, settings: RefineSettings | None = None,
                 progress: bool = False, callback=None) -> RefineResult:  # fmt: skip
    """Refine the poses of a scene's parts against a real depth image.

    Args:
        sensor: :class:`~ddsgen.sensor.depth_sensor.DepthSensor`; its parameters are not changed, and it
            is given the scene's camera (``scene.intrinsics``) for the call.
        scene: :class:`RefinableScene` at the initial poses (its ``poses`` are updated in place).
        real_depth: (H, W) float32 real depth (m, 0 = invalid), same camera as the scene.
        settings: :class:`RefineSettings`.
        progress: show a progress bar.
        callback: called as ``callback(step, scene, loss_m)`` after every step (e.g. to log or stop early).

    Returns:
        :class:`RefineResult`.
    """
    (result,) = refine_views(sensor, [scene], [real_depth], settings, progress,
                             None if callback is None else (lambda step, loss: callback(step, scene, loss)))
    return result


def refine_views(sensor, scenes: list, real_depths: list, settings: RefineSettings | None = None,
                 progress: bool = False, callback=None) -> list:  # fmt: skip
    """Refine several views together: one loss, the mean of the views' losses, and one optimiser.

    Views whose :class:`~ddsgen.scene_gradients.poses.ScenePoses` share their objects' corrections
    (:func:`ddsgen.scene_gradients.static_scene.refine_static_scene`) move those objects together;
    otherwise the views are independent problems that merely step in lockstep. View 0 draws exactly
    the noise a single-view refinement draws. ``callback(step, loss_m)`` after every step.

    Returns:
        one :class:`RefineResult` per view.
    """
    s = settings or RefineSettings()
    reals = [torch.as_tensor(r, dtype=torch.float32) for r in real_depths]
    if len(reals) != len(scenes) or not scenes:
        raise ValueError(f"{len(scenes)} scenes but {len(reals)} real depth images")
    for scene, real in zip(scenes, reals):
        if tuple(real.shape) != (scene.intrinsics.height, scene.intrinsics.width):
            raise ValueError(f"real depth is {tuple(real.shape)}, the scene's camera is "
                             f"{(scene.intrinsics.height, scene.intrinsics.width)}")  # fmt: skip
    trainable = [p for p in sensor.parameters() if p.requires_grad]
    for p in trainable:  # the sensor is fixed here; its flags are restored at the end
        p.requires_grad_(False)
    try:
        return _refine_loop(sensor, scenes, reals, s, progress, callback)
    finally:
        for p in trainable:
            p.requires_grad_(True)


def _noise_seed(s: RefineSettings, view: int, *step: int) -> list:
    """Noise stream of a view (view 0: the single-view stream) and, during the loop, of a step."""
    return [int(s.seed), REFINE_STREAM, *step] + ([view] if view else [])


def _distinct(parameters) -> list:
    out = []
    for p in parameters:
        if all(p is not q for q in out):
            out.append(p)
    return out


class _View:
    """One view's state in the loop: its scene, real depth, held-out pixels, cast and outline (re-made every re-cast)."""

    def __init__(self, index: int, scene: RefinableScene, real: torch.Tensor, s: RefineSettings):
        self.index, self.scene, self.real, self.s = index, scene, real, s
        self.edge_distance = torch.from_numpy(real_edge_distance(real.numpy(), s.edge_jump_m, s.edge_max_px))
        height, width = real.shape
        self.heldout = (heldout_blocks(height, width, int(s.holdout_block_px), s.seed, index)
                        if s.holdout_block_px > 0 else torch.zeros(real.shape, dtype=torch.bool))  # fmt: skip
        self.blocks = block_cells(height, width, max(int(s.holdout_block_px), 1), s.seed, index)
        self.meshes = [p.mesh for p in scene.parts]
        self.tensors, self.outline = None, None
        self.identifiability, self.visible_fraction = [], []

    def assess(self, sensor) -> None:
        """Each object's identifiability at the current (start) poses and cast (:mod:`.identifiability`)."""
        poses, s = self.scene.poses, self.s
        depth, valid, clean = self.render(sensor)
        owner = owner_image(self.tensors)
        measured = (self.real > 0) & (clean > 0)
        unoccluded = measured & (self.real >= clean - s.occluder_m)
        for k in range(self.scene.n_objects):
            modelled = int((measured & (owner == k)).sum())
            self.visible_fraction.append(float((unoccluded & (owner == k)).sum()) / modelled if modelled else 0.0)
        if poses.shared is not None or s.identify_max_sigma_m <= 0:
            return
        compared = compared_pixels(valid, clean, self.real, s.band_m, self.resolved_depth_m(sensor), s.occluder_m)
        for k in range(self.scene.n_objects):
            radius = float(np.linalg.norm(self.meshes[k].extents)) / 2.0
            self.identifiability.append(object_identifiability(
                poses, self.tensors, k, compared & (owner == k) & ~self.heldout, self.outline, self.scene.intrinsics,
                (owner == k).numpy(), max_sigma_m=s.identify_max_sigma_m, radius_m=max(radius, 1e-3)))  # fmt: skip

    def restrict(self) -> None:
        """Remove the objects' corrections along their undetermined directions."""
        poses = self.scene.poses
        with torch.no_grad():
            for k, identified in enumerate(self.identifiability):
                rotation, translation = identified.project(poses.rotation[k], poses.translation[k])
                poses.rotation[k], poses.translation[k] = rotation, translation

    def resolved_depth_m(self, sensor) -> float:
        """The depth (m) beyond which this view's depth values do not count, for the sensor's current baseline."""
        fb = self.scene.intrinsics.fx * float(sensor.baseline.detach())
        return resolved_depth_m(fb, sensor.preset.subpixel_step_px)

    def recast(self) -> None:
        poses = self.scene.poses
        self.tensors = self.scene.cast()
        if self.s.edge_weight <= 0:
            return
        with torch.no_grad():
            R, t = poses()
            clean = posed_geometry(self.tensors, R, t, poses.albedo).clean_depth.numpy()
        # Every outline point pulls, held-out block or not: the outline's pull on in-plane slides and turns is what
        # pins the rotation (the cat: 1.4 deg from 3 deg / 8 mm with all points, 3.0 deg with half), and the
        # acceptance judges depth residuals, not outlines.
        # An outline pixel where the real surface lies in front of the modelled one is behind something the scene
        # lacks: the real edge there is the occluder's, and would pull a hidden object onto it.
        real = self.real.numpy()
        seen = ~((real > 0) & (real < clean - self.s.occluder_m))
        self.outline = outline_points(self.tensors, self.meshes, clean, self.scene.n_objects, self.s.edge_jump_m, seen)

    def render(self, sensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(simulated depth (H, W) m, its validity, clean depth (H, W) m) at the current poses and the last cast,
        with the view's evaluation noise."""
        poses = self.scene.poses
        with torch.no_grad():
            R, t = poses()
            geometry = posed_geometry(self.tensors, R, t, poses.albedo)
            out = sensor(geometry, noise=sensor.draw_noise(_noise_seed(self.s, self.index)))
        return out.depth, out.valid, geometry.clean_depth

    def evaluate(self, sensor) -> tuple[np.ndarray, float]:
        """(simulated depth (H, W) m at the current poses, gap in mm) with the view's evaluation noise."""
        depth, valid, clean = self.render(sensor)
        gap = _gap_mm(depth, valid, clean, self.real, self.tensors.instance, self.s.band_m, self.resolved_depth_m(sensor))
        return depth.numpy().copy(), gap

    def loss(self, sensor, step: int):
        """(loss (m, differentiable), pixels compared) of this step, fresh noise."""
        s, poses = self.s, self.scene.poses
        R, t = poses()
        # Fresh noise every step (a fixed seeded sequence): the optimum is that of the expected loss, not of
        # one noise draw (with one fixed draw the poses fit its speckle: 1.5 deg left instead of 1 deg, measured).
        depth, valid, geometry = simulate_depth(sensor, self.tensors, R, t, poses.albedo,
                                                sensor.draw_noise(_noise_seed(s, self.index, step)), s.gradient)
        loss, mask = robust_depth_loss(depth, valid & ~self.heldout, geometry.clean_depth, self.real, s.band_m, s.huber_m,
                                       self.resolved_depth_m(sensor), s.occluder_m)
        if self.outline is not None:
            loss = loss + s.edge_weight * edge_loss(self.outline, R, t, self.edge_distance, self.scene.intrinsics).float()
        return loss, int(mask.sum())


def _refine_loop(sensor, scenes, reals, s, progress, callback) -> list:
    from tqdm import tqdm

    views = [_View(i, scene, real, s) for i, scene, real in zip(range(len(scenes)), scenes, reals)]
    all_poses = [v.scene.poses for v in views]
    shared = _distinct(p.shared for p in all_poses if p.shared is not None)
    rotations = _distinct([p.rotation for p in all_poses] + [m.rotation for m in shared])
    translations = _distinct([p.translation for p in all_poses] + [m.translation for m in shared])
    groups = [{"params": rotations, "lr": s.rotation_step()}, {"params": translations, "lr": s.lr_translation}]
    if s.lr_albedo > 0:
        groups.append({"params": [p.log_albedo for p in all_poses], "lr": s.lr_albedo})
    else:
        for p in all_poses:
            p.log_albedo.requires_grad_(False)
    optimiser = torch.optim.Adam(groups)
    base_lrs = [g["lr"] for g in groups]
    initial = [p.matrices() for p in all_poses]
    before = []
    for v in views:
        v.recast()
        with frame_camera(sensor, v.scene.intrinsics):
            before.append(v.evaluate(sensor))
            v.assess(sensor)
    histories = [[] for _ in views]
    first_averaged = s.steps - int(round(s.average_last * s.steps)) if s.average_last > 0 else s.steps
    averaged = []
    for step in tqdm(range(s.steps), desc="refine", unit="step", disable=not progress, leave=False):
        if step and step % max(int(s.recast_every), 1) == 0:
            for v in views:
                v.recast()
        decay = 0.02 + 0.98 * 0.5 * (1.0 + math.cos(math.pi * step / max(s.steps, 1)))
        for group, lr in zip(optimiser.param_groups, base_lrs):
            group["lr"] = lr * decay
        optimiser.zero_grad()
        losses = []
        for v, history in zip(views, histories):
            with frame_camera(sensor, v.scene.intrinsics):
                loss, pixels = v.loss(sensor, step)
            losses.append(loss / len(views))
            history.append({"step": step, "loss_mm": float(loss.detach()) * 1000.0, "pixels": pixels})
        total = sum(losses[1:], losses[0])
        if total.requires_grad:
            total.backward()
            optimiser.step()
            for v in views:
                v.restrict()
        if callback is not None:
            callback(step, float(total.detach()))
        if step >= first_averaged:
            averaged.append([p.detach().clone() for p in rotations + translations])
    if averaged:
        with torch.no_grad():
            for k, p in enumerate(rotations + translations):
                p.copy_(torch.stack([a[k] for a in averaged]).mean(0))
    optimised = []
    for v in views:
        v.recast()
        with frame_camera(sensor, v.scene.intrinsics):
            optimised.append(v.evaluate(sensor)[1])
    decisions = [[] for _ in views]
    heldout = [(float("nan"), float("nan"))] * len(views)
    if s.holdout_block_px > 0:
        start = start_costs(sensor, views, s.occluder_m, s.band_m)  # one cast and render of each view, for both
        decisions = accept_parts(sensor, views, s.occluder_m, s.band_m, start=start)
        heldout = frame_heldout_gaps(sensor, views, start, s.occluder_m, s.band_m)
    after = []
    for v in views:
        v.recast()
        with frame_camera(sensor, v.scene.intrinsics):
            after.append(v.evaluate(sensor))
    if s.holdout_block_px > 0:  # judged where the optimiser did not look, on one pixel set for both poses
        kept_start = _keep_start_where_not_better(views, [h[0] for h in heldout], [h[1] for h in heldout])
    else:
        kept_start = _keep_start_where_not_better(views, [b[1] for b in before], [a[1] for a in after])
    results = []
    for k, (v, history, init) in enumerate(zip(views, histories, initial)):
        (depth_before, gap_before), (depth_after, gap_after) = before[k], after[k]
        if kept_start:
            depth_after, gap_after = depth_before, gap_before
        poses = v.scene.poses
        results.append(RefineResult(initial=init, refined=poses.matrices(), albedo=poses.albedo.detach().numpy().copy(),
                                    history=history, gap_before_mm=gap_before, gap_after_mm=gap_after,
                                    depth_before=depth_before, depth_after=depth_after, decisions=decisions[k],
                                    kept_start=kept_start, gap_optimised_mm=optimised[k],
                                    identifiability=v.identifiability, visible_fraction=v.visible_fraction,
                                    heldout_gap_before_mm=heldout[k][0], heldout_gap_refined_mm=heldout[k][1],
                                    heldout_gap_after_mm=heldout[k][0] if kept_start else heldout[k][1]))  # fmt: skip
    return results


def _keep_start_where_not_better(views, gaps_before, gaps_after) -> bool:
    """Reset every correction to the start if the views' mean gap at the kept poses is not lower; True if reset.

    Views that share corrections are one decision; independent views (which only step in lockstep) are too, by
    their mean: a single-view refinement is the common case, and there it is the view's own gap."""
    before, after = float(np.nanmean(gaps_before)), float(np.nanmean(gaps_after))
    if after < before:
        return False
    with torch.no_grad():
        for v in views:
            poses = v.scene.poses
            poses.rotation.zero_()
            poses.translation.zero_()
            if poses.shared is not None:
                poses.shared.rotation.zero_()
                poses.shared.translation.zero_()
    return True
