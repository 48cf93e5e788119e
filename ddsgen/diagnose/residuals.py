"""Residual analysis: where do simulation and measurement disagree, and along which axis?

For every pixel of a frame's comparison region (:mod:`ddsgen.realscan.simulate`) two residuals:

* depth error ``sim - real`` (mm) where both are valid and the sensor resolves depth (nearer than
  the frame's ``resolved_depth_m``, as the gap's depth terms; clipped to +-:data:`CLIP_MM`, so a
  few flying pixels cannot dominate a bin);
* validity disagreement ``sim_valid - real_valid`` in {-1, 0, 1} (> 0: the simulation reports
  depth that the real sensor did not).

They are binned along seven axes: ``depth`` (clean depth, m), ``incidence`` (angle between the
surface normal and the viewing ray, deg), ``radius``, ``row`` and ``column`` (normalised image
coordinates r, y, x as the effects use them, :data:`~ddsgen.sensor.effects.features.PIXEL_AXES`;
a crop sees the values of the full frame), ``edge_distance`` (px to the
nearest depth discontinuity of the clean depth) and ``signal`` (local mean of the simulated IR
image, counts). Statistics are kept per frame (sums per bin), so profiles pool frames and a
bootstrap over frames gives their sampling noise.

The **structure** of an axis is the weighted RMS deviation of its bias profile from its mean,
combined with that of its validity profile (scaled by :data:`~ddsgen.realscan.losses.VALIDITY_MM`,
so both are in mm): ``S = sqrt(S_bias^2 + S_valid^2)``. Its **noise** is the same quantity
expected from sampling noise alone, ``sqrt(sum_b w_b SE_b^2)`` with bin standard errors from a
bootstrap over frames; the **excess** ``sqrt(max(S^2 - noise^2, 0))`` is what the axis
explains beyond noise.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass

import numpy as np
import torch

from ddsgen.realscan.losses import VALIDITY_MM, depth_compared
from ddsgen.sensor.effects.features import edge_distance, local_signal, normalised_coordinates

#: Depth errors are clipped to +- this (mm) before averaging.
CLIP_MM = 60.0

#: Axes and their labels (units).
AXES: dict[str, str] = {
    "depth": "depth (m)",
    "incidence": "incidence angle (deg)",
    "radius": "image radius sqrt(x^2 + y^2) (normalised: x = (u - cx) / fx, y = (v - cy) / fy)",
    "row": "image row y = (v - cy) / fy (normalised)",
    "column": "image column x = (u - cx) / fx (normalised)",
    "edge_distance": "distance to the nearest depth edge (px)",
    "signal": "local IR level of the simulation (counts)",
}
#: How an axis reads in a sentence.
AXIS_WORDS: dict[str, str] = {
    "depth": "with depth",
    "incidence": "with the incidence angle of the surface",
    "radius": "with the distance from the image centre",
    "row": "along image rows (top to bottom)",
    "column": "along image columns (left to right)",
    "edge_distance": "with the distance to depth edges",
    "signal": "with the IR signal level",
}
N_BINS = 10
# Fixed edges where the axis has a natural scale; the others use pooled quantiles.
_EDGE_BINS = np.array([0.0, 1.0, 2.0, 3.0, 4.0, 6.0, 9.0, 14.0, 20.0, 30.0, np.inf])


def frame_axes(frame, sim) -> dict[str, torch.Tensor]:
    """Per-pixel axis values (H, W) of a prepared frame and its simulation.

    Image position is in the effects' units (:data:`~ddsgen.sensor.effects.features.PIXEL_AXES`):
    normalised coordinates x = (u - cx) / fx, y = (v - cy) / fy and r = sqrt(x^2 + y^2), so a profile
    read here is the profile an axis term along that axis fits.
    """
    h, w = frame.shape
    intr = frame.intrinsics
    xn, yn = normalised_coordinates(h, w, intr.fx, intr.fy, intr.cx, intr.cy)
    cache = getattr(frame, "_diagnose_edge_distance", None)
    if cache is None:
        cache = edge_distance(frame.clean_depth)
        try:
            frame._diagnose_edge_distance = cache
        except AttributeError:  # pragma: no cover - slotted dataclass
            pass
    return {
        "depth": frame.clean_depth,
        "incidence": frame.incidence_deg,
        "radius": torch.sqrt(xn * xn + yn * yn),
        "row": yn,
        "column": xn,
        "edge_distance": cache,
        "signal": local_signal(sim.ir.detach().float()),
    }


@dataclass
class PixelResiduals:
    """Residuals of the region pixels of several frames, flattened.

    axes: name -> (N,) axis values; frame: (N,) frame position; error_mm: (N,) sim - real depth
    (NaN where not both valid); valid_diff: (N,) sim_valid - real_valid.
    """

    axes: dict[str, np.ndarray]
    frame: np.ndarray
    error_mm: np.ndarray
    valid_diff: np.ndarray
    n_frames: int


def pixel_residuals(frames, sims, stride: int = 1) -> PixelResiduals:
    """Collect the residuals of ``frames`` against their simulations ``sims`` (SensorOutput, same order).

    ``stride`` subsamples the pixel grid (memory for large frames; the statistics barely change).
    """
    axes: dict[str, list] = {k: [] for k in AXES}
    fr, err, vd = [], [], []
    for i, (frame, sim) in enumerate(zip(frames, sims)):
        region = frame.region.clone()
        if stride > 1:
            keep = torch.zeros_like(region)
            keep[::stride, ::stride] = True
            region &= keep
        values = frame_axes(frame, sim)
        sim_valid = sim.valid.detach()
        real_valid = frame.real_valid
        both = sim_valid & real_valid & depth_compared(frame)  # depth errors only where the sensor resolves them
        e = (sim.depth.detach() - frame.real_depth) * 1000.0
        e = torch.where(both, e.clamp(-CLIP_MM, CLIP_MM), torch.full_like(e, float("nan")))
        for k in AXES:
            axes[k].append(values[k][region].numpy().astype(np.float32))
        err.append(e[region].numpy().astype(np.float32))
        vd.append((sim_valid.float() - real_valid.float())[region].numpy().astype(np.float32))
        fr.append(np.full(int(region.sum()), i, np.int32))
    cat = np.concatenate
    return PixelResiduals({k: cat(v) for k, v in axes.items()}, cat(fr), cat(err), cat(vd), len(frames))


def bin_edges(values: np.ndarray, axis: str, n_bins: int = N_BINS) -> np.ndarray:
    """Bin edges of an axis: fixed for ``edge_distance``, pooled quantiles (deduplicated) otherwise."""
    if axis == "edge_distance":
        return _EDGE_BINS.copy()
    finite = values[np.isfinite(values)]
    if finite.size == 0:
        return np.array([0.0, 1.0])
    if axis in ("row", "column"):  # even spacing: a periodic pattern along the image shows as such
        lo, hi = float(finite.min()), float(finite.max()) + 1.0
        return np.linspace(lo, hi, 2 * n_bins + 1)
    edges = np.unique(np.quantile(finite, np.linspace(0.0, 1.0, n_bins + 1)))
    if edges.size < 2:
        edges = np.array([edges[0] - 0.5, edges[0] + 0.5])
    edges[-1] = np.nextafter(edges[-1], np.inf)
    return edges


@dataclass
class AxisStats:
    """Per-frame sums per bin along one axis (arrays (F, B))."""

    axis: str
    edges: np.ndarray
    n_err: np.ndarray
    s_err: np.ndarray
    n_px: np.ndarray
    s_vdiff: np.ndarray

    def profile(self, weights: np.ndarray | None = None) -> dict:
        """Pooled profile; ``weights`` (F,) multiplies each frame's sums (for the bootstrap)."""
        w = np.ones(self.n_err.shape[0]) if weights is None else weights
        n_err = w @ self.n_err
        n_px = w @ self.n_px
        with np.errstate(invalid="ignore", divide="ignore"):
            bias = (w @ self.s_err) / n_err
            vdiff = (w @ self.s_vdiff) / n_px
        return {"n_err": n_err, "n_px": n_px, "bias_mm": bias, "valid_diff": vdiff}

    def centres(self) -> np.ndarray:
        e = self.edges.copy()
        if not np.isfinite(e[-1]):
            e[-1] = e[-2] + (e[-2] - e[-3] if len(e) > 2 else 1.0)
        return 0.5 * (e[:-1] + e[1:])


def axis_stats(res: PixelResiduals, axis: str, edges: np.ndarray | None = None) -> AxisStats:
    values = res.axes[axis]
    edges = bin_edges(values, axis) if edges is None else edges
    b = np.clip(np.searchsorted(edges, values, side="right") - 1, 0, len(edges) - 2)
    nb, nf = len(edges) - 1, res.n_frames
    idx = res.frame.astype(np.int64) * nb + b
    has = np.isfinite(res.error_mm)
    size = nf * nb

    def acc(weights, mask=None):
        if mask is None:
            return np.bincount(idx, weights=weights, minlength=size).reshape(nf, nb)
        return np.bincount(idx[mask], weights=None if weights is None else weights[mask], minlength=size).reshape(nf, nb)

    return AxisStats(
        axis=axis, edges=edges, n_err=acc(None, has).astype(np.float64), s_err=acc(res.error_mm.astype(np.float64), has),
        n_px=acc(None).astype(np.float64), s_vdiff=acc(res.valid_diff.astype(np.float64)),
    )  # fmt: skip


def _structure(profile: dict, min_count: float = 30.0) -> tuple[float, float, float]:
    """(S_bias, S_valid, S) of a profile: weighted RMS deviations from the weighted mean (mm)."""

    def rms(values, counts):
        ok = np.isfinite(values) & (counts >= min_count)
        if ok.sum() < 2:
            return 0.0
        w = counts[ok] / counts[ok].sum()
        m = float(w @ values[ok])
        return float(math.sqrt(max(w @ (values[ok] - m) ** 2, 0.0)))

    sb = rms(profile["bias_mm"], profile["n_err"])
    sv = VALIDITY_MM * rms(profile["valid_diff"], profile["n_px"])
    return sb, sv, math.hypot(sb, sv)


@dataclass
class AxisStructure:
    axis: str
    bias_mm: float  # S_bias
    validity_mm: float  # S_valid
    strength_mm: float  # S
    noise_mm: float
    excess_mm: float

    @property
    def significant(self) -> bool:
        return self.excess_mm > 0 and self.strength_mm >= 2.0 * self.noise_mm


def axis_structure(stats: AxisStats, rng: np.random.Generator, n_boot: int = 200) -> AxisStructure:
    """Structure of one axis and its bootstrap noise floor (resampling frames with replacement)."""
    sb, sv, s = _structure(stats.profile())
    nf = stats.n_err.shape[0]
    if nf < 2:
        return AxisStructure(stats.axis, sb, sv, s, float("inf"), 0.0)
    boots_b, boots_v = [], []
    for _ in range(n_boot):
        weights = np.bincount(rng.integers(0, nf, nf), minlength=nf).astype(np.float64)
        p = stats.profile(weights)
        boots_b.append(p["bias_mm"])
        boots_v.append(p["valid_diff"])
    base = stats.profile()
    with np.errstate(invalid="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # bins empty in every resample: NaN, ignored below
        se_b = np.nanstd(np.array(boots_b), axis=0)
        se_v = np.nanstd(np.array(boots_v), axis=0) * VALIDITY_MM
    wb = np.where(np.isfinite(base["bias_mm"]) & (base["n_err"] >= 30), base["n_err"], 0.0)
    wv = np.where(np.isfinite(base["valid_diff"]) & (base["n_px"] >= 30), base["n_px"], 0.0)
    nb = float(np.nansum(wb / max(wb.sum(), 1e-9) * se_b**2))
    nv = float(np.nansum(wv / max(wv.sum(), 1e-9) * se_v**2))
    noise = math.sqrt(nb + nv)
    return AxisStructure(stats.axis, sb, sv, s, noise, math.sqrt(max(s * s - noise * noise, 0.0)))


def analyse(res: PixelResiduals, seed: int = 0, edges: dict | None = None) -> dict[str, tuple[AxisStats, AxisStructure]]:
    """Stats and structure of every axis (``edges``: fixed bin edges per axis, e.g. from a baseline)."""
    rng = np.random.default_rng([seed, 4242])
    out = {}
    for axis in AXES:
        stats = axis_stats(res, axis, None if edges is None else edges.get(axis))
        out[axis] = (stats, axis_structure(stats, rng))
    return out
