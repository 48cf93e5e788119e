"""Joint uncertainty of the continuous keys: a quadratic response surface, bootstrapped.

The profiles of :func:`~.search.fit_unpaired` vary one key with the others held at their fitted
values, so their spread is *conditional*: when two keys trade off (a lower IR signal-to-noise
ratio everywhere against darker corners; a higher confidence threshold against a lower SNR),
each profile is sharp while the distance is nearly flat along the diagonal, and the conditional
spread understates how far the value can move. Measured on hidden devices (docs/validation.md):
most continuous keys landed outside twice their conditional spread.

Here the total distance is evaluated on a small design around the fitted values (the centre, half a
coarse step along each key in both directions, and along both diagonals of every pair), a
full quadratic in the keys' search coordinates is fitted by least squares, and its minimum is
taken again for each bootstrap resample of the real and simulated frames (cached features re-summed:
no new rendering). The spread of those minima is the marginal uncertainty, correlations included.
A key that the resample's surface does not bound (it moves along a flat or falling direction) or whose minimum
lies beyond ``MAX_STEPS`` coarse steps is clipped there; when more than 20 % of a key's minima are, its spread is a
lower bound. Per key: on the real IC-BIN frames from kinect_v1 the SNR and beta are flat (high SNR), which had
clipped every key, the row smoothing's well-measured weight included (99 % of resamples).
"""

from __future__ import annotations

from itertools import combinations

import numpy as np

from ddsgen.fit.unpaired.spread import search_std

#: Design half-width, in coarse grid steps of each key (the profiles' inner points).
DESIGN_STEP = 0.5
#: Minima farther than this (coarse steps) from the fitted values are clipped: the quadratic is local.
MAX_STEPS = 2.0


def design_offsets(k: int) -> np.ndarray:
    """(n, k) offsets in design steps: centre, +-e_i, e_i + e_j and e_i - e_j (i < j): 1 + 2k + k(k-1)
    points (21 for 4 keys), more than the (k+1)(k+2)/2 terms of a full quadratic (15)."""
    eye = np.eye(k)
    rows = [np.zeros(k)] + [s * eye[i] for i in range(k) for s in (1, -1)]
    for i, j in combinations(range(k), 2):
        rows += [eye[i] + eye[j], eye[i] - eye[j]]
    return np.array(rows)


def _quadratic_basis(x: np.ndarray) -> np.ndarray:
    """(n, 1 + k + k(k+1)/2) columns 1, x_i, x_i x_j (i <= j)."""
    n, k = x.shape
    cols = [np.ones(n)] + [x[:, i] for i in range(k)]
    cols += [x[:, i] * x[:, j] for i in range(k) for j in range(i, k)]
    return np.stack(cols, axis=1)


#: A key moves with a direction of zero or negative curvature when its component in that (unit) direction exceeds
#: this: the surface does not bound it, and its minimum is clipped.
UNBOUNDED_LOADING = 0.3


def quadratic_minimum(x: np.ndarray, y: np.ndarray, limit: float) -> tuple[np.ndarray, np.ndarray]:
    """Minimum of the least-squares quadratic through (x (n, k), y (n,)), each key clipped to |x_i| <= limit.

    Along each curved direction of the Hessian (positive eigenvalue) the minimum is the vertex; along a flat or
    falling one the surface is followed downhill to the limit. Returns (x_min (k,), clipped (k,) bool): a key is
    clipped when it loads on a flat or falling direction (component > :data:`UNBOUNDED_LOADING`) or its minimum lies
    beyond the limit. So a key the frames do not constrain (the SNR at a high SNR) does not make an independent,
    well-constrained one (the row smoothing, on the grain) look unconstrained too."""
    k = x.shape[1]
    coef, *_ = np.linalg.lstsq(_quadratic_basis(x), y, rcond=None)
    g = coef[1 : k + 1]
    hessian = np.zeros((k, k))
    index = k + 1
    for i in range(k):
        for j in range(i, k):
            hessian[i, j] = hessian[j, i] = coef[index] * (2.0 if i == j else 1.0)
            index += 1
    eigen, vectors = np.linalg.eigh(hessian)
    curved = eigen > 1e-12 * max(abs(eigen).max(), 1e-300)
    slope = vectors.T @ g  # the gradient at the centre along each eigen-direction
    steps = np.where(curved, -slope / np.where(curved, eigen, 1.0), -np.sign(slope) * limit)
    x_min = vectors @ steps
    unbounded = (np.abs(vectors[:, ~curved]) > UNBOUNDED_LOADING).any(axis=1)
    clipped = unbounded | (np.abs(x_min) > limit)
    return np.clip(x_min, -limit, limit), clipped


def joint_uncertainty(params: list, values: dict, objective, resamples: list) -> dict[str, dict]:
    """Marginal spread of each continuous key's fitted value with the others free.

    Args:
        params: :class:`~.parameters.UnpairedParameter` entries; the continuous ones (not
            integer, no choices) are used, when there are at least two.
        values: the fitted values (preset keys).
        objective: ``objective(values, resample) -> float`` total distance; ``resample`` is None
            (all frames) or one entry of ``resamples``.
        resamples: the bootstrap's (real_idx, sim_idx) pairs.

    Returns:
        {key: {"std": value units, "std_search": search coordinate, "p05", "p95", "clipped": share of resamples that
        clipped this key, "lower_bound": bool}}; empty when fewer than two keys are continuous.
    """
    keys = [p for p in params if not p.integer and not p.choices]
    if len(keys) < 2 or not resamples:
        return {}
    steps = np.array([DESIGN_STEP * p.step() for p in keys])
    centre = np.array([p.to_unit(values[p.key]) for p in keys])
    points = []
    for offset in design_offsets(len(keys)):
        point = dict(values)
        for p, unit in zip(keys, centre + offset * steps):
            point[p.key] = p.from_unit(unit)  # clipped to the key's bounds
        points.append(point)
    # Design coordinates of the points actually evaluated (a bound clips some), in design steps.
    x = np.array([[(p.to_unit(pt[p.key]) - c) / s for p, c, s in zip(keys, centre, steps)] for pt in points])
    limit = MAX_STEPS / DESIGN_STEP
    draws, clipped = [], []
    for resample in resamples:
        y = np.array([objective(pt, resample) for pt in points])
        x_min, was_clipped = quadratic_minimum(x, y, limit)
        draws.append([p.from_unit(c + xm * s) for p, c, xm, s in zip(keys, centre, x_min, steps)])
        clipped.append(was_clipped)
    draws = np.array(draws, float)
    share = np.mean(clipped, axis=0)  # (k,) per key
    return {p.key: {"std": float(draws[:, i].std()), "std_search": search_std(p, draws[:, i]),
                    "p05": float(np.percentile(draws[:, i], 5)), "p95": float(np.percentile(draws[:, i], 95)),
                    "clipped": float(share[i]), "lower_bound": bool(share[i] > 0.2)}
            for i, p in enumerate(keys)}  # fmt: skip
