"""The sensor as a composition of stages (ddsgen.sensor.stages): each stage owns the keys of one stage of the
parameter registry and reads no other, every preset key has exactly one owner, and a stage handed to a sensor is
used and survives a change of the sensor's preset."""

from __future__ import annotations

import dataclasses

import torch

from ddsgen.parameters import PARAMETERS, STAGES as REGISTRY_STAGES, stage_keys
from ddsgen.preset import load_preset
from ddsgen.sensor.depth_sensor import STAGES, DepthSensor
from ddsgen.sensor.matcher import match
from ddsgen.sensor.stages import BlockMatcher
from sensor_scenes import plane_geometry, small_kinect

#: Registry stages the sensor owns itself, not through a stage object: the preset's name, the camera (intrinsics,
#: baseline, depth range; the ray cast's shadow bias), the effects (each with its own parameters) and the
#: post-processing CNN.
OWNED_BY_THE_SENSOR = ("name", "camera", "effects", "postprocess")


class RecordingPreset:
    """A preset that records which of its keys are read."""

    def __init__(self, preset):
        self._preset = preset
        self.read: set[str] = set()

    def __getattr__(self, name):
        if name in PARAMETERS:
            self.read.add(name)
        return getattr(self._preset, name)


def test_each_stage_owns_its_registry_stages_keys_and_every_key_has_one_owner():
    owners = [cls.stage for cls in STAGES.values()] + list(OWNED_BY_THE_SENSOR)
    assert sorted(owners) == sorted(REGISTRY_STAGES)  # each registry stage owned exactly once ...
    owned = [key for stage in owners for key in stage_keys(stage)]
    assert sorted(owned) == sorted(PARAMETERS)  # ... so each preset key is
    for cls in STAGES.values():
        assert cls.keys == tuple(stage_keys(cls.stage)), cls.__name__
        # The keys the sensor holds as parameters are the stage's keys with a fitted tensor of their own.
        tensors = {key for key in cls.keys if PARAMETERS[key].fit is not None and PARAMETERS[key].fit.attr}
        assert set(cls.tensor_keys) == tensors, cls.__name__


def test_a_stage_reads_its_own_keys_and_no_other():
    for name in ("kinect_v1", "kinect_v1_paper"):
        for cls in STAGES.values():
            preset = RecordingPreset(load_preset(name))
            cls.from_preset(preset)
            assert preset.read == set(cls.keys) - set(cls.tensor_keys), (name, cls.__name__)


def test_the_sensor_builds_its_stages_from_the_preset_and_gives_them_a_new_presets_settings():
    preset = small_kinect(160, 120)
    sensor = DepthSensor(preset)
    assert list(sensor.stages()) == list(STAGES)
    assert all(isinstance(stage, STAGES[name]) for name, stage in sensor.stages().items())
    assert sensor.cleanup.hole_px == preset.cleanup_hole_px and sensor.matcher.function is match
    sensor.preset = preset.replace(cleanup_hole_px=preset.cleanup_hole_px + 3, min_confidence=0.3)
    assert sensor.cleanup.hole_px == preset.cleanup_hole_px + 3 and sensor.matcher.min_confidence == 0.3


def test_a_matcher_handed_to_the_sensor_is_used_and_survives_a_preset_change():
    """A matching function that records its results: the sensor's matches are its, with the sensor's settings, also
    after the preset changes; the frame is the one the stock matcher gives."""
    preset = small_kinect(160, 120)
    calls = []

    def recording(*args, **kwargs):
        calls.append(kwargs["confirmed_match_zncc"])
        return match(*args, **kwargs)

    sensor = DepthSensor(preset, stages={"matcher": dataclasses.replace(BlockMatcher.from_preset(preset),
                                                                         function=recording)})  # fmt: skip
    geometry = plane_geometry(preset.intrinsics, 1.2)
    with torch.no_grad():
        out = sensor(geometry, seed=2)
        stock = DepthSensor(preset)(geometry, seed=2)
        sensor.preset = preset.replace(confirmed_match_zncc=1.0)
        sensor(geometry, seed=2)
    assert calls == [preset.confirmed_match_zncc, 1.0]
    assert torch.equal(out.depth, stock.depth) and torch.equal(out.valid, stock.valid)
    assert float(out.valid.float().mean()) > 0.5  # a plane at 1.2 m: mostly matched
