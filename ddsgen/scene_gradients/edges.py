"""Depth-edge term: the simulated objects' outlines pulled onto the real depth discontinuities.

Depth alone hardly pins a pose's in-plane slides and its turns about the viewing ray (or about a
symmetry axis): those move the surface along itself. The outline moves across the image instead. So:

1. the **real** depth's discontinuities: pixels whose depth is valid and whose neighbour is deeper by
   more than ``jump_m`` or invalid (the near side of an occluding edge, where a real outline is);
   their distance transform (px, truncated at ``max_px`` so far-off clutter edges do not pull);
2. the **simulated** outline: object pixels of the last ray cast whose neighbour is deeper by more
   than ``jump_m`` or empty (contact edges with the table, where nothing jumps, are left out), each
   kept as a *material* point of its triangle (object frame, from the cast's triangle id and
   barycentrics) so it moves with the pose;
3. the term: the material points posed and projected, the distance map sampled there (bilinear,
   differentiable in the projection), converted to metres at the point's depth (``px * z / f``), so
   it weighs like the depth residuals.

Between re-casts the outline is the same set of material points (the rim of a curved surface slides
over it as the object turns; the next re-cast catches up), as edge-based trackers do.
"""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import torch

from ddsgen.preset import Intrinsics

_NEIGHBOURS = ((0, 1), (0, -1), (1, 0), (-1, 0))



def occluding_edges(depth: np.ndarray, jump_m: float, reach_px: int = 12) -> np.ndarray:
    """(H, W) bool: the near side of occluding edges of a depth image (m, 0 = empty or invalid).

    A pixel is an edge when it is valid, a 4-neighbour is empty or deeper by more than ``jump_m``,
    and some pixel within ``reach_px`` is deeper by more than ``jump_m`` (so the far side of a hole --
    a projector shadow, an invalidated rim -- is not taken for an outline, its near side is).
    """
    depth = np.asarray(depth, dtype=np.float32)
    farthest = cv2.dilate(depth, np.ones((2 * reach_px + 1, 2 * reach_px + 1), np.uint8))
    return _step_down(depth, jump_m) & (farthest > depth + jump_m)


def _step_down(depth: np.ndarray, jump_m: float, at_holes: bool = True) -> np.ndarray:
    """(H, W) bool: valid pixels with a 4-neighbour deeper by more than ``jump_m`` (or, with
    ``at_holes``, empty: <= 0)."""
    height, width = depth.shape
    padded = np.pad(depth, 1, mode="edge")
    step = np.zeros(depth.shape, dtype=bool)
    for dy, dx in _NEIGHBOURS:
        other = padded[1 + dy: 1 + dy + height, 1 + dx: 1 + dx + width]
        step |= (other > depth + jump_m) | ((other <= 0) & at_holes)
    return step & (depth > 0)


def real_edge_distance(real_depth: np.ndarray, jump_m: float = 0.015, max_px: float = 6.0) -> np.ndarray:
    """Distance (px, float32 (H, W), truncated at ``max_px``) to the real depth's nearest occluding edge.

    Args:
        real_depth: (H, W) real depth (m, 0 = invalid).
        jump_m: a depth jump of more than this makes an edge (:func:`occluding_edges`).
        max_px: distances beyond are clipped (no pull from edges that far: clutter, other objects).
    """
    edges = occluding_edges(real_depth, jump_m)
    if not edges.any():
        return np.full(real_depth.shape, max_px, dtype=np.float32)
    distance = cv2.distanceTransform((~edges).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    return np.minimum(distance, max_px).astype(np.float32)


@dataclasses.dataclass
class OutlinePoints:
    """Material points on the simulated objects' occluding outlines (from one ray cast).

    points: (M, 3) float64 object-frame points (m); owner: (M,) int64 part index of each.
    """

    points: torch.Tensor
    owner: torch.Tensor

    def __len__(self) -> int:
        return int(self.owner.shape[0])


def outline_points(tensors, meshes, clean_depth: np.ndarray, n_objects: int, jump_m: float = 0.015,
                   seen: np.ndarray | None = None) -> OutlinePoints:  # fmt: skip
    """The occluding-outline pixels of the objects (not the background) as material points.

    Args:
        tensors: :class:`~ddsgen.scene_gradients.hits.SceneTensors` of the cast.
        meshes: the parts' meshes (object frame, m), in ``tensors``' owner order.
        clean_depth: (H, W) the cast's depth (m, 0 = no hit).
        n_objects: parts ``0 .. n_objects - 1`` are objects (the rest background: no outline).
        jump_m: an outline pixel has a neighbour deeper by more than this, or empty.
        seen: (H, W) bool or None: only outline pixels here count (the refinement passes the pixels where no real
            surface lies in front of the modelled one: an object's outline behind clutter the scene lacks would be
            pulled onto the clutter's edges).
    """
    height, width = tensors.shape
    owner = np.full(height * width, -1, dtype=np.int64)
    owner[tensors.index.numpy()] = tensors.owner.numpy()
    owner = owner.reshape(height, width)
    outline = _step_down(np.asarray(clean_depth, dtype=np.float32), jump_m) & (owner >= 0) & (owner < n_objects)
    if seen is not None:
        outline &= np.asarray(seen, dtype=bool)
    ys, xs = np.nonzero(outline)
    who = owner[ys, xs]
    face = tensors.triangle.numpy()[ys, xs].astype(np.int64)
    uv = tensors.barycentric.numpy()[ys, xs].astype(np.float64)
    points = np.zeros((len(ys), 3))
    for k in np.unique(who):
        sel = who == k
        corners = np.asarray(meshes[k].vertices, dtype=np.float64)[np.asarray(meshes[k].faces)[face[sel]]]
        u, v = uv[sel, :1], uv[sel, 1:]
        points[sel] = (1.0 - u - v) * corners[:, 0] + u * corners[:, 1] + v * corners[:, 2]
    return OutlinePoints(points=torch.from_numpy(points), owner=torch.from_numpy(who))


def edge_loss(outline: OutlinePoints, rotations: torch.Tensor, translations: torch.Tensor,
              distance: torch.Tensor, intrinsics: Intrinsics) -> torch.Tensor:  # fmt: skip
    """Mean distance (m) from the posed outline points to the real edges (differentiable in the poses).

    Args:
        outline: :func:`outline_points` of the last cast.
        rotations, translations: (N, 3, 3), (N, 3) the parts' current poses.
        distance: (H, W) float32 :func:`real_edge_distance` (px).
        intrinsics: the camera of the images.

    Returns:
        scalar: mean over the points of ``distance(projection) * z / f`` (m); 0 without points.
    """
    if len(outline) == 0:
        return (translations.sum() * 0.0).float()
    R, t = rotations[outline.owner], translations[outline.owner]
    X = (R @ outline.points[..., None].to(R.dtype))[..., 0] + t  # (M, 3) camera frame
    z = X[:, 2].clamp_min(1e-3)
    u = intrinsics.fx * X[:, 0] / z + intrinsics.cx
    v = intrinsics.fy * X[:, 1] / z + intrinsics.cy
    height, width = distance.shape
    # grid_sample's normalised coordinates (align_corners=True: -1 and 1 are the outer pixel centres)
    grid = torch.stack([2.0 * u / (width - 1) - 1.0, 2.0 * v / (height - 1) - 1.0], dim=-1).float()
    sampled = torch.nn.functional.grid_sample(distance[None, None], grid[None, None], mode="bilinear",
                                              padding_mode="border", align_corners=True)[0, 0, 0]  # fmt: skip
    return (sampled.double() * z / intrinsics.fx).mean()
