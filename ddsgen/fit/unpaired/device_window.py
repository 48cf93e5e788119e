"""Where the real frames' device outputs depth: its border window, and whether its depth is registered.

The window (border bands without depth, :mod:`ddsgen.sensor.output_window`) is measured on the real frames,
not searched. How to read it depends on whether the depth is registered to an RGB camera
(:mod:`ddsgen.sensor.registration`): a registered device's bands move with depth (the IR frame's left band
narrows as f b_r / Z grows), and the RGB view's pixels the IR camera does not see are holes right of near
objects. Fitted without the registration, that structure lands on the nearest searched key: on hidden
registered devices the beam fall-off went to its bound (16) in 5 of 5 draws and the paired gap ratio rose from
0.37 to 0.60 (draw 1).

Which model the frames show is measured too: both candidates, the preset's registration with its IR-frame
window measured through the inverse map, and no registration with the frames' own window, render the fit
scenes at the stock values, and the one whose validity by image radius (the distance term that sees border
bands, :func:`~.features.distance_terms`) is closer to the real frames' is used. Not the total distance: its
hole term compares hole sizes, which the fit scenes' content moves as much (measured at 320x240, frames of one
device with and without registration on other scenes than the fit's: radius term 0.0002-0.0011 for the right
reading against 0.012-0.022 for the wrong one, in all four cases; the hole term preferred the registered reading
of unregistered frames, 0.30 against 0.46). A device registered with other geometry than the preset's may be
better served by the plain window; IC-BIN's PrimeSense (its right band moves by about 9.3 px m against the
Kinect's 15.6, and it has no left band) still reads closer as registered (0.0004 against 0.0035).
"""

from __future__ import annotations

from dataclasses import dataclass

from ddsgen.errors import InputError
from ddsgen.fit.unpaired.features import distance_terms, frame_features, pool
from ddsgen.fit.unpaired.search import cast_scenes, render_depths
from ddsgen.realscan.realfolder import RealDepthFrame, round_like
from ddsgen.sensor.output_window import OutputWindow, measure_device_window
from ddsgen.sensor.registration import is_registered

#: The preset keys that switch the registration off.
UNREGISTERED = {"registration_ir_offset_m": 0.0, "registration_shift_px": 0.0}


@dataclass
class WindowModel:
    """One reading of the real frames' device: ``camera`` (the preset at the real frames' size with
    ``window`` and the registration keys of this model), its fit scenes' ``geometries`` and the radius term of
    its stock values' feature distance to the real frames (None when it was the only candidate)."""

    name: str
    camera: object
    window: OutputWindow
    geometries: list
    distance: float | None = None

    @property
    def registration_keys(self) -> dict:
        return {key: getattr(self.camera, key) for key in UNREGISTERED}


def _stock_radius_distance(model: WindowModel, real_features: list, resolution_m: float, seed: int) -> float:
    fb = model.camera.focal_px * model.camera.baseline_m
    depths = render_depths(model.camera, model.geometries, seed)
    simulated = [frame_features(round_like(d, resolution_m), fb) for d in depths]
    return float(distance_terms(pool(simulated), pool(real_features))["radius"])


#: The readings ``--registration`` offers; "auto" measures which one the frames show.
READINGS = ("auto", "registered", "unregistered")


def choose_window_model(stock_camera, real: list[RealDepthFrame], scene_list, sim_frames: int, seed: int,
                        progress: bool = False, reading: str = "auto",
                        real_features: list | None = None) -> tuple[WindowModel, list[WindowModel]]:  # fmt: skip
    """``(chosen, candidates)``: the device reading the fit uses (see the module docstring).

    Args:
        stock_camera: the preset at the real frames' image size (:func:`~.search.camera_for`).
        real: the real frames; scene_list, sim_frames, seed: the fit scenes (:func:`~.search.cast_scenes`).
        reading: one of :data:`READINGS`; "registered" or "unregistered" skips the measurement (the user knows
            what the frames are). "registered" needs a registered preset (InputError otherwise).
        real_features: :func:`.features.frame_features` of ``real`` with the preset's f b, when the caller has
            them already.
    """
    if reading not in READINGS:
        raise ValueError(f"reading must be one of {READINGS}, got {reading!r}")
    if reading == "registered" and not is_registered(stock_camera):
        raise InputError(f"--registration registered: the preset {stock_camera.name} writes unregistered depth "
                         f"(registration_ir_offset_m and registration_shift_px are 0)")  # fmt: skip
    depths = [f.depth for f in real]
    cameras = []
    if reading != "registered":
        cameras.append(("unregistered", stock_camera.replace(**UNREGISTERED)))
    if reading != "unregistered" and is_registered(stock_camera):
        cameras.append(("registered", stock_camera))
    candidates = []
    for name, camera in cameras:
        window = measure_device_window(depths, camera)
        camera = camera.replace(**window.as_keys())
        candidates.append(WindowModel(name, camera, window, cast_scenes(camera, scene_list, sim_frames, seed,
                                                                        progress)))  # fmt: skip
    if len(candidates) == 1:
        return candidates[0], candidates
    if real_features is None:
        fb = stock_camera.focal_px * stock_camera.baseline_m
        real_features = [frame_features(f.depth, fb) for f in real]
    resolution = max(f.resolution_m for f in real)
    for model in candidates:
        model.distance = _stock_radius_distance(model, real_features, resolution, seed)
    return min(candidates, key=lambda m: m.distance), candidates
