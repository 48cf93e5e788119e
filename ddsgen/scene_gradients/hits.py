"""Differentiable hit recomputation: the ray cast's triangle ids + posed triangles -> hit geometry in torch.

Ray casting (Embree) is not differentiable. It tells, per pixel, which part (``owner``) and which
triangle the ray hit; between re-casts that assignment is held fixed and the hit is recomputed
in torch as the intersection of the pixel's ray ``d = K^-1 [u, v, 1]`` (z = 1) with the plane of
its triangle *posed* by the part's current (R, t):

    n = R n_o,    n . X = n_o . V0 + n . t      (n_o, V0: the face normal and a vertex, object frame)
    z = (n_o . V0 + n . t) / (n . d),   P = z d,   normal = +-n facing the camera

This is exactly the plane through the three posed vertices R V_i + t, so the gradients are the
exact interior gradients: the point slides along its ray as the triangle moves, the dots it
receives move through the projector geometry, and the matcher sees the change. What the
assignment cannot follow (a pixel changing triangle, silhouettes, shadows) is caught up by
re-casting every few optimisation steps.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import torch

from ddsgen.sensor.geometry import SensorGeometry

# |n . d| below this is treated as grazing (avoids dividing by ~0 on silhouette pixels).
_MIN_COS = 1e-4


@dataclasses.dataclass
class SceneTensors:
    """The constant part of one ray cast, ready for :func:`posed_geometry`. Images are (H, W), flat M = hits.

    index: (M,) int64 flat pixel indices of the hits; owner: (M,) int64 part index of each hit.
    directions: (M, 3) float64 ray directions (z = 1); face_normal: (M, 3) float64 unit normal of the
    hit face in its part's frame; face_offset: (M,) float64 n_o . V0 (m).
    hit, shadow: (H, W) bool (shadow as cast: held fixed until the next re-cast);
    instance: (H, W) int32 object ids (0 = background or nothing); n_parts: number of parts.
    triangle (H, W) int32 and barycentric (H, W, 2) float32: the cast's, kept for users.
    ir_margin: the same for the strip the IR camera sees beyond the right edge, or None.
    """

    index: torch.Tensor
    owner: torch.Tensor
    directions: torch.Tensor
    face_normal: torch.Tensor
    face_offset: torch.Tensor
    hit: torch.Tensor
    shadow: torch.Tensor
    instance: torch.Tensor
    n_parts: int
    triangle: torch.Tensor
    barycentric: torch.Tensor
    ir_margin: "SceneTensors | None" = None

    @property
    def shape(self) -> tuple[int, int]:
        return tuple(self.hit.shape)


def scene_tensors(parts_meshes, hits, directions: np.ndarray) -> SceneTensors:
    """Build :class:`SceneTensors` from a :class:`ddsgen.raycast.RayHits`.

    Args:
        parts_meshes: the N parts' meshes (trimesh, object frame, metres) in the order of ``hits.owner``
            (scene.objects + scene.background).
        hits: the ray cast of the scene with those parts (must carry ``owner`` and ``triangle``).
        directions: (H, W, 3) ray directions with z = 1 (:func:`ddsgen.raycast.ray_directions`).
    """
    if hits.owner is None or hits.triangle is None:
        raise ValueError("RayHits without owner/triangle ids: cast with ddsgen.raycast.cast")
    owner_img = np.asarray(hits.owner).reshape(-1)
    face_img = np.asarray(hits.triangle).reshape(-1)
    index = np.flatnonzero(owner_img >= 0)
    owner = owner_img[index].astype(np.int64)
    face = face_img[index].astype(np.int64)
    normals = np.zeros((len(index), 3))
    offsets = np.zeros(len(index))
    for k, mesh in enumerate(parts_meshes):
        sel = owner == k
        if not sel.any():
            continue
        vertices = np.asarray(mesh.vertices, dtype=np.float64)
        faces = np.asarray(mesh.faces)
        tri = vertices[faces[face[sel]]]  # (m, 3, 3)
        n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
        normals[sel] = n
        offsets[sel] = np.einsum("ij,ij->i", n, tri[:, 0])
    t = torch.from_numpy
    return SceneTensors(
        index=t(index.astype(np.int64)), owner=t(owner), directions=t(directions.reshape(-1, 3)[index].astype(np.float64)),
        face_normal=t(normals), face_offset=t(offsets), hit=t(np.ascontiguousarray(hits.hit)),
        shadow=t(np.ascontiguousarray(hits.shadow)), instance=t(np.asarray(hits.instance).astype(np.int32)),
        n_parts=len(parts_meshes), triangle=t(np.ascontiguousarray(hits.triangle)),
        barycentric=t(np.ascontiguousarray(hits.barycentric)),
    )  # fmt: skip


def posed_geometry(scene: SceneTensors, rotations: torch.Tensor, translations: torch.Tensor,
                   albedo: torch.Tensor) -> SensorGeometry:  # fmt: skip
    """Hit geometry of the scene with its parts at the given poses (differentiable in all three).

    Args:
        scene: from :func:`scene_tensors`.
        rotations: (N, 3, 3) the parts' ``cam_T_obj`` rotations.
        translations: (N, 3) their translations (m).
        albedo: (N,) their IR reflectances.

    Returns:
        :class:`~ddsgen.sensor.geometry.SensorGeometry` (float32, (H, W)): points (m), normals
        (unit, facing the camera), albedo, clean_depth (m) recomputed in torch; hit and shadow as cast.
    """
    height, width = scene.shape
    owner = scene.owner
    n = (rotations[owner] @ scene.face_normal[..., None].to(rotations.dtype))[..., 0]  # (M, 3) camera frame
    offset = scene.face_offset.to(n.dtype) + (n * translations[owner]).sum(-1)
    cos = (n * scene.directions.to(n.dtype)).sum(-1)
    sign = torch.where(cos.detach() < 0, 1.0, -1.0).to(n.dtype)  # flips n to face the camera (n . d < 0)
    cos = torch.where(cos.abs() < _MIN_COS, -sign * _MIN_COS, cos)
    z = offset / cos
    points = z[:, None] * scene.directions.to(n.dtype)
    normals = n * sign[:, None]

    def scatter(values: torch.Tensor, channels: int) -> torch.Tensor:
        out = torch.zeros(height * width, channels, dtype=torch.float32)
        out = out.index_copy(0, scene.index, values.reshape(len(scene.index), channels).float())
        return out.reshape(height, width, channels) if channels > 1 else out.reshape(height, width)

    margin = None if scene.ir_margin is None else posed_geometry(scene.ir_margin, rotations, translations, albedo)
    return SensorGeometry(
        points=scatter(points, 3), normals=scatter(normals, 3), albedo=scatter(albedo[owner], 1),
        hit=scene.hit, shadow=scene.shadow, clean_depth=scatter(z, 1), ir_margin=margin,
    )  # fmt: skip
