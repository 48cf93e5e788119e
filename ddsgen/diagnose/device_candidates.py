"""What the device does to its own matches, as diagnosis candidates beside the library effects.

A library effect (:mod:`ddsgen.sensor.effects`) adds something physical to the model: an offset, a lens, a
dropout. A real PrimeSense-family device also *post-processes* its matches, and a model without that
post-processing loses depth that the real frames keep: windows that straddle a depth edge are kept when a
unique match nearby agrees, small holes inside one surface are filled, gaps narrow enough for a mostly lit
window are bridged, and small specks of valid depth are removed. Its signal also fades towards the image corners
(the projector's beam profile, the lens's vignetting), and a model without that keeps depth in the corners that
the device loses. These are keys of the device model
(``presets/kinect_v1.yaml``, each with its measurement), not effects. A preset that has one of them switched
off -- ``kinect_v1_paper`` has all of them off -- gets it as a candidate: the key set to each value of a short
grid (:data:`BEHAVIOURS`, from the ``diagnose`` records of :mod:`ddsgen.parameters`), judged by the same held-out
rule as every effect, and named in the report like one.

Measured on the real LineMOD cat, objects' region (``ddsgen compare``, one key of ``kinect_v1`` at a time on
``kinect_v1_paper``): gap beyond the floor 1.69 mm -> 0.58 (windows across edges kept), 0.76 (the clean-up),
0.15 with every device key of ``kinect_v1`` (docs/validation.md).
"""

from __future__ import annotations

import dataclasses

import torch

from ddsgen.diagnose.acceptance import relative_fall
from ddsgen.diagnose.config import DiagnoseConfig
from ddsgen.diagnose.evaluation import Evaluation, evaluate
from ddsgen.diagnose.plane import replaned
from ddsgen.parameters import behaviours
from ddsgen.sensor.depth_sensor import DepthSensor
from ddsgen.sensor.effects.base import EffectParam


@dataclasses.dataclass(frozen=True)
class DeviceBehaviour:
    """One device behaviour: a preset key, its value when the behaviour is off, and the values searched.

    Carries the attributes the diagnosis reads off a library effect class (``stage``, ``description``,
    ``signature``, ``axis``, ``params``, ``generic``), so that it is judged and reported like one.
    """

    name: str
    key: str
    off: float
    grid: tuple
    unit: str
    stage: str  # "disparity": changes the matches (re-matched, plane re-estimated); "validity": after them
    description: str
    signature: str
    axis: str
    generic: bool = False

    @property
    def params(self) -> dict[str, EffectParam]:
        return {self.key: EffectParam(self.off, min(self.grid), max(self.grid), self.unit, self.description)}


#: The device behaviours, in candidate order: the ``diagnose`` records of the parameter registry
#: (:class:`~ddsgen.parameters.Behaviour`), each with its key's unit.
BEHAVIOURS: dict[str, DeviceBehaviour] = {
    b.name: DeviceBehaviour(b.name, key.name, b.off, b.grid, key.unit, b.acts_on, b.description, b.signature, b.axis)
    for key, b in behaviours()
}


def is_device(name: str) -> bool:
    return name in BEHAVIOURS


def device_candidates(preset) -> list[str]:
    """The behaviours switched off in ``preset`` (the ones it can be missing)."""
    return [b.name for b in BEHAVIOURS.values() if getattr(preset, b.key) == b.off]


def sensor_like(sensor, preset):
    """A new DepthSensor of ``preset`` with ``sensor``'s camera, device, stages (given ``preset``'s settings) and
    stage cache (the candidate shares its model's cached stages), its parameters frozen (candidates are searched,
    not trained)."""
    new = DepthSensor(preset, intrinsics=sensor.intr, device=sensor.device_, stage_cache=sensor.stage_cache,
                      stages=sensor.stages())  # fmt: skip
    # The tensors ``sensor`` shares with it are copied, not rebuilt from the preset: exp then log moves a fitted
    # value by an ulp, and the candidate would no longer be the current model plus one thing (nor share its
    # cached front ends). The focal scale stays 1: the preset's focal length already carries it.
    source = dict(sensor.named_parameters()) | dict(sensor.named_buffers())
    with torch.no_grad():
        for name, t in (*new.named_parameters(), *new.named_buffers()):
            if name != "log_focal_scale" and name in source and source[name].shape == t.shape:
                t.copy_(source[name])
    for p in new.parameters():
        p.requires_grad_(False)
    return new


def with_behaviour(sensor, name: str, values: dict):
    """A new DepthSensor: ``sensor``'s current parameters, its preset's key of behaviour ``name`` set from
    ``values`` ({key: value}; the behaviour's first grid value if absent)."""
    b = BEHAVIOURS[name]
    value = values.get(b.key, b.grid[0])
    value = int(round(value)) if isinstance(b.off, int) else float(value)
    return sensor_like(sensor, sensor.to_preset().replace(**{b.key: value}))


def fit_behaviour(sensor, name: str, frames, config: DiagnoseConfig, base: Evaluation,
                  sims=None) -> tuple[object, dict, float]:  # fmt: skip
    """The behaviour's key searched over its grid on ``frames`` for the largest credited fall of the gap (the
    acceptance criterion, as :func:`~ddsgen.diagnose.candidates.fit_candidate` does for effects; the support
    plane re-estimated under each value when the behaviour changes the matches). ``sims`` is unused (no
    signature guess: the values are a short discrete grid). Returns (sensor, {key: value}, -credited fall)."""
    b = BEHAVIOURS[name]
    best = None
    for value in b.grid:
        candidate = with_behaviour(sensor, name, {b.key: value})
        trial = replaned(candidate, frames, config.seed) if b.stage != "validity" else frames
        with torch.no_grad():
            score = -relative_fall(base, evaluate(candidate, trial, config.seed))
        if best is None or score < best[2]:
            best = (candidate, {b.key: float(value)}, score)
    return best
