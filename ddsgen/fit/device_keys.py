"""Device keys of the preset in the fit: fall-off exponents, speckle, shot noise, clean-up sizes.

The device-faithful kinect_v1 has keys that are plain preset values, not tensors of the
:class:`~ddsgen.sensor.depth_sensor.DepthSensor`: they act through the noise draws (speckle
grain and contrast), a non-differentiable selection (the clean-up sizes are connected-component
thresholds: integers) or the IR image's brightness field (the projector's and the lens's fall-off,
whose only trace in depth is where the matcher's confidence drops below its threshold: validity,
which has no gradient). So each is fitted by a **1-D search** over a grid within its bounds
(:data:`ddsgen.fit.parameters.SENSOR_PARAMS` entries with ``attr=None``; integers for integer keys),
minimising the fit loss (depth + roughness + validity, same noise draws at every value) plus the
prior toward the input value, holding the other parameters; searched in table order, once.

What the depth images do not separate is said, not guessed: the projector fall-off and the lens
vignetting multiply the same image-radius profile (the projector sits 7.5 cm beside the camera,
so both are cos^n of almost the same angle) -- when both are asked for, only their sum is searched
(the projector's exponent, the vignetting held), like eta_c and the read noise.

The searched value is written into ``sensor.preset`` (``DepthSensor.forward`` reads these keys
from it on every call), and mirrored in a 0-d tensor per key (:func:`mirror`) so that
snapshot/revert (:mod:`ddsgen.fit.revert`) treat it like every other fitted tensor
(:func:`apply_mirrors` writes a reverted mirror back into the preset).
"""

from __future__ import annotations

import math

import numpy as np
import torch
#: Grid points of a continuous key's search (over its bounds); integer keys use at most this many integers.
GRID_POINTS = 9
#: Pairs whose effects on depth are the same profile: (searched, held when both are asked for).
CONFOUNDED = {"vignetting": "projector_falloff"}


def is_device_key(spec) -> bool:
    return spec.attr is None


def integer_key(sensor, key: str) -> bool:
    return isinstance(getattr(sensor.preset, key), (int, np.integer)) and not isinstance(
        getattr(sensor.preset, key), bool)


def mirror(sensor, key: str) -> torch.Tensor:
    """The 0-d float64 tensor mirroring preset key ``key`` (created from the preset on first use)."""
    mirrors = sensor.__dict__.setdefault("_fit_device_keys", {})
    if key not in mirrors:
        mirrors[key] = torch.tensor(float(getattr(sensor.preset, key)), dtype=torch.float64)
    return mirrors[key]


def apply_mirrors(sensor) -> None:
    """Write every mirrored key's tensor value into ``sensor.preset`` (integers rounded)."""
    mirrors = sensor.__dict__.get("_fit_device_keys", {})
    changes = {}
    for key, tensor in mirrors.items():
        value = float(tensor)
        changes[key] = int(round(value)) if integer_key(sensor, key) else value
    if changes:
        sensor.preset = sensor.preset.replace(**changes)


def set_key(sensor, key: str, value: float) -> None:
    with torch.no_grad():
        mirror(sensor, key).fill_(float(value))
    apply_mirrors(sensor)


def stored(spec, value: float) -> float:
    return math.log(max(value, 1e-12)) if spec.log else float(value)


def search_grid(sensor, spec) -> np.ndarray:
    """Candidate values of a device key within its bounds (physical units)."""
    start = float(getattr(sensor.preset, spec.key))
    if spec.log and start <= 0:  # switched off in the input (e.g. no shot noise): a factor of 0 stays 0
        return np.array([start])
    lo, hi = spec.stored_bounds(stored(spec, start))
    grid = np.linspace(lo, hi, GRID_POINTS)
    values = np.exp(grid) if spec.log else grid
    if integer_key(sensor, spec.key):
        values = np.unique(np.round(values).astype(int)).astype(float)
    return np.unique(np.append(values, start))


def search_device_key(sensor, name: str, spec, loss_of, prior_mm: float) -> dict:
    """1-D grid search of one device key (see the module docstring).

    Args:
        loss_of: callable () -> mean fit loss (mm) over the fit frames at the sensor's current values.
        prior_mm: weight of the prior toward the start value.

    Returns:
        {"method", "parameter", "start", "estimate", "objective_start", "objective", "profile": [(value, loss)]}.
    """
    start = float(getattr(sensor.preset, spec.key))
    profile = []
    for value in search_grid(sensor, spec):
        set_key(sensor, spec.key, value)
        prior = prior_mm * ((stored(spec, value) - stored(spec, start)) / spec.width) ** 2
        profile.append((float(value), float(loss_of()) + prior))
    best, best_loss = min(profile, key=lambda p: p[1])
    set_key(sensor, spec.key, best)
    start_loss = next(loss for value, loss in profile if value == start)
    return {"method": "1-D grid search on the fit loss + prior", "parameter": name, "start": start,
            "estimate": float(getattr(sensor.preset, spec.key)), "objective_start": start_loss,
            "objective": best_loss, "profile": [[round(v, 6), round(l, 5)] for v, l in profile]}  # fmt: skip


def search_device_keys(sensor, names: list[str], table: dict, loss_of, prior_mm: float) -> dict:
    """Search every device key in ``names`` (table order); returns name -> search result (or a 'held' note)."""
    out = {}
    asked = [n for n in names if n in table and is_device_key(table[n])]
    for name in asked:
        other = CONFOUNDED.get(name)
        if other in asked:
            out[name] = {"method": f"held: only the sum with {other} is identifiable ({other} searched)",
                         "parameter": name, "held": True}  # fmt: skip
            continue
        out[name] = search_device_key(sensor, name, table[name], loss_of, prior_mm)
    return out


def device_key_values(sensor, table: dict) -> dict:
    """Current values of every device key of ``table`` (preset key -> value), for reports."""
    return {spec.key: getattr(sensor.preset, spec.key) for spec in table.values() if is_device_key(spec)}

