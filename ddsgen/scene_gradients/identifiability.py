"""Which of an object's six pose directions its pixels determine, from the curvature of its data term.

Around the start pose the depth term of an object is, to second order, ``0.5 d^T F d`` in its pose
correction d = (rotation (3, rad), translation (3, m)), camera axes about the object's centre. F is the
Gauss-Newton matrix (Fisher information) of the residuals the optimiser compares:

* the clean depth of each of the object's compared pixels (not held out, not occluded), noise ``depth_sigma_m``;
* with the edge term, the position of each outline point across the outline (px, along the outline's image normal:
  a slide along the outline changes nothing the edges see), noise ``edge_sigma_px``;

each divided by ``correlated`` (neighbouring pixels share quantisation and noise: they count as fewer). The
Jacobian comes from central finite differences of the posed hits (the cast's triangles held fixed).

Rotations are scaled by the object's radius (a turn moves the surface by about angle x radius), so the six
directions compare in metres. An eigen-direction of F whose standard deviation ``1 / sqrt(lambda)`` exceeds
``max_sigma_m`` is undetermined: the correction has no component there (the object stays at its start along
it, e.g. a turn about a symmetry axis). An axis is reported determined if its own standard deviation (of F
with a small ridge) is within ``max_sigma_m``; an axis that is not keeps no correction either.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import torch

from ddsgen.scene_gradients.hits import posed_geometry

AXES = ("rotation x", "rotation y", "rotation z", "translation x", "translation y", "translation z")


@dataclasses.dataclass
class Identifiability:
    """One object's six directions (camera axes about its centre): AXES order.

    sigma: (6,) standard deviation of each axis (rotations in deg, translations in mm).
    determined: (6,) bool. projection: (6, 6) the projector onto the determined subspace, in the scaled
    coordinates (rotation x radius, translation; m). radius_m: the scale.
    """

    sigma: np.ndarray
    determined: np.ndarray
    projection: np.ndarray
    radius_m: float

    def undetermined_axes(self) -> list[str]:
        return [name for name, ok in zip(AXES, self.determined) if not ok]

    def as_dict(self) -> dict:
        return {name: {"determined": bool(ok), "sigma": round(float(s), 4), "unit": "deg" if i < 3 else "mm"}
                for i, (name, ok, s) in enumerate(zip(AXES, self.determined, self.sigma))}  # fmt: skip

    def project(self, rotation: torch.Tensor, translation: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The correction (rotation (3,) rad, translation (3,) m) with its undetermined components removed."""
        scaled = torch.cat([rotation * self.radius_m, translation])
        kept = torch.as_tensor(self.projection, dtype=scaled.dtype) @ scaled
        kept = kept * torch.as_tensor(self.determined, dtype=scaled.dtype)  # an undetermined axis: none at all
        return kept[:3] / self.radius_m, kept[3:]


def object_identifiability(poses, tensors, part: int, pixels: torch.Tensor, outline, intrinsics, silhouette=None, *,
                           depth_sigma_m: float = 0.003, edge_sigma_px: float = 1.0, correlated: float = 4.0,
                           max_sigma_m: float = 0.001, radius_m: float = 0.05, h: float = 1e-4) -> Identifiability:  # fmt: skip
    """Identifiability of part ``part`` (module docstring) at the poses' current correction.

    Args:
        poses: the :class:`~ddsgen.scene_gradients.poses.ScenePoses`; tensors: the last cast.
        pixels: (H, W) bool the object's compared pixels; outline: the cast's outline points (None: no edge term).
        silhouette: (H, W) bool the object's pixels in the cast (the outline's normals), needed with ``outline``.
        radius_m: the object's radius (rotation scale).
    """
    rows = []
    base_r = poses.rotation.detach().clone()
    base_t = poses.translation.detach().clone()
    depth_cols, edge_cols = [], []
    on_outline = None if outline is None or silhouette is None else (outline.owner == part)
    normals = None
    with torch.no_grad():
        for axis in range(6):
            values = []
            for sign in (1.0, -1.0):
                r, t = base_r.clone(), base_t.clone()
                (r if axis < 3 else t)[part, axis % 3] += sign * h
                poses.rotation.copy_(r)
                poses.translation.copy_(t)
                R, tt = poses()
                clean = posed_geometry(tensors, R, tt, poses.albedo).clean_depth[pixels].double()
                edge = _outline_image_px(outline, on_outline, R, tt, intrinsics)
                if edge is not None:
                    if normals is None:
                        normals = _outline_normals(silhouette, edge.detach())
                    edge = (edge * normals).sum(-1)
                values.append((clean, edge))
            depth_cols.append((values[0][0] - values[1][0]) / (2 * h))
            edge_cols.append(None if values[0][1] is None else (values[0][1] - values[1][1]) / (2 * h))
        poses.rotation.copy_(base_r)
        poses.translation.copy_(base_t)
    J = torch.stack(depth_cols, dim=1).numpy() / depth_sigma_m
    rows.append(J / np.sqrt(correlated))
    if edge_cols[0] is not None and edge_cols[0].numel():
        rows.append(torch.stack(edge_cols, dim=1).numpy() / edge_sigma_px / np.sqrt(correlated))
    J = np.concatenate(rows) if rows else np.zeros((0, 6))
    scale = np.array([1.0 / radius_m] * 3 + [1.0] * 3)  # d(residual)/d(rotation x radius)
    J = J * scale
    F = J.T @ J
    eigenvalues, vectors = np.linalg.eigh(F)
    keep = eigenvalues * max_sigma_m**2 >= 1.0
    projection = vectors[:, keep] @ vectors[:, keep].T
    ridge = np.linalg.inv(F + np.eye(6) / (100.0 * max_sigma_m) ** 2)
    sigma_m = np.sqrt(np.diag(ridge))
    determined = sigma_m <= max_sigma_m
    sigma = np.concatenate([np.degrees(sigma_m[:3] / radius_m), sigma_m[3:] * 1000.0])
    return Identifiability(sigma=sigma, determined=determined, projection=projection, radius_m=float(radius_m))


def _outline_normals(silhouette, uv: torch.Tensor) -> torch.Tensor:
    """(M, 2) unit image normals of the silhouette's outline at the points ``uv`` (M, 2) px (outwards)."""
    import cv2

    smooth = cv2.GaussianBlur(np.asarray(silhouette, dtype=np.float32), (0, 0), 1.5)
    gy, gx = np.gradient(smooth)
    u = np.clip(np.round(uv[:, 0].numpy()).astype(int), 0, smooth.shape[1] - 1)
    v = np.clip(np.round(uv[:, 1].numpy()).astype(int), 0, smooth.shape[0] - 1)
    n = -np.stack([gx[v, u], gy[v, u]], axis=-1).astype(np.float64)
    n /= np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-9)
    return torch.from_numpy(n)


def _outline_image_px(outline, selected, R, t, intrinsics):
    """(M, 2) the image positions (u, v) of the selected outline points (px), or None without any."""
    if outline is None or selected is None or not bool(selected.any()):
        return None
    owner = outline.owner[selected]
    X = (R[owner] @ outline.points[selected][..., None].to(R.dtype))[..., 0] + t[owner]
    z = X[:, 2].clamp_min(1e-3)
    return torch.stack([intrinsics.fx * X[:, 0] / z + intrinsics.cx, intrinsics.fy * X[:, 1] / z + intrinsics.cy], -1)
