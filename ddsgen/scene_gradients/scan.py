"""Pose refinement of a scan frame (real or rendered): its annotated objects and its support plane."""

from __future__ import annotations

import dataclasses

import numpy as np

from ddsgen.errors import InputError
from ddsgen.preset import SensorPreset
from ddsgen.realscan.simulate import frame_scene, prepare_frame
from ddsgen.scene_gradients.poses import pose_difference
from ddsgen.scene_gradients.refine import RefineResult, RefineSettings, refine_poses
from ddsgen.scene_gradients.scene import RefinableScene
from ddsgen.scene_gradients.static_scene import refine_static_scene
from ddsgen.sensor.depth_sensor import DepthSensor


@dataclasses.dataclass
class FrameRefinement:
    """The refinement of one scan frame.

    name: the frame's name; crop: (x0, y0, width, height) of the refined window in the frame.
    object_ids: the objects' instance ids (ScanObject.id), in the order of ``result``'s first rows.
    result: the :class:`RefineResult` (poses: objects, then the support plane if one was fitted).
    real_depth: (h, w) float32 real depth of the window (m, 0 invalid).
    plane_fitted: whether a support plane was fitted (and refined).
    object_labels: the objects' names in the dataset's own terms (:func:`object_label`), in the same order.
    """

    name: str
    crop: tuple[int, int, int, int]
    object_ids: list
    result: RefineResult
    real_depth: np.ndarray
    plane_fitted: bool
    object_labels: list = dataclasses.field(default_factory=list)
    dataset_visibility: list = dataclasses.field(default_factory=list)  # per object: the dataset's visible fraction or None

    def object_changes(self) -> list[dict]:
        """Per object: id, label, the pose change (deg, mm) from the initial to the refined pose, whether the
        refined pose was kept (``kept``, ``decision``: why, with the held-out gaps) and, where assessed, each
        direction's standard deviation and whether the data determine it (``directions``, ``undetermined``: those
        that stayed at the start)."""
        written = self.refined_poses()
        changes = object_changes(self.object_ids, self.result.initial, [written[i] for i in self.object_ids])
        decisions = self.result.decisions
        for k, change in enumerate(changes):
            change["label"] = self.object_labels[k] if k < len(self.object_labels) else f"instance {change['id']}"
            decision = decisions[k] if k < len(decisions) else None
            if decision is not None:
                change["kept"], change["decision"] = decision.kept, decision.reason()
                change["heldout_start_mm"] = round(decision.heldout_start_mm, 4)
                change["heldout_refined_mm"] = round(decision.heldout_refined_mm, 4)
            r = self.result
            if r.kept_start and (decision is None or decision.kept):  # (an object's own rejection says more)
                if r.heldout_gap_before_mm == r.heldout_gap_before_mm:
                    why = (f"held-out gap {r.heldout_gap_before_mm:.2f} mm at the start, "
                           f"{r.heldout_gap_refined_mm:.2f} mm at the refined poses")
                else:
                    why = f"gap {r.gap_before_mm:.2f} mm at the start, {r.gap_optimised_mm:.2f} mm refined"
                change["kept"], change["decision"] = False, f"start kept: the frame's gap is not lower ({why})"
            elif decision is None:
                change["kept"], change["decision"] = True, "refined pose kept (no acceptance test)"
            estimated = self.result.visible_fraction
            if k < len(estimated):
                change["visible_fraction_estimated"] = round(estimated[k], 4)
            if k < len(self.dataset_visibility) and self.dataset_visibility[k] is not None:
                change["visible_fraction_dataset"] = round(float(self.dataset_visibility[k]), 4)
            identified = self.result.identifiability
            if k < len(identified):
                change["directions"] = identified[k].as_dict()
                change["undetermined"] = identified[k].undetermined_axes()
        return changes

    def refined_poses(self) -> dict:
        """{object id: (4, 4) refined ``cam_T_obj``}: the start pose where the refined one was not kept."""
        r = self.result
        kept = [not r.kept_start and (k >= len(r.decisions) or r.decisions[k] is None or r.decisions[k].kept)
                for k in range(len(self.object_ids))]  # fmt: skip
        return {obj_id: (r.refined if kept[k] else r.initial)[k] for k, obj_id in enumerate(self.object_ids)}


def object_changes(object_ids, initial, refined) -> list[dict]:
    """Per object: {id, rotation_deg, translation_mm}, the change from its ``initial`` to its ``refined`` (4, 4)
    pose (both in object order; extra rows, e.g. a support plane's, are ignored)."""
    out = []
    for k, obj_id in enumerate(object_ids):
        deg, mm = pose_difference(initial[k], refined[k])
        out.append({"id": int(obj_id), "rotation_deg": round(deg, 4), "translation_mm": round(mm, 4)})
    return out


def object_label(obj, frame_objects=()) -> str:
    """An object's name in its dataset's terms: ``obj_id 6`` (BOP, or a manifest that gives obj_id), else its class;
    ``#<instance>`` is added when another object of ``frame_objects`` has the same name."""
    def name(o):
        return f"obj_id {o.obj_id}" if o.obj_id is not None else str(o.class_name)

    label = name(obj)
    if sum(name(o) == label for o in frame_objects) > 1:
        label += f" #{obj.id}"
    return label


def refine_scan_frame(preset: SensorPreset, frame, index: int = 0, settings: RefineSettings | None = None, *,
                      support_plane: bool = True, crop_margin_px: int = 32, progress: bool = False,
                      sensor=None) -> FrameRefinement:  # fmt: skip
    """Refine every annotated object's pose (and the fitted support plane) of one scan frame.

    Args:
        preset: the sensor preset with the frame's camera (:func:`ddsgen.realscan.inputs.adopt_camera`).
        frame: a :class:`~ddsgen.io.scan_frame.ScanFrame` (from ``read_scan_folder``).
        index: the frame's position in its folder (seeds the support-plane RANSAC).
        settings: :class:`RefineSettings`.
        support_plane: fit a RANSAC plane to the real depth outside the objects and refine it too.
        crop_margin_px: the window simulated is the objects' box plus this margin (exact: a crop
            of a pinhole image is a pinhole image); objects may move a little within it.
        sensor: a :class:`~ddsgen.sensor.depth_sensor.DepthSensor` to use (e.g. one being fitted; its
            camera is set to the window's for the call); default: a new one from ``preset``.
    """
    s = settings or RefineSettings()
    sensor = sensor if sensor is not None else DepthSensor(preset)  # refine_poses gives it the window's camera
    view = _ScanView(preset, frame, index, s, support_plane, crop_margin_px, float(sensor.baseline.detach()))
    result = refine_poses(sensor, view.refinable, view.real, s, progress=progress)
    return view.refinement(result)


def refine_static_scan(preset: SensorPreset, frames: list, settings: RefineSettings | None = None, *,
                       support_plane: bool = True, crop_margin_px: int = 32, progress: bool = False,
                       first_index: int = 0, max_views: int = 8, sensor=None) -> tuple[list[FrameRefinement], dict]:  # fmt: skip
    """Refine the frames of one static scene together: each object's correction is shared by every frame.

    Objects are matched across frames by their position in each frame's list and must have the same
    class there (BOP: the order of scene_gt.json, the same in every frame of a static scene); each
    frame keeps its own support plane. At most ``max_views`` frames, evenly spaced over the scene, are
    simulated (a BOP scene may hold a thousand; the correction is one per object); the correction they
    find is applied to the others too. Arguments as :func:`refine_scan_frame`; ``first_index`` is the
    first frame's position in its folder. Group a folder's frames into static scenes with
    :func:`static_scenes`.

    Returns:
        (one :class:`FrameRefinement` per simulated frame, {frame name: {object id: (4, 4) refined
        ``cam_T_obj``}} for every frame of the scene).
    """
    classes = [o.class_name for o in frames[0].objects]
    for frame in frames[1:]:
        if [o.class_name for o in frame.objects] != classes:
            raise InputError(f"{frame.source_depth_path}: frame {frame.name} lists objects "
                             f"{[o.class_name for o in frame.objects]}, frame {frames[0].name} {classes}: "
                             "a static scene needs the same objects in the same order in every frame")  # fmt: skip
    if max_views < 1:
        raise ValueError(f"max_views must be >= 1, got {max_views}")
    s = settings or RefineSettings()
    sensor = sensor if sensor is not None else DepthSensor(preset)  # given each view's window in turn
    baseline = float(sensor.baseline.detach())
    chosen = sorted(set(np.linspace(0, len(frames) - 1, min(max_views, len(frames))).round().astype(int).tolist()))
    views = [_ScanView(preset, frames[k], first_index + k, s, support_plane, crop_margin_px, baseline) for k in chosen]
    results = refine_static_scene(sensor, [v.refinable for v in views], [v.real for v in views], s, progress)
    shared = views[0].refinable.poses.shared
    poses = {}
    for frame in frames:  # the shared correction applied to each frame's own annotated poses
        scene = RefinableScene(frame_scene(frame), preset.intrinsics, baseline, preset.shadow_bias_m)
        scene.poses.share_objects(shared)
        poses[frame.name] = {o.id: T for o, T in zip(frame.objects, scene.object_poses())}
    return [v.refinement(r) for v, r in zip(views, results)], poses


def static_scenes(frames: list) -> list[tuple[int, list]]:
    """[(index of the scene's first frame, its frames)]: the static scenes of a folder's frames.

    BOP frames (and frames without camera poses) belong together by their scene folder; ddsgen frames
    while they hold the same classes at the same world poses (within 0.1 mm and 1e-4: a scene-list
    block of ``render``).
    """
    groups: list[tuple[int, list]] = []
    for index, frame in enumerate(frames):
        previous = groups[-1][1][0] if groups else None
        if previous is not None and _same_scene(previous, frame):
            groups[-1][1].append(frame)
        else:
            groups.append((index, [frame]))
    return groups


def _same_scene(a, b) -> bool:
    if a.layout == "bop" or a.world_T_cam is None or b.world_T_cam is None:  # BOP: the scene folder is the scene
        return a.name.split("/")[0] == b.name.split("/")[0]
    if [o.class_name for o in a.objects] != [o.class_name for o in b.objects]:
        return False
    for oa, ob in zip(a.objects, b.objects):
        wa, wb = a.world_T_cam @ oa.cam_T_obj, b.world_T_cam @ ob.cam_T_obj
        if np.abs(wa[:3, 3] - wb[:3, 3]).max() > 1e-4 or np.abs(wa[:3, :3] - wb[:3, :3]).max() > 1e-4:
            return False
    return True


class _ScanView:
    """One scan frame made ready to refine: its window, scene at the annotated poses, real depth."""

    def __init__(self, preset, frame, index, s, support_plane, crop_margin_px, baseline_m):
        prepared = prepare_frame(preset, frame, index, support_plane=support_plane, crop=True,
                                 crop_margin_px=crop_margin_px, seed=s.seed)  # fmt: skip
        if not bool((prepared.instance > 0).any()):
            raise InputError(f"{frame.source_depth_path}: frame {frame.name}: no annotated object is in view at its "
                             "pose (nothing to refine; check the poses, mesh units and intrinsics)")  # fmt: skip
        self.frame, self.crop, self.plane_fitted = frame, tuple(int(v) for v in prepared.crop), prepared.plane is not None
        scene = frame_scene(frame, plane=prepared.plane)
        self.refinable = RefinableScene(scene, prepared.intrinsics, baseline_m, preset.shadow_bias_m,
                                        ir_margin_px=preset.ir_margin_right_px)  # fmt: skip
        self.real = prepared.real_depth.clone()

    def refinement(self, result: RefineResult) -> FrameRefinement:
        objects = self.frame.objects
        return FrameRefinement(name=self.frame.name, crop=self.crop, object_ids=[o.id for o in objects],
                               result=result, real_depth=self.real.numpy(), plane_fitted=self.plane_fitted,
                               object_labels=[object_label(o, objects) for o in objects],
                               dataset_visibility=[o.visible_fraction for o in objects])  # fmt: skip
