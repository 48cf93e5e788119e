"""Beyond the library: a generic smooth term along the axis where residual structure remains.

When no named effect clears the acceptance rule, diagnose tries the generic terms of
:mod:`ddsgen.sensor.effects.axis_terms` along the axes whose residual structure is beyond noise:

* ``axis_disparity_term`` along an axis with *bias* structure: the disparity residual
  ``d_real - d_sim = f b (1/z_real - 1/z_sim)`` (px) of the pixels valid in both, fitted by trimmed
  least squares with a Legendre series along the axis (plus an affine term per frame on the
  support plane, which was fitted to the real depth and absorbed the affine part there);
* ``axis_validity_term`` along an axis with *validity* structure: the keep-probability that turns
  the simulation's valid rate into the real one, bin by bin (``p = real rate / sim rate``, at
  most 1), fitted as a Legendre series of its logit ``s`` (``p = min(1, 2 sigmoid(s))``) weighted
  by the pixels of each bin.

The fitted shape is scaled by a few factors and the factor with the largest credited fall of the
gap on the fit frames is kept (:func:`fit_axis_candidate`); it is then judged on the held-out
frames by the same rule as every named effect. A term that cannot be fitted is a failed fit
(:class:`FailedFit`), never tried on the held-out frames: one whose coefficients reach their
bounds (the least-squares shape did not fit inside the physical range: the residual along that
axis is not a smooth term's), or one that does not lower the gap on the fit frames themselves. An accepted term is reported as an *unnamed
effect along that axis* with its shape and the physical effects that produce such a shape.
Axis values are in the effects' units (:data:`~ddsgen.sensor.effects.features.PIXEL_AXES`).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import torch

from ddsgen.diagnose.acceptance import UNEXPLAINED_MIN_MM, relative_fall
from ddsgen.diagnose.candidates import with_effect
from ddsgen.diagnose.evaluation import evaluate
from ddsgen.diagnose.plane import replaned
from ddsgen.sensor.effects import REGISTRY
from ddsgen.sensor.effects.axis_terms import COEFFICIENTS, axis_coordinate, fit_axis_coefficients, legendre_basis
from ddsgen.sensor.effects.features import edge_distance, local_signal, normalised_coordinates

DISPARITY_TERM, VALIDITY_TERM = "axis_disparity_term", "axis_validity_term"
#: A coefficient within this fraction of its bound counts as at the bound.
AT_BOUND = 0.98


@dataclasses.dataclass(frozen=True)
class FailedFit:
    """A generic term that could not be fitted on the fit frames, and why (it is not judged on held-out frames)."""

    reason: str
#: Factors of the least-squares shape tried on the fit frames (the fit of a noisy residual is shrunk or not).
SCALES = (0.5, 0.75, 1.0, 1.25)
#: Axes tried per kind of term: the strongest ones with structure beyond noise.
MAX_AXES = 3
#: Bins of the validity profile fitted by the validity term.
VALIDITY_BINS = 16


def label(name: str, axis: str) -> str:
    """How an axis term is named in steps and diagnosis.json: ``axis_disparity_term:column``."""
    return f"{name}:{axis}"


def split_label(effect: str) -> tuple[str, dict]:
    """``axis_disparity_term:column`` -> ("axis_disparity_term", {"axis": "column"}); a named effect -> (name, {})."""
    name, _, axis = effect.partition(":")
    return name, ({"axis": axis} if axis else {})


def effect_axis_values(axis: str, frame, sim) -> torch.Tensor:
    """(H, W) the value of ``axis`` at every pixel, as the sensor's axis terms see it (PIXEL_AXES units)."""
    h, w = frame.shape
    intr = frame.intrinsics
    if axis in ("radius", "row", "column"):
        xn, yn = normalised_coordinates(h, w, intr.fx, intr.fy, intr.cx, intr.cy)
        return {"radius": torch.sqrt(xn * xn + yn * yn), "row": yn, "column": xn}[axis]
    if axis == "edge_distance":
        return edge_distance(frame.clean_depth)
    if axis == "incidence":
        return frame.incidence_deg
    if axis == "signal":
        return local_signal(sim.ir.detach().float())
    if axis == "depth":
        return sim.depth.detach()
    raise KeyError(axis)


def disparity_guess(axis: str, sensor, frames, sims) -> list[float] | None:
    """Least-squares Legendre coefficients (px) of the disparity residual along ``axis`` (module docstring)."""
    fb = float(sensor.baseline.detach()) * float(sensor.focal_scale.detach())
    values, targets, nuisance = [], [], []
    for i, (f, sim) in enumerate(zip(frames, sims)):
        both = f.region & sim.valid & f.real_valid
        if not bool(both.any()):
            continue
        z_real, z_sim = f.real_depth[both].double(), sim.depth.detach()[both].double()
        intr = f.intrinsics
        xn, yn = normalised_coordinates(*f.shape, intr.fx, intr.fy, intr.cx, intr.cy)
        plane = (f.instance[both] == 0).double()
        block = torch.zeros(plane.shape[0], 3 * len(frames), dtype=torch.float64)
        block[:, 3 * i : 3 * i + 3] = torch.stack([plane, plane * xn[both].double(), plane * yn[both].double()], 1)
        nuisance.append(block.numpy())
        values.append(effect_axis_values(axis, f, sim)[both].double().numpy())
        targets.append((intr.fx * fb * (1.0 / z_real - 1.0 / z_sim)).numpy())
    if not targets:
        return None
    return fit_axis_coefficients(axis, np.concatenate(values), np.concatenate(targets),
                                 nuisance=np.concatenate(nuisance), keep_quantile=0.8)  # fmt: skip


def validity_guess(axis: str, frames, sims) -> list[float] | None:
    """Legendre coefficients (logit) of the keep-probability that maps the sim's valid rate onto the real one."""
    values, real, sim_valid = [], [], []
    for f, sim in zip(frames, sims):
        values.append(effect_axis_values(axis, f, sim)[f.region].double().numpy())
        real.append(f.real_valid[f.region].numpy())
        sim_valid.append(sim.valid[f.region].numpy())
    a, r, s = np.concatenate(values), np.concatenate(real), np.concatenate(sim_valid)
    if a.size == 0:
        return None
    edges = np.unique(np.quantile(a, np.linspace(0.0, 1.0, VALIDITY_BINS + 1)))
    if edges.size < 3:
        return None
    b = np.clip(np.searchsorted(edges, a, side="right") - 1, 0, edges.size - 2)
    n = np.bincount(b, minlength=edges.size - 1).astype(np.float64)
    real_rate = np.bincount(b, weights=r, minlength=edges.size - 1) / np.maximum(n, 1)
    sim_rate = np.bincount(b, weights=s, minlength=edges.size - 1) / np.maximum(n, 1)
    keep = np.clip(real_rate / np.maximum(sim_rate, 1e-6), 0.02, 1.0)
    logit = np.log(keep / (2.0 - keep))  # p = 2 sigmoid(s)  <=>  s = ln(p / (2 - p)); 0 at p = 1
    centres = np.array([np.median(a[b == k]) if n[k] else 0.5 * (edges[k] + edges[k + 1]) for k in range(n.size)])
    design = legendre_basis(axis_coordinate(axis, torch.as_tensor(centres))).T.numpy()
    ok = n > 0
    w = np.sqrt(n[ok])
    coef = np.linalg.lstsq(design[ok] * w[:, None], logit[ok] * w, rcond=None)[0]
    return [float(c) for c in coef]  # unclipped: a shape beyond the bounds is a failed fit (fit_axis_candidate)


def fit_axis_candidate(sensor, name: str, axis: str, frames, config, base, sims):
    """Add ``name`` along ``axis`` to a copy of ``sensor``, its shape read off the residual and its scale searched.

    ``frames`` are fit frames re-planed under ``sensor``, ``base`` its evaluation on them and ``sims`` its
    simulations of them. Returns (sensor with the term, values, -credited fall), a :class:`FailedFit` (its
    coefficients at their bounds, or no fall of the gap on the fit frames), or None when there is nothing to fit.
    """
    coef = disparity_guess(axis, sensor, frames, sims) if name == DISPARITY_TERM else validity_guess(axis, frames, sims)
    if coef is None or not np.any(np.abs(coef) > 1e-9):
        return None
    moves_depth = name == DISPARITY_TERM
    bound = REGISTRY[name].params[COEFFICIENTS[0]].high
    if np.any(np.abs(coef) >= AT_BOUND * bound):
        shape = ", ".join(f"{c:.3g}" for c in coef)
        return FailedFit(f"its least-squares coefficients reach their bounds (+-{bound:g}: {shape})")
    best = None
    for m in SCALES:
        values = {k: float(np.clip(m * c, -bound, bound)) for k, c in zip(COEFFICIENTS, coef)}
        candidate = with_effect(sensor, name, {"axis": axis, **values})
        trial = replaned(candidate, frames, config.seed) if moves_depth else frames
        score = -relative_fall(base, evaluate(candidate, trial, config.seed))
        if best is None or score < best[2]:
            best = (candidate, candidate.effects[-1].values(), score)
    if best[2] >= 0.0:  # never worse than no term on the frames it was fitted on
        return FailedFit(f"it does not lower the gap on the fit frames (best credited fall {-100 * best[2]:+.1f} %)")
    return best


def axes_to_try(analysis: dict) -> dict[str, list[str]]:
    """Per term, the axes whose bias (disparity term) or validity (validity term) structure is beyond noise.

    Only axes that would be reported as unexplained (significant and at least UNEXPLAINED_MIN_MM beyond noise)
    are tried: on data the model already explains, no generic term gets a chance to fit noise.
    """
    significant = [(axis, s) for axis, (_, s) in analysis.items() if s.significant and s.excess_mm >= UNEXPLAINED_MIN_MM]
    by_bias = sorted((x for x in significant if x[1].bias_mm >= x[1].noise_mm), key=lambda x: -x[1].bias_mm)
    by_valid = sorted((x for x in significant if x[1].validity_mm >= x[1].noise_mm), key=lambda x: -x[1].validity_mm)
    return {DISPARITY_TERM: [a for a, _ in by_bias[:MAX_AXES]], VALIDITY_TERM: [a for a, _ in by_valid[:MAX_AXES]]}
