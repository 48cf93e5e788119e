"""Pose parameterisation of the scene's rigid parts: axis-angle + translation corrections.

Each part k (an object, or the support plane) keeps its initial pose ``cam_T_obj0 = [R0 | t0]``
and a correction (omega_k, tau_k): a rotation by ``exp([omega]_x)`` about the part's centre ``c_k``
(camera axes, radians) and a translation ``tau_k`` (camera frame, metres):

    X_cam = exp([omega]_x) (R0 X + t0 - c) + c + tau

Rotating about the part's own centre (not the camera origin) keeps the rotation and translation
directions nearly decoupled, so one learning rate per kind suits every part.

Views of one static scene share their objects' corrections (:class:`SharedObjectCorrections`): a
correction in the object's own frame (omega_b, tau_b) is, in a view whose initial rotation is R0, the
camera-frame correction (R0 omega_b, R0 tau_b) about the same centre, since

    exp([R0 omega_b]_x) (R0 X + t0 - c) + c + R0 tau_b = R0 (exp([omega_b]_x) (X - c_b) + c_b + tau_b) + t0

with c = R0 c_b + t0. So one body-frame correction moves the object alike in every view.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import nn


def axis_angle_to_matrix(rotation: torch.Tensor) -> torch.Tensor:
    """Rodrigues' formula: (..., 3) axis-angle vectors (rad) -> (..., 3, 3) rotation matrices.

    Smooth at zero (Taylor terms for tiny angles), so gradients at omega = 0 are exact.
    """
    theta2 = (rotation * rotation).sum(-1, keepdim=True)[..., None]  # (..., 1, 1)
    theta = theta2.clamp_min(1e-24).sqrt()
    small = theta2 < 1e-8
    a = torch.where(small, 1.0 - theta2 / 6.0, torch.sin(theta) / theta)
    b = torch.where(small, 0.5 - theta2 / 24.0, (1.0 - torch.cos(theta)) / theta2.clamp_min(1e-24))
    x, y, z = rotation.unbind(-1)
    zero = torch.zeros_like(x)
    k = torch.stack([zero, -z, y, z, zero, -x, -y, x, zero], dim=-1).reshape(*rotation.shape[:-1], 3, 3)
    eye = torch.eye(3, dtype=rotation.dtype, device=rotation.device).expand_as(k)
    return eye + a * k + b * (k @ k)


def rotation_angle_deg(R_a: np.ndarray, R_b: np.ndarray) -> float:
    """Angle (degrees) of the rotation R_a^T R_b between two (3, 3) rotation matrices."""
    cos = (np.trace(np.asarray(R_a).T @ np.asarray(R_b)) - 1.0) / 2.0
    return math.degrees(math.acos(float(np.clip(cos, -1.0, 1.0))))


def pose_difference(T_a: np.ndarray, T_b: np.ndarray) -> tuple[float, float]:
    """(rotation angle in degrees, translation distance in mm) between two (4, 4) poses."""
    T_a, T_b = np.asarray(T_a, dtype=np.float64), np.asarray(T_b, dtype=np.float64)
    return rotation_angle_deg(T_a[:3, :3], T_b[:3, :3]), float(np.linalg.norm(T_a[:3, 3] - T_b[:3, 3]) * 1000.0)


def perturb_pose(cam_T_obj: np.ndarray, centre: np.ndarray, angle_deg: float, offset_mm: float,
                 rng: np.random.Generator) -> np.ndarray:  # fmt: skip
    """The pose rotated by exactly ``angle_deg`` about a random axis through ``centre`` (camera frame, m)
    and moved by exactly ``offset_mm`` in a random direction (for refinement experiments and tests)."""
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    direction = rng.normal(size=3)
    direction /= np.linalg.norm(direction)
    R = axis_angle_to_matrix(torch.tensor(axis * math.radians(angle_deg), dtype=torch.float64)).numpy()
    T = np.asarray(cam_T_obj, dtype=np.float64).copy()
    centre = np.asarray(centre, dtype=np.float64)
    T[:3, :3] = R @ T[:3, :3]
    T[:3, 3] = R @ (T[:3, 3] - centre) + centre + direction * offset_mm / 1000.0
    return T


class ScenePoses(nn.Module):
    """Learnable pose corrections and IR albedos of N rigid parts.

    Args:
        initial: (N, 4, 4) initial ``cam_T_obj`` (metres).
        centres: (N, 3) rotation centres in the camera frame (m), e.g. the parts' mesh centres at
            their initial poses.
        albedo: (N,) initial IR reflectances (> 0).
        free: (N,) bool, which parts may move (default all); a fixed part keeps its initial pose.

    Parameters: ``rotation`` (N, 3) axis-angle (rad), ``translation`` (N, 3) m, ``log_albedo`` (N,).
    After :meth:`share_objects` the first n parts' corrections come from a
    :class:`SharedObjectCorrections` instead (their rows of ``rotation`` and ``translation`` are unused).
    """

    def __init__(self, initial, centres, albedo, free=None):
        super().__init__()
        initial = torch.as_tensor(np.asarray(initial), dtype=torch.float64)
        self.register_buffer("initial", initial)
        self.register_buffer("centres", torch.as_tensor(np.asarray(centres), dtype=torch.float64))
        n = initial.shape[0]
        free = torch.ones(n, dtype=torch.bool) if free is None else torch.as_tensor(np.asarray(free, dtype=bool))
        self.register_buffer("free", free)
        self.rotation = nn.Parameter(torch.zeros(n, 3, dtype=torch.float64))
        self.translation = nn.Parameter(torch.zeros(n, 3, dtype=torch.float64))
        albedo = torch.as_tensor(np.asarray(albedo), dtype=torch.float64).clamp_min(1e-6)
        self.log_albedo = nn.Parameter(albedo.log())
        self.shared = None

    def share_objects(self, shared: SharedObjectCorrections) -> None:
        """Take the first ``len(shared)`` parts' corrections from ``shared`` (body frame, tied across views)."""
        if len(shared) > len(self):
            raise ValueError(f"{len(shared)} shared objects, but the scene has {len(self)} parts")
        self.shared = shared

    def corrections(self) -> tuple[torch.Tensor, torch.Tensor]:
        """The camera-frame corrections (rotation (N, 3) rad, translation (N, 3) m) the poses apply."""
        free = self.free.to(self.rotation.dtype)[:, None]
        rotation, translation = self.rotation * free, self.translation * free
        if self.shared is None:
            return rotation, translation
        n = len(self.shared)
        R0 = self.initial[:n, :3, :3]
        rotation = torch.cat([(R0 @ self.shared.rotation[..., None])[..., 0], rotation[n:]])
        translation = torch.cat([(R0 @ self.shared.translation[..., None])[..., 0], translation[n:]])
        return rotation, translation

    def __len__(self) -> int:
        return int(self.initial.shape[0])

    @property
    def albedo(self) -> torch.Tensor:
        return self.log_albedo.exp()

    def forward(self) -> tuple[torch.Tensor, torch.Tensor]:
        """The current poses: R (N, 3, 3) and t (N, 3) (float64, differentiable)."""
        rotation, translation = self.corrections()
        dR = axis_angle_to_matrix(rotation)
        R = dR @ self.initial[:, :3, :3]
        t = (dR @ (self.initial[:, :3, 3] - self.centres)[..., None])[..., 0] + self.centres + translation
        return R, t

    def matrices(self) -> np.ndarray:
        """(N, 4, 4) float64 numpy: the current ``cam_T_obj`` (detached)."""
        with torch.no_grad():
            R, t = self()
        T = np.tile(np.eye(4), (len(self), 1, 1))
        T[:, :3, :3], T[:, :3, 3] = R.numpy(), t.numpy()
        return T


class SharedObjectCorrections(nn.Module):
    """Pose corrections of n objects in their own frames, shared by every view of one static scene.

    Parameters: ``rotation`` (n, 3) axis-angle (rad, object axes) about each object's bounding-box
    centre, ``translation`` (n, 3) (m, object axes). See the module docstring for why a body-frame
    correction moves the object alike in every view.
    """

    def __init__(self, n_objects: int):
        super().__init__()
        self.rotation = nn.Parameter(torch.zeros(int(n_objects), 3, dtype=torch.float64))
        self.translation = nn.Parameter(torch.zeros(int(n_objects), 3, dtype=torch.float64))

    def __len__(self) -> int:
        return int(self.rotation.shape[0])
