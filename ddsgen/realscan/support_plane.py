"""The support plane of a scan frame: the table its objects stand on, fitted by RANSAC to the real depth.

:func:`fit_support_plane` fits a :class:`Plane` to the valid real depth outside the objects' silhouettes, with the
inlier test in disparity (the tolerance follows the sensor's depth resolution), and takes the plane the posed objects
rest on when a frame holds two large ones (a table and the floor below it). :func:`ddsgen.realscan.simulate.prepare_frame`
adds it to the frame's scene as a large background quad posed by :func:`plane_pose`, so that the table and the
objects' projector shadows on it are modelled too.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ddsgen.preset import Intrinsics


@dataclasses.dataclass
class Plane:
    """A plane n . X + d = 0 in the camera frame (n unit, pointing towards the camera)."""

    normal: np.ndarray
    offset: float
    inliers: int
    candidates: int

    def as_dict(self) -> dict:
        return {"normal": [round(float(x), 6) for x in self.normal], "offset_m": round(float(self.offset), 6),
                "inliers": int(self.inliers), "candidates": int(self.candidates)}  # fmt: skip


def plane_pose(plane: Plane) -> np.ndarray:
    """A pose whose z axis is the plane normal and whose origin is the foot of the camera's optical axis on it."""
    n = np.asarray(plane.normal, dtype=np.float64)
    # Point on the plane closest to the optical axis hit (or to the origin if the axis is parallel).
    if abs(n[2]) > 1e-6:
        origin = np.array([0.0, 0.0, -plane.offset / n[2]])
    else:
        origin = -plane.offset * n
    helper = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(helper, n)
    x /= np.linalg.norm(x)
    y = np.cross(n, x)
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = x, y, n, origin
    return T


def backproject(depth: np.ndarray, intrinsics: Intrinsics) -> np.ndarray:
    """(H, W, 3) camera-frame points of a depth image (z = depth)."""
    h, w = depth.shape
    u = (np.arange(w) - intrinsics.cx) / intrinsics.fx
    v = (np.arange(h) - intrinsics.cy) / intrinsics.fy
    return np.stack([u[None, :] * depth, v[:, None] * depth, depth], axis=-1)


def fit_support_plane(depth: np.ndarray, intrinsics: Intrinsics, exclude: np.ndarray, disparity_fb: float,
                      rng: np.random.Generator, iterations: int = 300, tolerance_px: float = 0.5,
                      min_inlier_fraction: float = 0.2, max_points: int = 20000, resting: np.ndarray | None = None,
                      support_gap_m: float = 0.05) -> Plane | None:  # fmt: skip
    """RANSAC plane through the valid real depth outside ``exclude``.

    Inliers agree with the plane within ``tolerance_px`` px of disparity (f b / z), so the
    tolerance follows the sensor's depth resolution (it grows with z^2). The best plane is
    refined by least squares on its inliers. Returns None when fewer than
    ``min_inlier_fraction`` of the candidate pixels are inliers (no dominant plane).

    ``resting``: (K, 3) camera-frame points of the posed objects (their visible surface). A real
    frame can hold two large planes (the LineMOD cat: the table at 0.75 m and the floor 0.73 m below
    it, with 6209 and 6150 inliers: the noise seed decided); the support plane is the one the objects
    rest on, so a hypothesis counts only when the objects' lowest point lies within ``support_gap_m``
    of it on the camera's side. When no hypothesis qualifies (objects seen only from far above the
    plane), the plane with the most inliers is taken.
    """
    mask = (depth > 0) & ~exclude
    points = backproject(depth, intrinsics)[mask]
    if len(points) < 50:
        return None
    if len(points) > max_points:
        points = points[rng.choice(len(points), max_points, replace=False)]
    z = points[:, 2]
    disp = disparity_fb / z
    best, best_count = None, 0
    supported, supported_count = None, 0
    for _ in range(iterations):
        sample = points[rng.choice(len(points), 3, replace=False)]
        n = np.cross(sample[1] - sample[0], sample[2] - sample[0])
        norm = np.linalg.norm(n)
        if norm < 1e-9:
            continue
        n /= norm
        d = -float(n @ sample[0])
        inliers = _plane_inliers(points, disp, n, d, disparity_fb, tolerance_px)
        count = int(inliers.sum())
        if count > best_count:
            best, best_count = (n, d), count
        if count > supported_count and _objects_rest_on(resting, n, d, support_gap_m):
            supported, supported_count = (n, d), count
    if supported is not None and supported_count >= min_inlier_fraction * len(points):
        best, best_count = supported, supported_count
    if best is None or best_count < min_inlier_fraction * len(points):
        return None
    n, d = best
    for _ in range(2):  # least-squares refinement on the inliers
        inliers = _plane_inliers(points, disp, n, d, disparity_fb, tolerance_px)
        sel = points[inliers]
        centroid = sel.mean(axis=0)
        _, _, vt = np.linalg.svd(sel - centroid, full_matrices=False)
        n = vt[2]
        d = -float(n @ centroid)
    if d < 0:  # orient the normal towards the camera (origin on the positive side)
        n, d = -n, -d
    count = int(_plane_inliers(points, disp, n, d, disparity_fb, tolerance_px).sum())
    return Plane(normal=n, offset=d, inliers=count, candidates=len(points))


def _objects_rest_on(resting: np.ndarray | None, n: np.ndarray, d: float, gap_m: float) -> bool:
    """Whether the objects' lowest point lies within ``gap_m`` of the plane n.P + d = 0, on the camera's side."""
    if resting is None or len(resting) == 0:
        return False
    height = (resting @ n + d) * (1.0 if d >= 0 else -1.0)  # > 0 on the camera's side (origin: height |d|)
    return bool(-gap_m <= height.min() <= gap_m)


def _plane_inliers(points, disp, n, d, fb, tolerance_px):
    # Depth of the plane along each point's ray: ray r = p / z (z = 1), plane n.(t r) + d = 0.
    rays = points / points[:, 2:3]
    denom = rays @ n
    with np.errstate(divide="ignore", invalid="ignore"):
        t = -d / denom
        plane_disp = np.where(t > 0, fb / t, np.inf)
    return np.abs(plane_disp - disp) <= tolerance_px
