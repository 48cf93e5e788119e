"""Simulation stages served from caches while their inputs do not change (diagnosis speed).

A diagnosis simulates the same frames hundreds of times, and most trials change only a late stage of
the sensor: a validity effect's threshold leaves the IR image, the matching and the depth as they
were; a disparity effect leaves the IR image. A :class:`StageCache` holds three caches, all bounded
(least recently used entries go):

* the block matcher's result for an identical IR image;
* the noise draws for a seed;
* everything before the validity stage (:meth:`~ddsgen.sensor.depth_sensor.DepthSensor.front_end`) for identical
  geometry, noise and parameters other than the validity effects'.

The cache is part of the sensors it is given to (``DepthSensor(..., stage_cache=cache)``; the candidates
:func:`~ddsgen.diagnose.device_candidates.sensor_like` makes carry their model's), not of the process: the sensor
asks it for its noise, its front end and its matches, and tells it each stage it computes (:attr:`StageCache.computed`:
machine-independent work, for benchmarks and tests). It serves only while :meth:`StageCache.serving` is active, and
only calls without gradients (the diagnosis' evaluations); a fit computes as usual.
"""

from __future__ import annotations

import contextlib
import hashlib
from collections import OrderedDict

import torch

from ddsgen.parameters import PARAMETERS, fit_rules, stage_keys

#: Entries kept by each cache. At 640 x 480 a match result holds 5 maps (~6 MB), a front end ~7 maps and its
#: noise draws (~15 MB): 32 front ends cover the fit frames x two noise draws of a candidate search with room to
#: spare. (An unbounded match cache grew a test worker to 3 GB; 256 matches + 48 front ends to 4.6 GB.)
MATCH_ENTRIES = 64
FRONT_END_ENTRIES = 32


class LruCache:
    """A dict that keeps its ``size`` most recently used entries."""

    def __init__(self, size: int):
        self.size = size
        self.entries: OrderedDict = OrderedDict()

    def get(self, key, compute):
        if key in self.entries:
            self.entries.move_to_end(key)
            return self.entries[key]
        value = compute()
        self.entries[key] = value
        if len(self.entries) > self.size:
            self.entries.popitem(last=False)
        return value


#: Preset keys read only by the validity stage (:meth:`~ddsgen.sensor.depth_sensor.DepthSensor.validity_stage`): the
#: clean-up's. Each is set to its default in the state.
VALIDITY_STAGE_KEYS = {key: PARAMETERS[key].default for key in stage_keys("cleanup")}


#: Preset keys the sensor holds as parameters (:class:`~ddsgen.sensor.depth_sensor.DepthSensor`) and its front end
#: reads nowhere else (the baseline's preset value places the ray casts, which the geometry holds): the fit's keys
#: stored in a tensor of their own value (the focal scale is a ratio to the preset's focal length).
PARAMETER_KEYS = tuple(rule.key for rule in fit_rules().values() if rule.attr is not None and not rule.tensor_is_ratio)


#: Effect stages the sensor runs after its front end (in its validity stage).
AFTER_FRONT_END = ("validity", "image")


def front_end_state(sensor) -> tuple:
    """Everything a sensor's front end depends on besides geometry and noise: the preset (without its effects),
    the camera, the values of every parameter and buffer except those of validity- and image-stage effects and of the
    post-processing (both act after the front end), the other effects' entries and the unit (its dots)."""
    later = {f"effects.{i}." for i, e in enumerate(sensor.effects) if e.stage in AFTER_FRONT_END} | {"postprocess."}
    tensors = tuple((name, tuple(t.detach().reshape(-1).tolist()))
                    for name, t in (*sensor.named_parameters(), *sensor.named_buffers())
                    if not any(name.startswith(prefix) for prefix in later))  # fmt: skip
    effects = tuple(repr(e.to_entry()) for e in sensor.effects if e.stage not in AFTER_FRONT_END)
    intr = sensor.intr
    # The clean-up's keys act in the validity stage too (a device-behaviour candidate changes only them). The keys
    # held as parameters take the parameters' values: the preset's only started them (a candidate's preset holds
    # the float32 round trip of the current values, 1500000.375 for 1500000.0: the same front end).
    current = sensor.physical_parameters()
    preset = sensor.preset.replace(effects=[], **VALIDITY_STAGE_KEYS, **{k: current[k] for k in PARAMETER_KEYS})
    return (repr(preset), (intr.width, intr.height, intr.fx, intr.fy, intr.cx, intr.cy),
            tensors, effects, sensor.unit)  # fmt: skip


class StageCache:
    """Matches, noise draws and front ends shared by the sensors that hold this cache (see the module docstring).

    A :class:`~ddsgen.sensor.depth_sensor.DepthSensor` with ``stage_cache`` set calls :meth:`noise`,
    :meth:`front_end` and :meth:`match` with the function that computes the value, and :meth:`count` for every
    stage it computes. The cached objects are kept alive by the cache, so the ids in the keys stay unique.

    Attributes:
        computed: {"front_end": n, "validity_stage": n}, the stages the sensors computed (not served).
        serve: whether the caches serve now (:meth:`serving`); False when made, so a sensor holding the cache
            computes everything until its owner turns serving on.
    """

    def __init__(self, match_entries: int = MATCH_ENTRIES, front_end_entries: int = FRONT_END_ENTRIES):
        self.matches = LruCache(match_entries)
        self.noises = LruCache(front_end_entries)
        self.front_ends = LruCache(front_end_entries)
        self.computed = {"front_end": 0, "validity_stage": 0}
        self.serve = False

    @contextlib.contextmanager
    def serving(self):
        """Serve from the caches while the context is active."""
        before, self.serve = self.serve, True
        try:
            yield self
        finally:
            self.serve = before

    def count(self, stage: str) -> None:
        """Record one computed ``stage`` ("front_end" or "validity_stage")."""
        self.computed[stage] += 1

    def match(self, matcher, observed, reference_phases, pad, d_min, d_max, block, beta, *args, **kwargs):
        """``matcher(observed, reference_phases, ...)`` (:func:`ddsgen.sensor.matcher.match`'s signature), served
        for an identical IR image (same bytes) and identical settings when neither the IR image nor beta needs a
        gradient. With only post-matching effect parameters free, every simulation after the first of a frame
        skips the matcher."""
        needs_grad = observed.requires_grad or (torch.is_tensor(beta) and beta.requires_grad)
        if needs_grad or not self.serve:
            return matcher(observed, reference_phases, pad, d_min, d_max, block, beta, *args, **kwargs)
        digest = hashlib.blake2b(observed.detach().contiguous().cpu().numpy().tobytes(), digest_size=16).hexdigest()
        key = (digest, tuple(observed.shape), reference_phases.data_ptr(), pad, round(float(d_min), 9),
               round(float(d_max), 9), block, round(float(beta), 9), args, tuple(sorted(kwargs.items())))  # fmt: skip
        return self.matches.get(key, lambda: matcher(observed, reference_phases, pad, d_min, d_max, block, beta,
                                                     *args, **kwargs))  # fmt: skip

    def noise(self, sensor, seed, geometry, draw):
        """``draw(seed, geometry)``, the sensor's noise draws, served for the same integer seed, unit and noise keys
        (and the same geometry object when the speckle is fixed to the scene): the same seed returns the same
        object. A Generator seed is drawn every time (its draws depend on its state)."""
        if not self.serve or not isinstance(seed, (int, tuple, list)):
            return draw(seed, geometry)
        p = sensor.preset
        key = (tuple(seed) if isinstance(seed, (tuple, list)) else seed, sensor.intr.height, sensor.intr.width,
               sensor.ir_margin_px, p.speckle_shape, p.speckle_grain_px, p.speckle_fixed_to_scene, sensor.unit,
               id(geometry) if geometry is not None else None)  # fmt: skip
        return self.noises.get(key, lambda: (draw(seed, geometry), geometry))[0]

    def front_end(self, sensor, geometry, noise, quantise, compute):
        """``compute(geometry, noise, quantise)``, the sensor's front end, served for the same geometry and noise
        objects and :func:`front_end_state` when no gradient is recorded."""
        if not self.serve or torch.is_grad_enabled():
            return compute(geometry, noise, quantise)
        key = (id(geometry), id(noise), quantise, front_end_state(sensor))
        return self.front_ends.get(key, lambda: (compute(geometry, noise, quantise), geometry, noise))[0]
