"""Simulation stages served from caches while their inputs do not change (diagnosis speed).

A diagnosis simulates the same frames hundreds of times, and most trials change only a late stage of
the sensor: a validity effect's threshold leaves the IR image, the matching and the depth as they
were; a disparity effect leaves the IR image. Two caches, both bounded (least recently used entries go):

* :func:`reuse_matches` -- the block matcher's result for an identical IR image;
* :func:`reuse_front_ends` -- the noise draws for a seed, and everything before the validity stage
  (:meth:`~ddsgen.sensor.depth_sensor.DepthSensor.front_end`) for identical geometry, noise and
  parameters other than the validity effects'.

Both serve only calls without gradients (the diagnosis' evaluations); a fit inside the context
computes as usual.
"""

from __future__ import annotations

import contextlib
import hashlib
from collections import OrderedDict

import torch

import ddsgen.sensor.depth_sensor as depth_sensor
from ddsgen.parameters import PARAMETERS, fit_rules, stage_keys
from ddsgen.sensor.depth_sensor import DepthSensor

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


@contextlib.contextmanager
def reuse_matches(size: int = MATCH_ENTRIES):
    """Serve block-matching results from a cache while the matcher's input does not change.

    Inside the context, :func:`ddsgen.sensor.matcher.match` as called by the sensor is wrapped:
    when neither the IR image nor beta needs a gradient, the result for an identical IR image
    (same bytes) and identical settings is computed once and reused. With only post-matching
    effect parameters free, every simulation after the first of a frame skips the matcher.
    """
    original = depth_sensor.match
    cache = LruCache(size)

    def cached_match(observed, reference_phases, pad, d_min, d_max, block, beta, *args, **kwargs):
        needs_grad = observed.requires_grad or (torch.is_tensor(beta) and beta.requires_grad)
        if needs_grad:
            return original(observed, reference_phases, pad, d_min, d_max, block, beta, *args, **kwargs)
        digest = hashlib.blake2b(observed.detach().contiguous().cpu().numpy().tobytes(), digest_size=16).hexdigest()
        key = (digest, tuple(observed.shape), reference_phases.data_ptr(), pad, round(float(d_min), 9),
               round(float(d_max), 9), block, round(float(beta), 9), args, tuple(sorted(kwargs.items())))  # fmt: skip
        return cache.get(key, lambda: original(observed, reference_phases, pad, d_min, d_max, block, beta, *args,
                                               **kwargs))  # fmt: skip

    depth_sensor.match = cached_match
    try:
        yield cache
    finally:
        depth_sensor.match = original


#: Preset keys read only by the validity stage (:meth:`~ddsgen.sensor.depth_sensor.DepthSensor.validity_stage`): the
#: clean-up's. Each is set to its default in the state.
VALIDITY_STAGE_KEYS = {key: PARAMETERS[key].default for key in stage_keys("cleanup")}


#: Preset keys the sensor holds as parameters (:class:`~ddsgen.sensor.depth_sensor.DepthSensor`) and its front end
#: reads nowhere else (the baseline's preset value places the ray casts, which the geometry holds): the fit's keys
#: stored in a tensor of their own value (the focal scale is a ratio to the preset's focal length).
PARAMETER_KEYS = tuple(rule.key for rule in fit_rules().values() if rule.attr is not None and not rule.tensor_is_ratio)


def front_end_state(sensor) -> tuple:
    """Everything a sensor's front end depends on besides geometry and noise: the preset (without its effects),
    the camera, the values of every parameter and buffer except those of validity-stage effects and of the
    post-processing (both act after the front end), the other effects' entries and the unit (its dots)."""
    later = {f"effects.{i}." for i, e in enumerate(sensor.effects) if e.stage == "validity"} | {"postprocess."}
    tensors = tuple((name, tuple(t.detach().reshape(-1).tolist()))
                    for name, t in (*sensor.named_parameters(), *sensor.named_buffers())
                    if not any(name.startswith(prefix) for prefix in later))  # fmt: skip
    effects = tuple(repr(e.to_entry()) for e in sensor.effects if e.stage != "validity")
    intr = sensor.intr
    # The clean-up's keys act in the validity stage too (a device-behaviour candidate changes only them). The keys
    # held as parameters take the parameters' values: the preset's only started them (a candidate's preset holds
    # the float32 round trip of the current values, 1500000.375 for 1500000.0: the same front end).
    current = sensor.physical_parameters()
    preset = sensor.preset.replace(effects=[], **VALIDITY_STAGE_KEYS, **{k: current[k] for k in PARAMETER_KEYS})
    return (repr(preset), (intr.width, intr.height, intr.fx, intr.fy, intr.cx, intr.cy),
            tensors, effects, sensor.unit)  # fmt: skip


@contextlib.contextmanager
def reuse_front_ends(size: int = FRONT_END_ENTRIES):
    """Serve noise draws and sensor front ends from caches (see the module docstring).

    Noise draws are keyed by their integer seed and the sensor's unit (and the geometry when the speckle is fixed
    to the scene),
    so the same seed returns the same object; front ends by that noise object, the geometry object and
    :func:`front_end_state`. The cached objects are kept alive by the cache, so their ids stay unique.
    """
    original_noise, original_front = DepthSensor.draw_noise, DepthSensor.front_end
    noises, fronts = LruCache(size), LruCache(size)

    def draw_noise(self, seed, geometry=None):
        if not isinstance(seed, (int, tuple, list)):  # a Generator: its draws depend on its state
            return original_noise(self, seed, geometry)
        p = self.preset
        key = (tuple(seed) if isinstance(seed, (tuple, list)) else seed, self.intr.height, self.intr.width,
               self.ir_margin_px, p.speckle_shape, p.speckle_grain_px, p.speckle_fixed_to_scene, self.unit,
               id(geometry) if geometry is not None else None)  # fmt: skip
        return noises.get(key, lambda: (original_noise(self, seed, geometry), geometry))[0]

    def front_end(self, geometry, noise, quantise=True):
        if torch.is_grad_enabled():
            return original_front(self, geometry, noise, quantise)
        key = (id(geometry), id(noise), quantise, front_end_state(self))
        return fronts.get(key, lambda: (original_front(self, geometry, noise, quantise), geometry, noise))[0]

    DepthSensor.draw_noise, DepthSensor.front_end = draw_noise, front_end
    try:
        yield fronts
    finally:
        DepthSensor.draw_noise, DepthSensor.front_end = original_noise, original_front


@contextlib.contextmanager
def counting_computed_stages():
    """Count the sensor stages actually computed while the context is active: yields a dict
    ``{"front_end": n, "validity_stage": n}`` that grows with every call of those
    :class:`~ddsgen.sensor.depth_sensor.DepthSensor` methods. Enter it *before* :func:`reuse_front_ends`
    wraps them, so that what the caches serve is not counted (machine-independent work, for
    benchmarks and tests)."""
    counts = {"front_end": 0, "validity_stage": 0}
    originals = {name: getattr(DepthSensor, name) for name in counts}

    def counted(name):
        method = originals[name]

        def wrapper(self, *args, **kwargs):
            counts[name] += 1
            return method(self, *args, **kwargs)

        return wrapper

    for name in counts:
        setattr(DepthSensor, name, counted(name))
    try:
        yield counts
    finally:
        for name, method in originals.items():
            setattr(DepthSensor, name, method)
