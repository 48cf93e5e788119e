"""Pose refinement of a scan frame (real or rendered): its annotated objects and its support plane."""

from __future__ import annotations

import dataclasses

import numpy as np

from ddsgen.preset import SensorPreset
from ddsgen.scene_gradients.refine import RefineResult, RefineSettings, refine_poses
from ddsgen.scene_gradients.scene import RefinableScene


@dataclasses.dataclass
class FrameRefinement:
    """The refinement of one scan frame.

    name: the frame's name; crop: (x0, y0, width, height) of the refined window in the frame.
    object_ids: the objects' instance ids (ScanObject.id), in the order of ``result``'s first rows.
    result: the :class:`RefineResult` (poses: objects, then the support plane if one was fitted).
    real_depth: (h, w) float32 real depth of the window (m, 0 invalid).
    plane_fitted: whether a support plane was fitted (and refined).
    """

    name: str
    crop: tuple[int, int, int, int]
    object_ids: list
    result: RefineResult
    real_depth: np.ndarray
    plane_fitted: bool

    def object_changes(self) -> list[dict]:
        """Per object: id and the pose change (deg, mm) from the initial to the refined pose."""
        from ddsgen.scene_gradients.poses import pose_difference

        out = []
        for k, obj_id in enumerate(self.object_ids):
            deg, mm = pose_difference(self.result.initial[k], self.result.refined[k])
            out.append({"id": int(obj_id), "rotation_deg": round(deg, 4), "translation_mm": round(mm, 4)})
        return out


def refine_scan_frame(preset: SensorPreset, frame, index: int = 0, settings: RefineSettings | None = None, *,
                      support_plane: bool = True, crop_margin_px: int = 32, progress: bool = False,
                      sensor=None) -> FrameRefinement:  # fmt: skip
    """Refine every annotated object's pose (and the fitted support plane) of one scan frame.

    Args:
        preset: the sensor preset with the frame's camera (:func:`ddsgen.fit.inputs.adopt_camera`).
        frame: a :class:`~ddsgen.io.scanfolder.ScanFrame` (from ``read_scan_folder``).
        index: the frame's position in its folder (seeds the support-plane RANSAC).
        settings: :class:`RefineSettings`.
        support_plane: fit a RANSAC plane to the real depth outside the objects and refine it too.
        crop_margin_px: the window simulated is the objects' box plus this margin (exact: a crop
            of a pinhole image is a pinhole image); objects may move a little within it.
        sensor: a :class:`~ddsgen.sensor.depth_sensor.DepthSensor` to use (e.g. one being fitted; its
            camera is set to the window's for the call); default: a new one from ``preset``.
    """
    from ddsgen.fit.simulate import frame_camera, frame_scene, prepare_frame
    from ddsgen.sensor.depth_sensor import DepthSensor

    s = settings or RefineSettings()
    prepared = prepare_frame(preset, frame, index, support_plane=support_plane, crop=True,
                             crop_margin_px=crop_margin_px, seed=s.seed)  # fmt: skip
    x0, y0, width, height = prepared.crop
    window = prepared.intrinsics
    scene = frame_scene(frame, plane=prepared.plane)
    if sensor is None:
        sensor = DepthSensor(preset, intrinsics=window)
    baseline = float(sensor.baseline.detach())
    refinable = RefinableScene(scene, window, baseline, preset.shadow_bias_m, ir_margin_px=preset.ir_margin_right_px)
    real = prepared.real_depth.clone()
    with frame_camera(sensor, window):
        result = refine_poses(sensor, refinable, real, s, progress=progress)
    return FrameRefinement(name=frame.name, crop=(int(x0), int(y0), int(width), int(height)), object_ids=[o.id for o in frame.objects],
                           result=result, real_depth=real.numpy(), plane_fitted=prepared.plane is not None)  # fmt: skip
