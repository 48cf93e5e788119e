"""Keep a refined pose only where pixels the optimiser never saw say it is better.

The image is cut into square blocks (``holdout_block_px``) coloured like a checkerboard whose phase
is drawn from the seed and the view's index: the optimiser compares depth only on one colour
(:func:`heldout_blocks` is False there); the other colour judges the result. For every free part
(an object, the support plane) the held-out cost at the start poses is compared with the cost when that
part alone takes its refined pose, and when it takes only the refined translation (its start rotation),
all on one pixel set (the part's held-out pixels at the start or at either candidate). The turn is taken only
if it lowers the cost below the translation's alone by more than ``TURN_SIGMAS`` (0.5) noise units of that
difference; the part keeps the start unless the chosen candidate lowers the cost below the start's by more than
``KEEP_SIGMAS`` (3) noise units of that difference: a part seen through gaps in clutter can lower its held-out cost a
little by sliding onto what lies around it, and a gain within the noise is no evidence that it moved towards the
truth.

The noise of a difference of summed costs (:func:`block_difference_noise`) comes from held-out blocks that touch
at a corner: blocks are the independent units, and two neighbours see nearly the same systematic change, so the
difference of their means is noise. (A real turn makes one side of a part better and the other worse; the spread
over all pixels or all blocks counts that change as noise.) ``TURN_SIGMAS`` and ``KEEP_SIGMAS`` were chosen on the
tuning seeds of tests/refine_validation.py; the report seeds' numbers are in docs/validation.md. A turn the held-out
pixels do not show is not taken: the start rotation is the annotation's, the turn only the optimiser's. Half a unit,
not more: the real cat's needed turn from a 3 deg start is shown by under one unit.

The per-pixel cost (:func:`pixel_cost`, m) is the same for every pose, so sums over one fixed pixel
set compare fairly (the part's held-out pixels at the start pose and at the refined one):

* the real surface nearer than the modelled one by more than ``occluder_m`` (an occluder, clutter
  the scene lacks), or no simulated depth: a fixed charge ``occluder_m`` -- it explains the pixel
  no better and no worse wherever the object is, so hiding an object in clutter earns nothing;
* otherwise ``|simulated - real|``, at most ``absence_cap_m``: where the model puts a surface in front of
  a farther real one (the object is not there) the pixel costs the cap, more than any charge.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import torch

from ddsgen.realscan.simulate import frame_camera

#: Hold-out pattern: the checkerboard's phase of a view comes from rng([seed, HOLDOUT_STREAM, view]).
HOLDOUT_STREAM = 16065
#: A refined turn is taken only if it lowers the held-out cost below the refined translation's alone by more than this
#: many noise units (:func:`block_difference_noise`).
TURN_SIGMAS = 0.5
#: A part takes its refined pose (or translation) only if that lowers its held-out cost below the start's by more than
#: this many noise units of the difference: a gain within the noise is no evidence.
KEEP_SIGMAS = 3.0


@dataclasses.dataclass
class PartDecision:
    """Whether a part's refined pose was kept, by its held-out cost (mean over its held-out pixels, mm)."""

    part: int
    kept: bool
    heldout_start_mm: float
    heldout_refined_mm: float
    pixels: int
    translation_only: bool = False  # kept the refined translation with the start rotation
    candidates_mm: tuple = ()  # held-out gap (mm) of the whole refined pose, of its translation alone
    gain_sigmas: float = float("nan")  # the chosen candidate's held-out gain over the start, in noise units

    def reason(self) -> str:
        """One phrase for the terminal and the report."""
        if self.pixels == 0:
            return "start kept: no held-out pixel shows it"
        if not self.kept and self.heldout_refined_mm < self.heldout_start_mm:
            verdict = ("start kept: the refined pose lowers it within the noise "
                       + (f"({self.gain_sigmas:.1f} noise units)" if self.gain_sigmas == self.gain_sigmas
                          else "(too few held-out blocks to tell)"))
        elif not self.kept:
            verdict = "start kept: the refined pose does not lower"
        elif self.translation_only:
            verdict = "refined translation kept, start rotation (the turn does not lower beyond noise)"
        else:
            verdict = "refined pose kept"
        return f"{verdict} (held-out gap {self.heldout_start_mm:.2f} mm -> {self.heldout_refined_mm:.2f} mm)"


def _checkerboard(height: int, width: int, block_px: int, seed: int, view: int):
    """((H,) block row of every image row, (W,) block column of every image column, held-out parity)."""
    rng = np.random.default_rng([int(seed), HOLDOUT_STREAM, int(view)])
    oy, ox = rng.integers(0, block_px, size=2)
    parity = int(rng.integers(0, 2))
    return (np.arange(height) + oy) // block_px, (np.arange(width) + ox) // block_px, parity


def heldout_blocks(height: int, width: int, block_px: int, seed: int, view: int) -> torch.Tensor:
    """(H, W) bool: the held-out colour of a checkerboard of ``block_px`` blocks, phase seeded by (seed, view)."""
    rows, cols, parity = _checkerboard(height, width, block_px, seed, view)
    return torch.from_numpy(((rows[:, None] + cols[None, :]) % 2) == parity)


def block_cells(height: int, width: int, block_px: int, seed: int, view: int) -> torch.Tensor:
    """(H, W, 2) int64: the (row, column) of every pixel's block in the checkerboard of :func:`heldout_blocks`."""
    rows, cols, _ = _checkerboard(height, width, block_px, seed, view)
    grid = np.stack(np.broadcast_arrays(rows[:, None], cols[None, :]), axis=-1)
    return torch.from_numpy(np.ascontiguousarray(grid, dtype=np.int64))


def block_difference_noise(differences: list, cells: list) -> float | None:
    """Standard deviation (m) that noise gives the sum of ``differences``, from neighbouring held-out blocks.

    Args:
        differences: per view, (P,) float64 per-pixel difference of two candidates' held-out costs (m).
        cells: per view, (P, 2) int64 (row, column) of each pixel's block (:func:`block_cells`); all one colour.

    Blocks are the independent units; a block's sum varies by ``tau^2`` x its pixel count. Two held-out blocks
    that touch at a corner see nearly the same systematic change -- a real turn makes one side of a part better and
    the other worse, smoothly across it -- so the difference of their mean differences is noise:
    ``tau^2 = mean over touching pairs (of every view) of (m_a - m_b)^2 / (1/n_a + 1/n_b)``, and the sum's standard
    deviation is ``tau x sqrt(pixels)``. (The spread over all pixels or blocks counts that systematic change as
    noise.) None when no two held-out blocks touch.
    """
    terms, pixels = [], 0
    for difference, cell in zip(differences, cells):
        if difference.numel() == 0:
            continue
        pixels += difference.numel()
        local = cell - cell.min(0).values
        n_rows, n_cols = int(local[:, 0].max()) + 1, int(local[:, 1].max()) + 1
        flat = local[:, 0] * n_cols + local[:, 1]
        sums = torch.zeros(n_rows * n_cols, dtype=torch.float64).index_add_(0, flat, difference.double())
        counts = torch.zeros(n_rows * n_cols, dtype=torch.float64).index_add_(0, flat, torch.ones_like(sums[flat]))
        sums, counts = sums.reshape(n_rows, n_cols), counts.reshape(n_rows, n_cols)
        means = sums / counts.clamp(min=1.0)
        down_right = ((slice(None, -1), slice(None, -1)), (slice(1, None), slice(1, None)))
        down_left = ((slice(None, -1), slice(1, None)), (slice(1, None), slice(None, -1)))
        for a, b in (down_right, down_left):
            both = (counts[a] > 0) & (counts[b] > 0)
            gap = (means[a] - means[b])[both]
            terms.append(gap**2 / (1.0 / counts[a][both] + 1.0 / counts[b][both]))
    terms = torch.cat(terms) if terms else torch.zeros(0)
    if terms.numel() == 0:
        return None
    return float(terms.mean() * pixels) ** 0.5


def pixel_cost(depth, valid, clean, real, occluder_m: float, absence_cap_m: float, max_depth_m: float):
    """((H, W) cost in m, (H, W) bool where it is defined: a real depth and a modelled surface within range)."""
    defined = (real > 0) & (clean > 0) & (clean <= max_depth_m)
    occluded = real < clean - occluder_m
    residual = (depth - real).abs().clamp(max=absence_cap_m)
    charge = torch.full_like(residual, occluder_m)
    return torch.where(occluded | ~valid, charge, residual), defined


def owner_image(tensors) -> torch.Tensor:
    """(H, W) int64 part index of every pixel of a cast (-1: nothing hit)."""
    height, width = tensors.shape
    owner = torch.full((height * width,), -1, dtype=torch.int64)
    owner[tensors.index] = tensors.owner
    return owner.reshape(height, width)


@dataclasses.dataclass
class _Unit:
    """One decision: the correction rows that move a part (one row of each tensor), the views it moves it in."""

    rows: list  # [(parameter tensor, row)]
    views: list  # view indices
    part: int


def start_costs(sensor, views, occluder_m: float, absence_cap_m: float) -> list:
    """Per view, (cost (H, W) m, owner image) at the start poses (every part's correction zero), for
    :func:`accept_parts` and :func:`frame_heldout_gaps`; the refined corrections are restored afterwards."""
    units = _units(views)
    refined = {id(p): p.detach().clone() for u in units for p, _ in u.rows}
    for u in units:
        _set(u.rows, None)
    start = [_view_cost(sensor, v, occluder_m, absence_cap_m) for v in views]
    for u in units:
        _set(u.rows, refined)
    return start


def accept_parts(sensor, views, occluder_m: float, absence_cap_m: float, start: list | None = None) -> list[list]:
    """Keep each part's refined correction only if it lowers the part's held-out cost; reset the others.

    Args:
        sensor: the DepthSensor (each view's camera is set for its evaluation).
        views: the refinement loop's views (``scene``, ``real``, ``heldout``, ``blocks`` (H, W, 2) block (row, column)
            of every pixel, ``index``, ``recast()``,
            ``render(sensor)`` -> (depth, valid, clean), ``resolved_depth_m(sensor)``), at the refined poses.
        start: :func:`start_costs` of the views, when the caller has them (computed here otherwise).

    Returns:
        per view, per part: a :class:`PartDecision` (None for a part that does not move).
    """
    if start is None:
        start = start_costs(sensor, views, occluder_m, absence_cap_m)
    units = _units(views)
    refined = {id(p): p.detach().clone() for u in units for p, _ in u.rows}
    for u in units:
        _set(u.rows, None)
    decisions = [[None] * len(v.scene.parts) for v in views]
    chosen = []  # the rows to set to their refined values
    for u in units:
        candidates = [u.rows, u.rows[1:]]  # the whole correction; its translation only
        maps = []  # per candidate, per view of the unit: (cost, owner)
        for rows in candidates:
            _set(rows, refined)
            maps.append([_view_cost(sensor, views[i], occluder_m, absence_cap_m) for i in u.views])
            _set(rows, None)
        # one pixel set for all three: the part's held-out pixels at the start or at either candidate
        judged = [views[i].heldout & ((start[i][1] == u.part) | (maps[0][j][1] == u.part) | (maps[1][j][1] == u.part))
                  for j, i in enumerate(u.views)]  # fmt: skip
        base = torch.cat([start[i][0][m] for i, m in zip(u.views, judged)]).double()
        full, shift = (torch.cat([c[j][0][m] for j, m in enumerate(judged)]).double() for c in maps)
        pixels = int(base.numel())
        before, after = float(base.sum()), [float(full.sum()), float(shift.sum())]
        # The turn is taken only if it lowers the cost below the translation's alone by more than TURN_SIGMAS noise
        # units of the difference (from neighbouring held-out blocks, which a real turn does not inflate).
        noise = block_difference_noise([(maps[0][j][0][m] - maps[1][j][0][m]).double() for j, m in enumerate(judged)],
                                       [views[i].blocks[m] for i, m in zip(u.views, judged)])  # fmt: skip
        best = 0 if noise is not None and after[1] - after[0] > TURN_SIGMAS * noise else 1
        # The chosen candidate moves the part only if its gain over the start is beyond KEEP_SIGMAS noise units.
        gain_noise = block_difference_noise([(start[i][0][m] - maps[best][j][0][m]).double()
                                             for j, (i, m) in enumerate(zip(u.views, judged))],
                                            [views[i].blocks[m] for i, m in zip(u.views, judged)])  # fmt: skip
        gain = (before - after[best]) / gain_noise if gain_noise else float("nan")
        keep = pixels > 0 and after[best] < before and gain > KEEP_SIGMAS
        if keep:
            chosen.append(candidates[best])
        n = max(pixels, 1)
        decision = PartDecision(u.part, keep, before / n * 1000.0, after[best] / n * 1000.0,
                                pixels, translation_only=keep and best == 1,
                                candidates_mm=tuple(a / n * 1000.0 for a in after),
                                gain_sigmas=gain)  # fmt: skip
        for i in u.views:
            decisions[i][u.part] = decision
    for rows in chosen:
        _set(rows, refined)
    return decisions


def frame_heldout_gaps(sensor, views, start: list, occluder_m: float,
                       absence_cap_m: float) -> list[tuple[float, float]]:  # fmt: skip
    """Per view, (held-out gap at the start, at the current poses) in mm: the mean :func:`pixel_cost` over the view's
    held-out pixels that an object owns at either pose (one pixel set for both, so the two compare fairly; a mean
    over each pose's own in-band pixels would favour the pose that leaves its worst pixels out of the band).

    ``start``: :func:`start_costs` of the views."""
    gaps = []
    for v, (cost_start, owner_start) in zip(views, start):
        cost_now, owner_now = _view_cost(sensor, v, occluder_m, absence_cap_m)
        n_objects = v.scene.n_objects
        on_object = ((owner_start >= 0) & (owner_start < n_objects)) | ((owner_now >= 0) & (owner_now < n_objects))
        judged = v.heldout & on_object
        if not bool(judged.any()):
            gaps.append((float("nan"), float("nan")))
            continue
        start_mm, now_mm = (float(cost[judged].double().mean()) * 1000.0 for cost in (cost_start, cost_now))
        gaps.append((start_mm, now_mm))
    return gaps


def _set(rows, refined) -> None:
    """Set the rows to their refined values (``refined``: {id(tensor): values}) or to 0 (None: the start)."""
    with torch.no_grad():
        for p, row in rows:
            p[row] = 0.0 if refined is None else refined[id(p)][row]


def _view_cost(sensor, v, occluder_m, absence_cap_m):
    """:func:`_cost` of a view in its own camera."""
    with frame_camera(sensor, v.scene.intrinsics):
        return _cost(v, sensor, occluder_m, absence_cap_m)


def _cost(v, sensor, occluder_m, absence_cap_m):
    """(cost (H, W) m with undefined pixels 0, owner image) of a view at its current poses."""
    v.recast()
    depth, valid, clean = v.render(sensor)
    cost, defined = pixel_cost(depth, valid, clean, v.real, occluder_m, absence_cap_m, v.resolved_depth_m(sensor))
    return torch.where(defined, cost, torch.zeros_like(cost)), torch.where(defined, owner_image(v.tensors), -1)


def _units(views) -> list:
    """The decisions to make: each free part of each view, a shared object's correction once for all views."""
    units, shared_done = [], set()
    for i, v in enumerate(views):
        poses = v.scene.poses
        n_shared = len(poses.shared) if poses.shared is not None else 0
        free = poses.free.tolist()
        for k in range(len(poses)):
            if not free[k] and k >= n_shared:
                continue
            if k < n_shared:
                if k in shared_done:
                    continue
                shared_done.add(k)
                sharing = [j for j, w in enumerate(views) if w.scene.poses.shared is poses.shared]
                units.append(_Unit([(poses.shared.rotation, k), (poses.shared.translation, k)], sharing, k))
            else:
                units.append(_Unit([(poses.rotation, k), (poses.translation, k)], [i], k))
    return units
