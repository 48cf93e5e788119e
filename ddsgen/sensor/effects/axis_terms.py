"""Generic smooth terms along one pixel axis: what diagnose fits when no named effect explains a residual.

A term is a low-order Legendre series over the axis' normalised range,
``s(t) = sum_k c_k P_k(t)``, ``t = 2 (a - low) / (high - low) - 1`` clamped to [-1, 1]
(constant beyond the range), with ``a`` the pixel's value on the axis
(:func:`~ddsgen.sensor.effects.features.pixel_axis`; domains in :data:`AXIS_DOMAINS`).
All coefficients zero is the neutral setting.

* ``axis_disparity_term`` adds ``s`` (px) to the matched disparity (stage ``"disparity"``);
* ``axis_validity_term`` multiplies the keep-probability by ``min(1, 2 sigmoid(s))``
  (stage ``"validity"``): 1 at s = 0 (neutral), below 0.5 -- the pixel dropped -- where
  s < -ln 3. It can only remove pixels, like every validity effect.

Preset entry: ``{name: axis_disparity_term, axis: column, coefficients: [0, 0.1, 0, -0.05, 0]}``
(or the scalars ``c0`` ... ``c4``). Each term knows its axis, a sentence about what it
does there and the physical effects that produce such a shape (:data:`PHYSICAL_CAUSES`);
:func:`axis_shape` returns the shape for plotting and :func:`fit_axis_coefficients` the
least-squares coefficients of a residual profile (a starting point for a search).
"""

from __future__ import annotations

import numpy as np
import torch

from ddsgen.sensor.effects import register
from ddsgen.effect_params import AXIS_DOMAINS, COEFFICIENTS, EFFECTS, N_COEFFICIENTS
from ddsgen.sensor.effects.base import Effect
from ddsgen.sensor.effects.context import EffectContext
from ddsgen.sensor.effects.features import PIXEL_AXES, pixel_axis

#: Physical effects that leave a smooth residual along each axis (what a user should look at).
PHYSICAL_CAUSES: dict[str, tuple[str, ...]] = {
    "radius": ("IR lens distortion", "vignetting of the IR lens", "projector beam fall-off",
               "disparity distortion field (Herrera 2012)"),
    "row": ("projector/camera misalignment across the epipolar lines (vertical disparity)",
            "tilt of the reference pattern", "disparity distortion field (Herrera 2012)"),
    "column": ("projector/camera misalignment (rotation about the vertical axis)", "reference pattern drift",
               "temperature-dependent pattern shift", "disparity distortion field (Herrera 2012)"),
    "edge_distance": ("edge fattening of the matching window", "projector shadow band",
                      "on-device clean-up of small segments near edges"),
    "incidence": ("grazing-angle dropout", "speckle and dot smearing on tilted surfaces",
                  "foreshortening bias of the matching window"),
    "depth": ("disparity offset", "depth (focal length x baseline) scale error", "low signal at far range",
              "disparity-dependent distortion"),
    "signal": ("low-signal dropout", "detector saturation on bright or near surfaces",
               "signal-dependent bias of the sub-pixel refinement"),
}  # fmt: skip


def legendre_basis(t: torch.Tensor, n: int = N_COEFFICIENTS) -> torch.Tensor:
    """Legendre polynomials P_0 .. P_{n-1} at ``t`` (any shape), stacked on a new first dim: (n, *t.shape).

    Bonnet's recurrence in torch (``torch.special.legendre_polynomial_p`` has no gradient in t).
    """
    basis = [torch.ones_like(t), t]
    for k in range(1, n - 1):
        basis.append(((2 * k + 1) * t * basis[k] - k * basis[k - 1]) / (k + 1))
    return torch.stack(basis[:n])


def axis_coordinate(axis: str, values: torch.Tensor) -> torch.Tensor:
    """Axis values (its units) -> t in [-1, 1] over :data:`AXIS_DOMAINS` (clamped)."""
    low, high = AXIS_DOMAINS[axis]
    if axis == "signal":
        values = torch.log10(values.clamp_min(1e-6))
    return (2.0 * (values - low) / (high - low) - 1.0).clamp(-1.0, 1.0)


class _AxisTerm(Effect):
    """A smooth Legendre series along one pixel axis (see the module docstring)."""

    generic = True
    signature = "a smooth bias or dropout profile along one pixel axis, fitted rather than derived from a cause"
    axis = "radius"  # default; each instance follows its own ``axis`` option
    options = EFFECTS["axis_disparity_term"].options  # the two terms share their axes and coefficients
    groups = EFFECTS["axis_disparity_term"].groups
    unit: str = ""

    def __init__(self, **values):
        super().__init__(**values)
        self.axis = self.choices["axis"]

    @property
    def causes(self) -> tuple[str, ...]:
        """Physical effects that produce a shape along this term's axis."""
        return PHYSICAL_CAUSES[self.axis]

    def coefficients(self) -> torch.Tensor:
        """(N_COEFFICIENTS,) the physical coefficient values (differentiable)."""
        return torch.stack([self.value(k) for k in COEFFICIENTS])

    def term(self, values: torch.Tensor) -> torch.Tensor:
        """The smooth term s (same shape as ``values``, which are in the axis' units)."""
        basis = legendre_basis(axis_coordinate(self.axis, values))
        c = self.coefficients().to(basis.dtype)
        return torch.tensordot(c, basis, dims=1)

    def describe(self) -> dict:
        """Axis, unit, what the term does and the physical effects that produce such a shape (plain data)."""
        return {
            "name": self.name, "axis": self.axis, "axis_unit": PIXEL_AXES[self.axis], "unit": self.unit,
            "description": f"{self.description[:-1]} (here: {self.axis.replace('_', ' ')}).",
            "causes": list(self.causes), "coefficients": [self.values()[k] for k in COEFFICIENTS],
        }  # fmt: skip


@register
class AxisDisparityTerm(_AxisTerm):
    """A smooth disparity bias along one pixel axis."""

    name = "axis_disparity_term"
    stage = "disparity"
    unit = "px"
    description = "An unnamed smooth disparity bias that varies along one pixel axis."
    params = EFFECTS["axis_disparity_term"].params

    def forward(self, disparity: torch.Tensor, ctx: EffectContext) -> torch.Tensor:
        """disparity (H, W) px -> disparity + s(axis) where a match exists (> 0)."""
        s = self.term(pixel_axis(self.axis, ctx, disparity, self.stage)).to(disparity.dtype)
        return torch.where(disparity > 0, disparity + s, disparity)


@register
class AxisValidityTerm(_AxisTerm):
    """A smooth dropout profile along one pixel axis."""

    name = "axis_validity_term"
    stage = "validity"
    unit = "logit"
    description = "An unnamed smooth dropout whose probability varies along one pixel axis."
    params = EFFECTS["axis_validity_term"].params

    def forward(self, depth: torch.Tensor, ctx: EffectContext) -> torch.Tensor:
        """depth (H, W) m -> keep-probability min(1, 2 sigmoid(s(axis))) (H, W)."""
        s = self.term(pixel_axis(self.axis, ctx, depth, self.stage)).to(depth.dtype)
        return keep_probability(s)


def keep_probability(s: torch.Tensor) -> torch.Tensor:
    """min(1, 2 sigmoid(s)): exactly 1 at s >= 0, 0.5 at s = -ln 3, -> 0 as s -> -inf."""
    return (2.0 * torch.sigmoid(s)).clamp(max=1.0)


def axis_shape(effect: _AxisTerm, points: int = 101) -> tuple[np.ndarray, np.ndarray]:
    """The shape of an axis term for plotting: (axis values (points,), term values (points,)).

    Axis values span :data:`AXIS_DOMAINS` in the axis' units (``signal`` in counts, log-spaced).
    Term values are the disparity bias (px) of ``axis_disparity_term`` or the keep-probability
    of ``axis_validity_term``.
    """
    low, high = AXIS_DOMAINS[effect.axis]
    grid = np.linspace(low, high, points)
    values = 10.0**grid if effect.axis == "signal" else grid
    with torch.no_grad():
        s = effect.term(torch.as_tensor(values, dtype=torch.float64))
        out = keep_probability(s) if effect.stage == "validity" else s
    return values, out.numpy()


def fit_axis_coefficients(axis: str, values, target, weights=None, nuisance=None, keep_quantile: float = 1.0,
                          n: int = N_COEFFICIENTS) -> list[float]:  # fmt: skip
    """Least-squares Legendre coefficients of ``target`` against ``values`` on ``axis``.

    Args:
        axis: a key of :data:`AXIS_DOMAINS`.
        values: (N,) axis values of the pixels (the axis' units).
        target: (N,) what the term should add, e.g. the disparity residual d_real - d_sim (px).
        weights: optional (N,) non-negative weights.
        nuisance: optional (N, M) regressors fitted jointly and discarded (e.g. an affine term per
            frame on a support plane that was fitted to the real depth and absorbed part of the shape).
        keep_quantile: trimmed fit (see :func:`least_squares`), e.g. 0.8.

    Returns:
        ``n`` coefficients within the parameters' range, e.g. a starting point of ``axis_disparity_term``
        (``{"axis": axis, "coefficients": [...]}``). When the pixels cover only part of the axis (the rows of
        one object), a high degree fits them with coefficients far beyond the range, whose clipped shape has
        nothing to do with the data; the degree is then lowered until the fit stays in range (the rest 0).
    """
    t = axis_coordinate(axis, torch.as_tensor(np.asarray(values, np.float64)))
    bound = AxisDisparityTerm.params["c0"].high
    design = legendre_basis(t, n).T.numpy()
    for degree in range(n, 0, -1):
        coef = least_squares(design[:, :degree], target, weights, nuisance, keep_quantile)
        if np.all(np.abs(coef) <= bound):
            break
    coef = np.concatenate([np.clip(coef, -bound, bound), np.zeros(n - len(coef))])
    return [float(c) for c in coef]


def least_squares(design: np.ndarray, target, weights=None, nuisance=None, keep_quantile: float = 1.0) -> np.ndarray:
    """Weighted least-squares coefficients of ``design`` (N, K) for ``target`` (N,).

    ``nuisance`` (N, M) columns are fitted alongside and dropped from the result (K,). With
    ``keep_quantile`` < 1 the fit is trimmed: three passes, each refitted on the rows whose
    absolute residual is within that quantile of the previous pass (mismatches and depth edges
    are not the shape being fitted).
    """
    a = np.asarray(design, np.float64)
    k = a.shape[1]
    if nuisance is not None:
        a = np.concatenate([a, np.asarray(nuisance, np.float64).reshape(len(a), -1)], 1)
    y = np.asarray(target, np.float64)
    if weights is not None:
        root = np.sqrt(np.asarray(weights, np.float64))
        a, y = a * root[:, None], y * root
    keep = np.ones(len(y), bool)
    coef = np.linalg.lstsq(a, y, rcond=None)[0]
    for _ in range(3 if keep_quantile < 1.0 else 0):
        deviation = np.abs(y - a @ coef)
        keep = deviation <= np.quantile(deviation, keep_quantile)
        coef = np.linalg.lstsq(a[keep], y[keep], rcond=None)[0]
    return coef[:k]
