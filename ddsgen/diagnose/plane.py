"""The support plane as a nuisance of the comparison: re-estimated under each sensor model.

The plane of :func:`ddsgen.realscan.simulate.prepare_frames` is fitted to the real depth, so it already
contains any bias that keeps planes planar (a disparity offset, a depth scale error); a model with
that effect would apply it twice.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import torch

from ddsgen.realscan.simulate import simulate
from ddsgen.realscan.support_plane import Plane


def replane(frame, sim, min_pixels: int = 200, clip_quantile: float = 0.1):
    """``frame`` with its support plane re-estimated under the model that produced ``sim``.

    The support plane of :func:`ddsgen.realscan.simulate.prepare_frames` is fitted to the *real*
    depth, so it already contains every bias that keeps a plane a plane (a disparity offset:
    1/z shifts by a constant; a depth scale error) -- simulating a sensor that has the effect
    on that plane would apply it twice. The plane is a nuisance of the comparison, so it is
    re-estimated for each model: one Gauss-Newton step in inverse depth, where a plane is an
    affine function of the normalised pixel coordinates, moves it by the affine fit (trimmed
    least squares) of the inverse-depth residual 1/z_sim - 1/z_real over its pixels valid in
    both. Plane pixels get the new depth, points and normal; objects and masks are unchanged.

    Returns ``frame`` itself when it has no plane or too few plane pixels.
    """
    if frame.plane is None:
        return frame
    g = frame.geometry
    on_plane = frame.hit & (frame.instance == 0)
    use = on_plane & frame.region & sim.valid & frame.real_valid
    if int(use.sum()) < min_pixels:
        return frame
    intr = frame.intrinsics
    xn, yn = _normalised(intr, *frame.shape)
    r = (1.0 / sim.depth.double()[use] - 1.0 / frame.real_depth.double()[use]).numpy()
    coef = _trimmed_affine_fit(r, xn.expand(use.shape)[use].numpy(), yn.expand(use.shape)[use].numpy(), clip_quantile)
    n = np.asarray(frame.plane.normal, np.float64)
    d = float(frame.plane.offset)
    # Plane n.X + d = 0  <=>  1/z = alpha + beta x_n + gamma y_n with (beta, gamma, alpha) = -n / d.
    abc = -n / d - np.array([coef[1], coef[2], coef[0]])
    norm = float(np.linalg.norm(abc))
    new_n, new_d = -abc / norm, 1.0 / norm

    # The image's own depth and incidence, then the sensor's geometry (for a registered device, the IR camera's
    # view: its points are the image's moved by +b_r along x, its principal point registration_shift_px left).
    z, ok = _plane_depth(new_n, new_d, xn, yn, on_plane)
    clean = torch.where(ok, z, frame.clean_depth)
    # The angle between the viewing ray (x_n, y_n, 1) and the plane's normal (the depth cancels out).
    cos = ((new_n[0] * xn + new_n[1] * yn + new_n[2]) / torch.sqrt(xn * xn + yn * yn + 1.0)).abs().clamp(max=1.0)
    hit = frame.hit & (ok | ~on_plane)
    incidence = torch.where(ok, torch.rad2deg(torch.acos(cos)).float(), torch.where(hit, frame.incidence_deg, 90.0))
    plane = Plane(normal=new_n, offset=new_d, inliers=frame.plane.inliers, candidates=frame.plane.candidates)
    return dataclasses.replace(frame, geometry=_replaned_geometry(g, intr, n, d, new_n, new_d, on_plane),
                               incidence_deg=incidence.float(), plane=plane, clean_depth=clean, hit=hit)  # fmt: skip


def _trimmed_affine_fit(r: np.ndarray, xn: np.ndarray, yn: np.ndarray, clip_quantile: float) -> np.ndarray:
    """(3,) coefficients (c0, c_x, c_y) of r ~ c0 + c_x x_n + c_y y_n by least squares, refitted twice without the
    ``clip_quantile`` largest residuals of the previous fit. (N,) float64 inputs; 3x3 normal equations (the
    coordinates are O(1), so they are well conditioned; ~10x faster than lstsq on the (N, 3) matrix)."""
    keep = np.ones(r.shape, bool)
    coef = np.zeros(3)
    for _ in range(3):
        x, y, v = xn[keep], yn[keep], r[keep]
        sx, sy = x.sum(), y.sum()
        gram = np.array([[float(keep.sum()), sx, sy], [sx, x @ x, x @ y], [sy, x @ y, y @ y]])
        coef = np.linalg.solve(gram, np.array([v.sum(), x @ v, y @ v]))
        dev = np.abs(r - coef[0] - coef[1] * xn - coef[2] * yn)
        keep = dev <= np.quantile(dev, 1.0 - clip_quantile)
    return coef


def _normalised(intr, height: int, width: int, shift_px: float = 0.0):
    """Normalised image coordinates of a camera (principal point ``shift_px`` left), float64, broadcastable to
    (H, W): x_n (1, W) and y_n (H, 1) (whole-image arithmetic on them builds each (H, W) result once)."""
    xn = ((torch.arange(width, dtype=torch.float64) - (intr.cx - shift_px)) / intr.fx)[None, :]
    yn = ((torch.arange(height, dtype=torch.float64) - intr.cy) / intr.fy)[:, None]
    return xn, yn


def _plane_depth(normal, offset: float, xn, yn, pixels):
    """(z float32 (H, W) m, ok bool (H, W)): the depth of the plane n.X + d = 0 along each pixel's ray, on
    ``pixels`` where it lies in front of the camera."""
    inv = -(normal[0] * xn + normal[1] * yn + normal[2]) / offset
    ok = pixels & (inv > 1e-6)
    return torch.where(ok, inv.clamp_min(1e-6).reciprocal().float(), 0.0), ok


def _replaned_geometry(g, intr, n, d, new_n, new_d, on_plane):
    """The sensor's geometry with its plane pixels moved from plane (n, d) to (new_n, new_d) (image frame)."""
    b_r = g.registration_offset_m
    if g.registration is None:
        pixels = g.hit & on_plane
    else:  # the IR view's plane pixels: on the old plane (in the IR frame its offset is d - n_x b_r), facing as it
        # float32 is ample here: the points are ~1 m from the camera (rounding ~1e-7 m against 1e-3 m).
        n32 = torch.tensor(n, dtype=torch.float32)
        pixels = g.hit & ((g.points @ n32 + float(d - n[0] * b_r)).abs() < 1e-3) & ((g.normals @ n32) > 0.999)
    xn, yn = _normalised(intr, *g.shape, g.registration_shift_px)
    z, ok = _plane_depth(new_n, new_d - new_n[0] * b_r, xn, yn, pixels)
    moved = ok[..., None]
    points = torch.where(moved, torch.stack([xn.float() * z, yn.float() * z, z], -1), g.points)
    normals = torch.where(moved, torch.tensor(new_n, dtype=torch.float32), g.normals)
    clean = torch.where(ok, z, g.clean_depth)
    # The same real surface: the speckle stays the scene's (a new field per estimate would add noise to every
    # comparison between models judged on re-estimated planes).
    scene = g.speckle_scene if g.speckle_scene is not None else g
    return dataclasses.replace(g, points=points, normals=normals, clean_depth=clean, hit=g.hit & (ok | ~pixels),
                               speckle_scene=scene)  # fmt: skip


def replane_all(sensor, frames, seed: int) -> list:
    """Every frame re-planed under ``sensor`` (see :func:`replane`)."""
    out = []
    with torch.no_grad():
        for f in frames:
            out.append(replane(f, simulate(sensor, f, seed)) if f.plane is not None else f)
    return out


def replaned(sensor, frames, seed: int, steps: int = 1) -> list:
    """``frames`` with their support planes re-estimated under ``sensor`` (``steps`` Gauss-Newton steps)."""
    for _ in range(steps):
        frames = replane_all(sensor, frames, seed)
    return frames
