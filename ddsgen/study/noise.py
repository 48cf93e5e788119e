"""The noise study of the paper (Planche & Singh 2021, Fig. S4): a flat surface at distance z, tilted by alpha.

Set-up (camera frame = world frame, OpenCV axes): a large flat rectangle through the point (0, 0, z) on the
optical axis, rotated by alpha about the camera's vertical (y) axis, so its right side recedes
(Z = z + X tan alpha) and the incidence angle at the image centre is alpha. Each (z, alpha) is ray cast
once (:func:`ddsgen.raycast.cast`, Embree) and its geometry reused for K frames that differ only in the
sensor's noise seed; every frame goes through the full :class:`~ddsgen.sensor.depth_sensor.DepthSensor`
(IR image, block matching, depth).

Measured per (z, alpha), over the valid pixels of a region of interest (the central half of the rows and
columns, restricted to where the true depth is within +-10 % of z, so tilted planes are measured near z):

* ``bias_m``: mean of (depth - true depth);
* ``rms_m``: root mean square of (depth - true depth);
* ``std_m``: axial noise as Nguyen, Izadi & Lovell (2012) measure it: per frame, fit a plane to the measured
  depths (1/Z is linear in the pixel coordinates for a plane, so the fit is exact; fitted on the inliers
  within max(5 robust sigma, 3 quantisation steps)), then the root mean square of the residuals of *all*
  valid pixels, pooled over the K frames;
* ``valid_fraction``: valid pixels / region pixels, over the K frames;
* ``step_m``: the quantisation step: the spacing of the distinct depth values the sensor output near z
  (:func:`ddsgen.study.quantisation.lattice_step`).

Published curves (docs/validation.md, noise study): :func:`nguyen_sigma`, :func:`khoshelham_sigma`; the predicted
quantisation step and the real Kinect depth values are in :mod:`ddsgen.study.quantisation`.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Callable, Iterable

import numpy as np

from ddsgen.errors import InputError
from ddsgen.preset import Intrinsics, SensorPreset
from ddsgen.scene.sampling import FrameScene, PlacedObject
from ddsgen.sensor.depth_sensor import DepthSensor
from ddsgen.sensor.sensor_cast import cast_for_sensor
from ddsgen.study.quantisation import lattice_step, quantisation_step

DEFAULT_Z = "0.5:4.0:0.25"
DEFAULT_ANGLES = "0,15,30,45,60,75"
DEFAULT_ALBEDO = 0.8  # IR reflectance of the board (a matte white-ish target)
ROI_DEPTH_TOLERANCE = 0.10  # region of interest: |true depth - z| <= 10 % of z
JSON_KEYS = ("z", "angle_deg", "rms_m", "std_m", "bias_m", "valid_fraction", "step_m")


# ------------------------------------------------------------------------------------------------ published models


def nguyen_sigma(z, angle_deg=None):
    """Nguyen, Izadi & Lovell 2012 axial noise of a Kinect V1 (m).

    ``angle_deg=None``: the 10-60 deg curve 0.0012 + 0.0019 (z - 0.4)^2. With an angle theta (deg), plus the
    angle term 0.0001 / sqrt(z) * theta^2 / (pi/2 - theta)^2 (theta in radians).
    """
    z = np.asarray(z, dtype=np.float64)
    sigma = 0.0012 + 0.0019 * (z - 0.4) ** 2
    if angle_deg is not None:
        theta = np.radians(np.asarray(angle_deg, dtype=np.float64))
        sigma = sigma + 0.0001 / np.sqrt(z) * theta**2 / (np.pi / 2 - theta) ** 2
    return sigma


def nguyen_sigma_px(z, disparity_fb: float):
    """:func:`nguyen_sigma` (10-60 deg) read as disparity, sigma_z f b / z^2 (px) for a sensor of f b (px m)."""
    z = np.asarray(z, dtype=np.float64)
    return nguyen_sigma(z) * disparity_fb / z**2


def khoshelham_sigma(z):
    """Khoshelham & Oude Elberink 2012 random depth error of a Kinect V1, ~1.425e-3 z^2 (m)."""
    return 1.425e-3 * np.asarray(z, dtype=np.float64) ** 2


# ------------------------------------------------------------------------------------------------ grid parsing


def parse_grid(text: str, option: str, low: float, high: float, low_open: bool = False) -> list[float]:
    """Parse ``START:STOP:STEP`` (inclusive of STOP when it falls on the grid) or ``A,B,C`` into sorted floats.

    Raises:
        InputError: ``OPTION: problem`` on malformed text or values outside [low, high] (or (low, high]).
    """
    raw = str(text).strip()
    shown = repr(text)
    if not raw:
        raise InputError(f"{option}: expected START:STOP:STEP or a comma-separated list, got {shown}")
    if ":" in raw:
        parts = raw.split(":")
        if len(parts) != 3:
            raise InputError(f"{option}: expected START:STOP:STEP (three numbers), got {shown}")
        try:
            start, stop, step = (float(p) for p in parts)
        except ValueError:
            raise InputError(f"{option}: expected START:STOP:STEP with numbers, got {shown}") from None
        if not all(math.isfinite(v) for v in (start, stop, step)):
            raise InputError(f"{option}: START:STOP:STEP must be finite numbers, got {shown}")
        if step <= 0:
            raise InputError(f"{option}: STEP must be > 0, got {shown}")
        if stop < start:
            raise InputError(f"{option}: STOP must not be smaller than START, got {shown}")
        count = int(math.floor((stop - start) / step + 1e-9)) + 1
        if count > 1000:
            raise InputError(f"{option}: {count} values is too many (at most 1000), got {shown}")
        values = [round(start + i * step, 9) for i in range(count)]
    else:
        values = []
        for item in raw.split(","):
            try:
                value = float(item)
            except ValueError:
                raise InputError(f"{option}: {item.strip()!r} is not a number (in {shown})") from None
            if not math.isfinite(value):
                raise InputError(f"{option}: values must be finite, got {shown}")
            values.append(value)
    for value in values:
        below = value <= low if low_open else value < low
        if below or value > high:
            bracket = "(" if low_open else "["
            raise InputError(f"{option}: {value:g} is outside {bracket}{low:g}, {high:g}]")
    return sorted(set(values))


# ------------------------------------------------------------------------------------------------ set-up


def plane_scene(z: float, angle_deg: float, albedo: float = DEFAULT_ALBEDO):
    """A :class:`~ddsgen.scene.sampling.FrameScene` with one flat rectangle at distance z, tilted by alpha.

    The rectangle passes through (0, 0, z) (camera frame = world frame), with in-plane x axis
    (cos a, 0, sin a) and normal (-sin a, 0, cos a): rotated by ``angle_deg`` about the vertical axis, the
    right side receding. It extends 3 z along its x axis on the far side and, on the near side, at most to
    where it comes within 0.25 z of the camera, and far enough vertically to fill the field of view.
    """
    import trimesh

    a = math.radians(angle_deg)
    sin_a, cos_a = math.sin(a), math.cos(a)
    far = 3.0 * z
    near = min(3.0 * z, 0.75 * z / sin_a) if sin_a > 1e-9 else 3.0 * z
    half_y = 0.6 * (z + far * sin_a) + 0.5 * z
    vertices = np.array([[-near, -half_y, 0.0], [far, -half_y, 0.0], [far, half_y, 0.0], [-near, half_y, 0.0]])
    mesh = trimesh.Trimesh(vertices=vertices, faces=np.array([[0, 1, 2], [0, 2, 3]]), process=False)
    world_T_obj = np.eye(4)
    world_T_obj[:3, 0] = [cos_a, 0.0, sin_a]
    world_T_obj[:3, 1] = [0.0, 1.0, 0.0]
    world_T_obj[:3, 2] = [-sin_a, 0.0, cos_a]
    world_T_obj[:3, 3] = [0.0, 0.0, z]
    board = PlacedObject(1, "board", f"plane:{near + far:g}x{2 * half_y:g}", mesh, world_T_obj, float(albedo))
    return FrameScene(objects=[board], background=[], world_T_cam=np.eye(4), frame_index=0, seed=0,
                      scene_name=f"plane z={z:g} angle={angle_deg:g}")  # fmt: skip


def study_intrinsics(preset: SensorPreset, rows: int | None = None) -> Intrinsics:
    """The preset's intrinsics, or a centred crop of ``rows`` image rows (same focal length and columns).

    A crop sees exactly the central rows of the full sensor: the rows are matched independently and the
    pattern is centred on the image, so a crop is the same physics on fewer pixels (used by the tests).
    """
    intr = preset.intrinsics
    if rows is not None and rows > intr.height:  # not silently the whole image: the user asked for something else
        raise InputError(f"--rows: the preset's image has {intr.height} rows, got {rows}")
    if rows is None or rows == intr.height:
        return intr
    if rows < 2 * preset.block_size_px or (intr.height - rows) % 2:
        raise InputError(
            f"--rows: must be >= {2 * preset.block_size_px} and leave an even number of rows "
            f"({intr.height} - rows), got {rows}"
        )
    top = (intr.height - rows) // 2
    return Intrinsics(intr.width, rows, intr.fx, intr.fy, intr.cx, intr.cy - top)


def region_of_interest(clean_depth: np.ndarray, usable: np.ndarray, z: float) -> np.ndarray:
    """(H, W) bool: the central half of rows and columns, where the true depth is within 10 % of z."""
    height, width = clean_depth.shape
    roi = np.zeros((height, width), bool)
    roi[height // 4 : height - height // 4, width // 4 : width - width // 4] = True
    return roi & usable & (np.abs(clean_depth - z) <= ROI_DEPTH_TOLERANCE * z)


# ------------------------------------------------------------------------------------------------ measurements


def plane_residuals(u: np.ndarray, v: np.ndarray, depth: np.ndarray, inlier_floor_m: float = 0.0) -> np.ndarray:
    """Depth minus the plane fitted to (u, v, depth); NaN-free, same length as ``depth``.

    A plane's inverse depth is linear in the pixel coordinates, so 1/Z = a u + b v + c is fitted by least
    squares, first on all points, then again on the inliers within max(5 robust sigma, ``inlier_floor_m``)
    (mismatches must not tilt the reference plane; they still count in the residuals returned).
    """
    design = np.stack([u, v, np.ones_like(u)], axis=1).astype(np.float64)
    inverse = 1.0 / depth.astype(np.float64)
    keep = np.ones(len(depth), bool)
    residual = np.zeros(len(depth))
    for _ in range(2):
        coef, *_ = np.linalg.lstsq(design[keep], inverse[keep], rcond=None)
        residual = depth - 1.0 / (design @ coef)
        centre = np.median(residual[keep])
        robust_sigma = 1.4826 * np.median(np.abs(residual[keep] - centre))
        keep = np.abs(residual - centre) <= max(5.0 * robust_sigma, inlier_floor_m)
        if keep.sum() < 3:
            break
    return residual


@dataclasses.dataclass
class NoisePoint:
    """The measurements at one (z, alpha). Lengths in metres. ``None`` where nothing valid was measured."""

    z: float
    angle_deg: float
    rms_m: float | None
    std_m: float | None
    bias_m: float | None
    valid_fraction: float
    step_m: float | None
    roi_pixels: int = 0  # region pixels per frame
    frames: int = 0
    outlier_fraction: float | None = None  # valid pixels whose plane residual exceeds 5 robust sigma / 3 steps
    inlier_std_m: float | None = None  # like std_m, without the outliers (the noise of the correct matches)

    def as_json(self) -> dict:
        """Exactly the ``noise.json`` keys."""
        return {key: getattr(self, key) for key in JSON_KEYS}


class _Accumulator:
    """Pools the per-frame statistics of one (z, alpha)."""

    def __init__(self, clean_depth: np.ndarray, roi: np.ndarray, step_floor_m: float):
        self.v, self.u = (a.astype(np.float64) for a in np.nonzero(roi))
        self.roi = roi
        self.truth = clean_depth[roi].astype(np.float64)
        self.step_floor_m = step_floor_m
        self.frames = 0
        self.n_valid = 0
        self.err_sum = 0.0
        self.err_sq = 0.0
        self.res_sq = 0.0
        self.res_n = 0
        self.outliers = 0
        self.inlier_sq = 0.0
        self.inlier_n = 0
        self.values: list[np.ndarray] = []

    def add(self, depth: np.ndarray, valid: np.ndarray) -> None:
        self.frames += 1
        d = depth[self.roi].astype(np.float64)
        ok = valid[self.roi] & (d > 0)
        if not ok.any():
            return
        d_ok = d[ok]
        error = d_ok - self.truth[ok]
        self.n_valid += int(ok.sum())
        self.err_sum += float(error.sum())
        self.err_sq += float((error**2).sum())
        self.values.append(d_ok.astype(np.float32))
        if ok.sum() >= 10:
            residual = plane_residuals(self.u[ok], self.v[ok], d_ok, inlier_floor_m=3.0 * self.step_floor_m)
            self.res_sq += float((residual**2).sum())
            self.res_n += len(residual)
            centre = np.median(residual)
            sigma = 1.4826 * np.median(np.abs(residual - centre))
            inlier = np.abs(residual - centre) <= max(5.0 * sigma, 3.0 * self.step_floor_m)
            self.outliers += int((~inlier).sum())
            self.inlier_sq += float((residual[inlier] ** 2).sum())
            self.inlier_n += int(inlier.sum())

    def result(self, z: float, angle_deg: float) -> NoisePoint:
        n_roi = int(self.roi.sum())
        total = n_roi * self.frames
        valid_fraction = self.n_valid / total if total else 0.0
        if self.n_valid == 0:
            return NoisePoint(z, angle_deg, None, None, None, valid_fraction, None, n_roi, self.frames)
        values = np.concatenate(self.values)
        return NoisePoint(
            z=z,
            angle_deg=angle_deg,
            rms_m=math.sqrt(self.err_sq / self.n_valid),
            std_m=math.sqrt(self.res_sq / self.res_n) if self.res_n else None,
            bias_m=self.err_sum / self.n_valid,
            valid_fraction=valid_fraction,
            step_m=lattice_step(values, z),
            roi_pixels=n_roi,
            frames=self.frames,
            outlier_fraction=self.outliers / self.res_n if self.res_n else None,
            inlier_std_m=math.sqrt(self.inlier_sq / self.inlier_n) if self.inlier_n else None,
        )


def frame_seed(seed: int, z: float, angle_deg: float, frame: int) -> list[int]:
    """The noise seed of frame k at (z, alpha): independent of the rest of the grid."""
    return [int(seed), int(round(z * 10000)), int(round(angle_deg * 10000)), int(frame)]


def simulate_point(sensor, geometry, seed: int, z: float, angle_deg: float, frames: int,
                   add: Callable[[np.ndarray, np.ndarray], None], on_frame: Callable[[], None] | None = None) -> None:
    """The K = ``frames`` frames of one (z, alpha) through ``sensor``: ``add(depth (H, W) m, valid (H, W) bool)``
    for each (frame k's noise seed :func:`frame_seed`), then ``on_frame()``."""
    import torch

    for k in range(frames):
        with torch.no_grad():
            out = sensor(geometry, seed=frame_seed(seed, z, angle_deg, k))
        add(out.depth.numpy(), out.valid.numpy())
        if on_frame is not None:
            on_frame()


def run_noise_study(
    preset: SensorPreset,
    zs: Iterable[float],
    angles_deg: Iterable[float],
    frames: int = 4,
    seed: int = 0,
    rows: int | None = None,
    albedo: float = DEFAULT_ALBEDO,
    on_frame: Callable[[], None] | None = None,
) -> list[NoisePoint]:
    """Render and measure every (z, alpha) of the grid; K = ``frames`` noise seeds each.

    Args:
        preset: the sensor.
        zs: plane distances (m); angles_deg: tilts about the vertical axis (deg, 0 <= alpha < 90).
        frames: frames (noise seeds) per point.
        seed: study seed; frame k of (z, alpha) uses :func:`frame_seed`.
        rows: render only a centred crop of this many rows (None: the full image).
        albedo: IR reflectance of the board.
        on_frame: called after every simulated frame (progress).

    Returns:
        One :class:`NoisePoint` per (z, alpha), z-major.
    """
    if frames < 1:
        raise InputError(f"--frames: must be >= 1, got {frames}")
    intr = study_intrinsics(preset, rows)
    sensor = DepthSensor(preset, intrinsics=intr).eval()
    points = []
    for z in zs:
        step_floor = float(quantisation_step(z, intr.fx, preset.baseline_m, preset.subpixel_level))
        for angle in angles_deg:
            hits, geometry = cast_for_sensor(plane_scene(z, angle, albedo), intr, preset)
            roi = region_of_interest(hits.depth, hits.hit & ~hits.shadow, z)
            acc = _Accumulator(hits.depth, roi, step_floor)
            simulate_point(sensor, geometry, seed, z, angle, frames, acc.add, on_frame)
            points.append(acc.result(float(z), float(angle)))
    return points
