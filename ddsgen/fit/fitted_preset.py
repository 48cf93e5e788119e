"""The preset a calibration writes: the user's preset with the values it found, loadable from any folder.

``ddsgen fit``, ``ddsgen fit --unpaired`` and ``ddsgen diagnose --apply`` all write their result this way: the
user's preset (``original``: its camera, its name, its comments' source) replaced by the changed keys, renamed, and
with every file it names (the dot pattern, the post-processing weights) still reachable once the new file lies in
another folder than the original.
"""

from __future__ import annotations

from pathlib import Path

from ddsgen.fit.parameters import preset_values
from ddsgen.preset import PATTERN_DIR, SensorPreset, save_preset


def sensor_changes(sensor, original: SensorPreset) -> dict:
    """The preset keys a fitted :class:`~ddsgen.sensor.depth_sensor.DepthSensor` changes: its physical values
    (:func:`~ddsgen.fit.parameters.preset_values`, focal lengths in ``original``'s pixels) and its effects."""
    return {**preset_values(sensor, original), "effects": [e.to_entry() for e in sensor.effects]}


def _reachable_files(original: SensorPreset) -> dict:
    """{key: absolute path} for the files ``original`` names relative to its own folder (a shipped pattern keeps
    its bare name: it is found from any folder)."""
    files = {}
    if original.pattern:
        pattern = Path(original.resolve_path(original.pattern)).resolve()
        if pattern.parent != Path(PATTERN_DIR).resolve():
            files["pattern"] = str(pattern)
    if original.postprocess:
        files["postprocess"] = str(Path(original.resolve_path(original.postprocess)).resolve())
    return files


def assemble_preset(original: SensorPreset, changes: dict, suffix: str) -> SensorPreset:
    """``original`` with ``changes`` and the name ``<original>_<suffix>``; files it names stay reachable unless
    ``changes`` names others (e.g. newly fitted post-processing weights)."""
    return original.replace(**{**_reachable_files(original), **changes}, name=f"{original.name}_{suffix}")


def write_preset(preset: SensorPreset, path: str | Path, comment: str) -> Path:
    """Write ``preset`` to ``path`` (its folder created), ``comment`` as its header; returns the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    save_preset(preset, path, comment=comment)
    return path
