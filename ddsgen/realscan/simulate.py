"""Simulate the views of a folder of scans: meshes at their ground-truth poses, ray cast once.

For each :class:`~ddsgen.io.scan_frame.ScanFrame` (real or rendered), :func:`prepare_frames`
builds a :class:`FrameData`:

1. a :class:`~ddsgen.scene.sampling.FrameScene` in the camera frame (``world_T_cam`` = I)
   holding the listed meshes at ``cam_T_obj`` (scaled to metres by ``mesh_scale``);
2. optionally a **support plane** fitted by RANSAC to the real depth outside the objects'
   silhouettes (the table the objects stand on, :mod:`ddsgen.realscan.support_plane`), added as a
   large background quad, so that the table and the objects' projector shadows on it are
   modelled too;
3. one ray cast (embreex) with the sensor's baseline and shadow bias -> the constant
   :class:`~ddsgen.sensor.geometry.SensorGeometry` the differentiable sensor consumes
   (ray casting is not differentiable: it is done once per frame and cached in FrameData);
4. optionally a **crop** to the objects' bounding box plus a margin (a sub-window of a
   pinhole image is a pinhole image with a shifted principal point, so the crop is
   simulated exactly; it only makes fitting cheaper);
5. the **comparison region** (:mod:`ddsgen.realscan.region`): pixels where the modelled
   geometry is visible (clean depth hit) and plausible: the real depth agrees with the clean
   depth within ``plausible_px`` px of disparity f*b/z (things that are not modelled -- hands,
   other objects, a wall -- are far off and left out), or it is invalid where the modelled
   scene can explain that (on a posed object or on the support plane's real extent, and not
   in the projector shadow of something unmodelled). A border of ``block // 2 + 1`` px is left
   out of crops (the matcher cannot match there, the real sensor could).

The sensor's intrinsics are set per frame by :func:`simulate` (frames may have different
cameras; the sensor's parameters are shared).
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import math

import numpy as np
import torch

from ddsgen.errors import InputError
from ddsgen.preset import Intrinsics, SensorPreset
from ddsgen.raycast import cast
from ddsgen.realscan.losses import resolved_depth_m
from ddsgen.realscan.region import comparison_region
from ddsgen.realscan.support_plane import Plane, fit_support_plane, plane_pose
from ddsgen.scene import shapes
from ddsgen.scene.sampling import FrameScene, PlacedObject, sample_frame
from ddsgen.scene.scenelist import load_mesh, load_scene_list
from ddsgen.sensor.ir_lens import IRLens
from ddsgen.sensor.output_window import OutputWindow
from ddsgen.sensor.registration import output_projector_x_m
from ddsgen.sensor.sensor_cast import sensor_geometry

#: Default IR reflectance of modelled surfaces (the scene-list default for objects). eta_c and
#: albedo only appear as their product in the IR image, so a fitted eta_c is relative to this.
DEFAULT_ALBEDO = 0.6
#: Plausibility threshold: |f b / z_real - f b / z_clean| <= this (px of disparity).
DEFAULT_PLAUSIBLE_PX = 2.0
#: Noise stream of simulated frames: rng([seed, frame_index, SIM_STREAM]) -- never the
#: stream ``render`` uses (1), so simulating a rendered folder does not reuse its noise.
SIM_STREAM = 7919


@dataclasses.dataclass
class FrameData:
    """One scan frame prepared for simulation and comparison (all tensors (H, W), CPU).

    name: the scan frame's name; index: position in the folder (seeds the frame's IR noise).
    intrinsics: camera of the (possibly cropped) image; crop: (x0, y0, width, height) of the
        image in the original frame.
    geometry: ray-cast geometry (constant); instance: int32 object ids (0 = support plane / none).
    real_depth: float32 m (0 = invalid); real_valid: bool.
    region: bool, where the comparison counts (modelled, visible, plausible);
    object_region: region & instance > 0.
    incidence_deg: angle between the normal and the ray to the camera; radius: distance from
        the principal point over the half-diagonal of the original image (0..~1).
    plane: the fitted support plane, or None. pose_error_mm: median |real - clean| on the
        objects' pixels where the real depth is valid (a check of the ground-truth poses).
    full_intrinsics: the camera of the uncropped frame.
    clean_depth: float32 m, the image's ray-cast depth (0 = no hit); hit: bool. For a device registered to an
        RGB camera the geometry is the IR camera's view, these are the image's; default: the geometry's.
    resolved_depth_m: the depth values of pixels beyond this clean depth do not count, their validity does
        (:func:`ddsgen.realscan.losses.resolved_depth_m`; inf: all count).
    """

    name: str
    index: int
    intrinsics: Intrinsics
    crop: tuple[int, int, int, int]
    geometry: object  # SensorGeometry
    instance: torch.Tensor
    real_depth: torch.Tensor
    real_valid: torch.Tensor
    region: torch.Tensor
    object_region: torch.Tensor
    incidence_deg: torch.Tensor
    radius: torch.Tensor
    plane: Plane | None = None
    pose_error_mm: float = float("nan")
    full_intrinsics: Intrinsics | None = None
    clean_depth: torch.Tensor | None = None
    hit: torch.Tensor | None = None
    resolved_depth_m: float = math.inf

    def __post_init__(self):
        if self.clean_depth is None:
            self.clean_depth = self.geometry.clean_depth
        if self.hit is None:
            self.hit = self.geometry.hit

    @property
    def shape(self) -> tuple[int, int]:
        return tuple(self.real_depth.shape)

    def noise_seed(self, seed: int = 0) -> list[int]:
        return [int(seed), int(self.index), SIM_STREAM]


# ------------------------------------------------------------------------------------------ scene


def _load_object_mesh(obj):
    return load_mesh(obj.mesh_path, obj.mesh_scale)  # a file's errors name it (passing it as source named it twice)


@functools.lru_cache(maxsize=4)
def _scene_list(path: str | None):
    """The scene list a render names (its meshes looked up as ``render`` does), None when it no longer loads."""
    try:
        return load_scene_list(path)
    except InputError:  # e.g. meshes found through a --models folder at render time and not now
        return None


def rendered_background(frame) -> tuple[list[PlacedObject], dict[int, float]] | None:
    """A ddsgen render's frame as it was rendered, beside its listed objects: the background (ground, table, floor,
    walls, distractors) in the camera frame, and the objects' albedos by id. None for any other frame, and for a
    render whose scene list cannot be made again (:class:`~ddsgen.io.scan_frame.RenderedScene`)."""
    rendered = getattr(frame, "rendered", None)
    scene_list = None if rendered is None or rendered.missing else _scene_list(rendered.scenes_path)
    if scene_list is None or frame.world_T_cam is None:
        return None
    scene = sample_frame(scene_list, frame.frame, rendered.seed)
    if not np.allclose(scene.world_T_cam, frame.world_T_cam, rtol=0.0, atol=1e-9):  # not the scene of this frame
        return None
    cam_T_world = np.linalg.inv(scene.world_T_cam)
    background = [dataclasses.replace(b, world_T_obj=cam_T_world @ b.world_T_obj) for b in scene.background]
    return background, {o.id: o.albedo for o in scene.objects}


def frame_scene(frame, albedo: float = DEFAULT_ALBEDO, plane: Plane | None = None, plane_size_m: float = 20.0):
    """The FrameScene of a scan frame (camera frame = world frame): its objects at their poses, and behind them the
    background it was rendered with (a ddsgen render whose scene list is at hand: :func:`rendered_background`) or
    else the support ``plane`` when given. ``albedo``: the IR reflectance of surfaces the frame does not state."""
    objects, background = [], []
    rendered = rendered_background(frame)
    albedos = rendered[1] if rendered is not None else {}
    for obj in frame.objects:
        mesh = _load_object_mesh(obj)
        objects.append(PlacedObject(id=int(obj.id), class_name=obj.class_name, mesh_ref=obj.mesh_path, mesh=mesh,
                                    world_T_obj=np.asarray(obj.cam_T_obj, dtype=np.float64),
                                    albedo=float(albedos.get(int(obj.id), albedo)), mesh_scale=float(obj.mesh_scale)))  # fmt: skip
    if rendered is not None:
        background = rendered[0]
    elif plane is not None:
        background.append(PlacedObject(0, "support_plane", "plane:fitted", shapes.plane_mesh(plane_size_m, plane_size_m),
                                       plane_pose(plane), float(albedo)))  # fmt: skip
    return FrameScene(objects=objects, background=background, world_T_cam=np.eye(4), frame_index=int(frame.frame),
                      seed=0, scene_name=frame.name)  # fmt: skip


# ------------------------------------------------------------------------------------------ frames


def _crop_box(instance: np.ndarray, margin: int, min_size: int) -> tuple[int, int, int, int]:
    h, w = instance.shape
    rows, cols = np.nonzero(instance > 0)
    if len(rows) == 0:
        return 0, 0, w, h
    x0, x1 = int(cols.min()) - margin, int(cols.max()) + margin + 1
    y0, y1 = int(rows.min()) - margin, int(rows.max()) + margin + 1
    # Grow to the minimum size around the centre, then clip to the image (never larger than it).
    def grow(a, b, limit):
        size = min(max(b - a, min_size), limit)
        centre = (a + b) // 2
        a = max(0, min(centre - size // 2, limit - size))
        return a, a + size

    x0, x1 = grow(x0, x1, w)
    y0, y1 = grow(y0, y1, h)
    return x0, y0, x1 - x0, y1 - y0


def crop_intrinsics(intrinsics: Intrinsics, box: tuple[int, int, int, int]) -> Intrinsics:
    x0, y0, w, h = box
    return Intrinsics(int(w), int(h), intrinsics.fx, intrinsics.fy, intrinsics.cx - x0, intrinsics.cy - y0)


def prepare_frame(preset: SensorPreset, frame, index: int, *, support_plane: bool = True,
                  albedo: float = DEFAULT_ALBEDO, plausible_px: float = DEFAULT_PLAUSIBLE_PX,
                  crop: bool = False, crop_margin_px: int = 24, seed: int = 0, plane_depth=None) -> FrameData:  # fmt: skip
    """One :class:`FrameData` (see :func:`prepare_frames`)."""
    intr = frame.intrinsics
    real = np.asarray(frame.depth, dtype=np.float32)
    real = np.where(np.isfinite(real) & (real > 0), real, 0.0).astype(np.float32)
    if not real.any():  # nothing measured: every comparison, fit or refinement against it would be noise
        raise InputError(f"{frame.source_depth_path}: depth: no valid pixel (all zero) in frame {frame.name}")
    fb = intr.fx * preset.baseline_m
    scene = frame_scene(frame, albedo)
    hits = cast(scene, intr, output_projector_x_m(preset), preset.shadow_bias_m)
    plane = None
    whole_scene = rendered_background(frame) is not None  # a render whose background is modelled: no plane to fit
    if support_plane and not whole_scene:
        # Exclude the objects' silhouettes grown by a few px (their rims are mixed pixels).
        import cv2

        exclude = cv2.dilate((hits.instance > 0).astype(np.uint8), np.ones((7, 7), np.uint8)) > 0
        plane_input = real if plane_depth is None else plane_depth(real, intr)
        resting = hits.points[hits.instance > 0]
        plane = fit_support_plane(plane_input, intr, exclude, fb, np.random.default_rng([seed, index, 5]),
                                  resting=resting)  # fmt: skip
        if plane is not None:
            scene = frame_scene(frame, albedo, plane)
            hits = cast(scene, intr, output_projector_x_m(preset), preset.shadow_bias_m)

    instance = hits.instance.astype(np.int32)
    object_px = instance > 0
    pose_error = float("nan")
    both = object_px & (real > 0)
    if both.any():
        pose_error = float(np.median(np.abs(real[both] - hits.depth[both])) * 1000.0)

    # Comparison region, on the whole frame (the support plane's real extent is a whole-frame notion).
    region = comparison_region(real, hits.depth, hits.hit, object_px, hits.shadow, fb, plausible_px,
                               preset.block_size_px, plane is not None, OutputWindow.of(preset))  # fmt: skip

    box = _crop_box(instance, crop_margin_px, min_size=max(4 * preset.block_size_px, 48)) if crop else (
        0, 0, intr.width, intr.height)  # fmt: skip
    x0, y0, w, h = box
    # The sensor's geometry: the whole frame (the IR margin beyond its right edge; a registered device's IR
    # view), then the crop's window.
    geometry = sensor_geometry(scene, intr, preset, hits)
    if crop:
        geometry = geometry.cropped(x0, y0, w, h)
    sl = (slice(y0, y0 + h), slice(x0, x0 + w))
    for name in ("depth", "points", "normals", "instance", "hit", "shadow", "albedo"):
        setattr(hits, name, np.ascontiguousarray(getattr(hits, name)[sl]))
    real = np.ascontiguousarray(real[sl])
    instance = instance[sl]
    region = np.ascontiguousarray(region[sl])
    cintr = crop_intrinsics(intr, box) if crop else intr
    if crop:  # the pixels the crop's own IR image can match (a border, bent by an IR lens)
        region &= IRLens.from_preset(preset).usable(cintr, geometry.registration_shift_px, preset.block_size_px).numpy()

    p = hits.points
    with np.errstate(divide="ignore", invalid="ignore"):
        ray = -p / np.maximum(np.linalg.norm(p, axis=-1, keepdims=True), 1e-9)
        cos = np.clip((ray * hits.normals).sum(-1), -1.0, 1.0)
    incidence = np.where(hits.hit, np.degrees(np.arccos(np.abs(cos))), 90.0).astype(np.float32)
    u = np.arange(x0, x0 + w) - intr.cx
    v = np.arange(y0, y0 + h) - intr.cy
    half_diag = 0.5 * math.hypot(intr.width, intr.height)
    radius = (np.hypot(u[None, :], v[:, None]) / half_diag).astype(np.float32)

    t = torch.from_numpy
    return FrameData(
        name=frame.name, index=int(index), intrinsics=cintr, crop=box, geometry=geometry,
        instance=t(instance), real_depth=t(real), real_valid=t(real > 0), region=t(region),
        object_region=t(region & (instance > 0)), incidence_deg=t(incidence), radius=t(radius), plane=plane,
        pose_error_mm=pose_error, full_intrinsics=intr, clean_depth=t(hits.depth), hit=t(hits.hit),
        resolved_depth_m=resolved_depth_m(fb, preset.subpixel_step_px),
    )  # fmt: skip


def prepare_frames(preset: SensorPreset, scan_frames, *, support_plane: bool = True,
                   albedo: float = DEFAULT_ALBEDO, plausible_px: float = DEFAULT_PLAUSIBLE_PX,
                   crop: bool = False, crop_margin_px: int = 24, seed: int = 0, progress: bool = False,
                   plane_depth=None) -> list[FrameData]:  # fmt: skip
    """Ray-cast every scan frame once: the constant inputs of simulation, comparison and fitting.

    Args:
        preset: the sensor preset (its baseline and shadow bias are used for the ray cast and
            its baseline for the plausibility test in disparity).
        scan_frames: list of :class:`~ddsgen.io.scan_frame.ScanFrame` (from ``read_scan_folder``).
        support_plane: add a RANSAC plane fitted to the real depth outside the objects.
        albedo: IR reflectance given to every modelled surface.
        plausible_px: plausibility threshold (px of disparity) of the comparison region.
        crop: crop each frame to its objects' bounding box plus ``crop_margin_px``.
        seed: seeds RANSAC (and, via :meth:`FrameData.noise_seed`, the simulated IR noise).
        plane_depth: optional ``(real depth (H, W) m, intrinsics) -> depth`` the support plane is fitted
            to instead of the raw real depth (:mod:`ddsgen.realscan.plane_depth`: the sensor's errors undone).
        progress: show a progress bar.

    Returns:
        One :class:`FrameData` per scan frame, in order.

    Raises:
        InputError: a frame has no objects, or none of its modelled geometry is in view.
    """
    from tqdm import tqdm

    if not scan_frames:
        raise InputError("scan folder: no frames")
    out = []
    for i, frame in enumerate(tqdm(scan_frames, desc="ray cast", unit="frame", disable=not progress, leave=False)):
        if not frame.objects:
            raise InputError(f"{frame.source_depth_path}: frame {frame.name} lists no objects (nothing to simulate)")
        data = prepare_frame(preset, frame, i, support_plane=support_plane, albedo=albedo, plausible_px=plausible_px,
                             crop=crop, crop_margin_px=crop_margin_px, seed=seed, plane_depth=plane_depth)  # fmt: skip
        if not bool(data.region.any()):
            raise InputError(f"{frame.source_depth_path}: frame {frame.name}: no modelled object is visible and "
                             f"plausible (check the poses, mesh units and intrinsics)")  # fmt: skip
        frame.release()
        out.append(data)
    return out


# ------------------------------------------------------------------------------------------ simulate


@contextlib.contextmanager
def frame_camera(sensor, intrinsics: Intrinsics):
    """Temporarily give ``sensor`` the camera of a frame (the parameters stay shared)."""
    old = sensor.intr
    sensor.intr = intrinsics
    try:
        yield sensor
    finally:
        sensor.intr = old


@contextlib.contextmanager
def sensor_unit(sensor, unit: int):
    """Temporarily make ``sensor`` another unit of its model (``DepthSensor.unit``: its own speckle and dots)."""
    old = sensor.unit
    sensor.unit = int(unit)
    try:
        yield sensor
    finally:
        sensor.unit = old


def simulate(sensor, frame: FrameData, seed: int = 0):
    """Run the differentiable sensor on a prepared frame -> SensorOutput (gradients if enabled).

    The IR noise of frame ``i`` is drawn from ``rng([seed, i, SIM_STREAM])``: the same draws
    at every call (common random numbers across fitting steps), different draws for another seed.
    With ``speckle_fixed_to_scene`` the speckle is seeded by the frame's geometry, as ``render``
    draws it (a static scene shows the same speckle whatever the seed); the read noise follows the seed.
    """
    with frame_camera(sensor, frame.intrinsics):
        noise = sensor.draw_noise(frame.noise_seed(seed), frame.geometry)
        return sensor(frame.geometry, noise=noise)


#: Seed offset and unit of the (first) twin that measures the noise floor.
TWIN_SEED_OFFSET, TWIN_UNIT = 1000, 1
#: Unit draws the floor of a comparison averages at least, spread over its frames (:func:`twin_draws`). One
#: unit's draw on one frame scatters by tens of percent: on the LineMOD cat's object region the floor is
#: 0.40-1.50 mm against units 1-8 (mean 0.68); over 9 frames units 1-4 agree within 3 % (docs/validation.md).
FLOOR_DRAWS = 4


def twin_draws(frame_count: int, draws: int = FLOOR_DRAWS) -> int:
    """Twins per frame for a floor over ``frame_count`` frames: ceil(draws / frames), at least 1.

    1 frame: 4 twins; 2 frames: 2 each; 3: 2 each; 4 or more: 1 each. Costs at most ``draws - 1``
    simulations more than one twin per frame.
    """
    return max(1, -(-int(draws) // max(int(frame_count), 1)))


def simulate_twin(sensor, frame: FrameData, seed: int = 0, draw: int = 0):
    """The frame as another unit of the same sensor model takes it: what a real scan is to a perfect model.

    Same parameters as ``sensor``; its own read noise (seed ``seed + TWIN_SEED_OFFSET * (draw + 1)``) and
    its own scene-fixed patterns (laser speckle, dot sub-pixel positions: ``DepthSensor.unit`` =
    ``TWIN_UNIT + draw``). A real scan was taken by a unit whose speckle and dots the model cannot know, so
    the gap between ``simulate(sensor, frame, seed)`` and this twin is the noise floor a perfect model scores
    against real data. (A twin that shared the speckle with the simulation scored far lower: 4.4 against
    8.8 mm on the blind diagnose scans, docs/validation.md.) ``draw`` 0, 1, ...: further units, for a
    floor averaged over several (:func:`twin_draws`).
    """
    with sensor_unit(sensor, TWIN_UNIT + int(draw)):
        return simulate(sensor, frame, seed + TWIN_SEED_OFFSET * (int(draw) + 1))
