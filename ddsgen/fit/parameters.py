"""The fittable sensor parameters: their table, what a name on the command line stands for, their current values.

:data:`SENSOR_PARAMS` maps each CLI name to the :class:`~ddsgen.sensor.depth_sensor.DepthSensor` tensor (or, for a
device key of the preset, ``attr=None``: :mod:`ddsgen.fit.device_keys`), its bounds, prior and group
(:mod:`ddsgen.fit.priors`), derived from the parameter registry (:mod:`ddsgen.parameters`). :func:`resolve_params`
turns names (``--params``) into the tensors :func:`ddsgen.fit.fitting.fit_sensor` moves, :func:`physical_values` reads
the values reports show, :func:`values_to_write` the values a written preset holds.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from ddsgen.errors import InputError
from ddsgen.fit.device_keys import device_key_values, is_device_key, mirror
from ddsgen.fit.priors import SensorParam
from ddsgen.parameters import fit_rules
from ddsgen.sensor.effects import REGISTRY
from ddsgen.sensor.postprocess import PostProcessCNN

DEFAULT_PARAMS = ("emitted_intensity", "read_noise_std", "beta", "baseline")
#: What ``ddsgen fit`` fits when ``--params`` is not given: the paper's four, and the device behaviours the real depth
#: shows directly -- its edge rule (windows across depth edges kept) and its clean-up sizes -- on 1-D grids, so a fit
#: from a preset without them (kinect_v1_paper) can reach the device; each group is kept only if it lowers the
#: held-out gap.
COMMAND_DEFAULT_PARAMS = DEFAULT_PARAMS + ("confirmed_match", "cleanup_fill_width", "cleanup_hole", "cleanup_speckle")
#: Fittable sensor parameters by CLI name: the DepthSensor tensor, bounds, prior and group (:class:`SensorParam`), in
#: the fit's order -- the ``fit`` records of the parameter registry (a sensor parameter joins the fit with a ``fit``
#: record on its key in :data:`ddsgen.parameters.PARAMETERS`).
SENSOR_PARAMS: dict[str, SensorParam] = fit_rules()


def param_names_help() -> str:
    return ", ".join([*SENSOR_PARAMS, "effects", "effect:NAME[.PARAM]", "cnn"])


def resolve_params(sensor, names) -> dict[str, list[torch.nn.Parameter]]:
    """Map parameter names to the tensors they stand for; attaches a CNN for ``cnn``.

    Names: the keys of :data:`SENSOR_PARAMS`; ``effects`` (every effect's parameters);
    ``effect:NAME`` or ``effect:NAME.PARAM``; ``cnn``.

    Raises:
        InputError: unknown name or an effect the preset does not list.
    """
    out: dict[str, list[torch.nn.Parameter]] = {}
    effects = {e.name: e for e in sensor.effects}
    for name in names:
        if name in SENSOR_PARAMS:
            spec = SENSOR_PARAMS[name]
            out[name] = [mirror(sensor, spec.key) if is_device_key(spec) else getattr(sensor, spec.attr)]
        elif name == "effects":
            for effect in sensor.effects:
                for key, p in effect.raw.items():
                    out[f"effect:{effect.name}.{key}"] = [p]
        elif name.startswith("effect:"):
            effect_name, _, key = name[len("effect:"):].partition(".")
            if effect_name not in effects:
                fix = (f"; to fit it, list it under the preset's effects: (- name: {effect_name}), or let "
                       f"ddsgen diagnose --candidates {effect_name} --apply add it" if effect_name in REGISTRY else
                       f"; the library has no such effect either (known: {', '.join(sorted(REGISTRY))})")  # fmt: skip
                raise InputError(f"--params: {name}: the preset has no effect {effect_name!r} "
                                 f"(listed: {', '.join(effects) or 'none'}){fix}")  # fmt: skip
            raw = effects[effect_name].raw
            if key and key not in raw:
                raise InputError(f"--params: {name}: effect {effect_name} has no parameter {key!r} "
                                 f"(has: {', '.join(raw)})")  # fmt: skip
            for k, p in raw.items():
                if not key or k == key:
                    out[f"effect:{effect_name}.{k}"] = [p]
        elif name == "cnn":
            if sensor.postprocess is None:
                sensor.postprocess = PostProcessCNN().to(sensor.device_)
            out["cnn"] = list(sensor.postprocess.parameters())
        else:
            raise InputError(f"--params: unknown parameter {name!r} (known: {param_names_help()})")
    return out


def physical_values(sensor) -> dict:
    """Physical parameter values plus effect values (plain floats), for reports."""
    values = {k: round(v, 9) for k, v in sensor.physical_parameters().items()}
    values.update(device_key_values(sensor, SENSOR_PARAMS))
    for effect in sensor.effects:
        for key, value in effect.values().items():
            values[f"effect:{effect.name}.{key}"] = round(value, 9)
    return values


#: Relative difference within which a value is the input's own after a float32 (and log-exp) round trip.
FLOAT32_ROUND_TRIP = 2e-6


def preset_values(sensor, original) -> dict:
    """The sensor's physical values as a fitted or extended preset file holds them (:func:`values_to_write`): the
    keys of :meth:`~ddsgen.sensor.depth_sensor.DepthSensor.physical_parameters`, with the focal lengths those of
    ``original`` (the user's preset, whose camera may differ from the scans') times the fitted focal scale."""
    values = sensor.physical_parameters()
    scale = float(sensor.focal_scale.detach())
    values["focal_px"], values["focal_y_px"] = original.focal_px * scale, original.focal_y_px * scale
    return values_to_write(values, original)


def values_to_write(values: dict, original) -> dict:
    """Preset values as a fitted or extended preset file should hold them.

    The sensor holds its parameters as float32 (several as logs), so a value the fit did not move comes back as
    0.07499999552965164 for 0.075, or 1500000.375 for 1500000. Such a value is written as the input preset's own
    (``original``'s); any other with the fewest decimal digits that give the same float32. Non-float values pass.
    """
    out = {}
    for key, value in values.items():
        before = getattr(original, key, None)
        if not isinstance(value, float) or not math.isfinite(value):
            out[key] = value
        elif (isinstance(before, (int, float)) and not isinstance(before, bool)
              and math.isclose(value, before, rel_tol=FLOAT32_ROUND_TRIP, abs_tol=0.0)):  # fmt: skip
            out[key] = before
        else:
            out[key] = float(np.format_float_positional(np.float32(value), unique=True))
    return out
