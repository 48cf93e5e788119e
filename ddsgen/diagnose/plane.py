"""The support plane as a nuisance of the comparison: re-estimated under each sensor model.

The plane of :func:`ddsgen.fit.simulate.prepare_frames` is fitted to the real depth, so it already
contains any bias that keeps planes planar (a disparity offset, a depth scale error); a model with
that effect would apply it twice.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import torch

from ddsgen.fit.simulate import simulate


def replane(frame, sim, min_pixels: int = 200, clip_quantile: float = 0.1):
    """``frame`` with its support plane re-estimated under the model that produced ``sim``.

    The support plane of :func:`ddsgen.fit.simulate.prepare_frames` is fitted to the *real*
    depth, so it already contains every bias that keeps a plane a plane (a disparity offset:
    1/z shifts by a constant; a depth scale error) -- simulating a sensor that has the effect
    on that plane would apply it twice. The plane is a nuisance of the comparison, so it is
    re-estimated for each model: one Gauss-Newton step in inverse depth, where a plane is an
    affine function of the normalised pixel coordinates, moves it by the affine fit (trimmed
    least squares) of the inverse-depth residual 1/z_sim - 1/z_real over its pixels valid in
    both. Plane pixels get the new depth, points and normal; objects and masks are unchanged.

    Returns ``frame`` itself when it has no plane or too few plane pixels.
    """
    from ddsgen.fit.simulate import Plane

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
    a = np.stack([np.ones_like(r), xn[use].numpy(), yn[use].numpy()], 1)
    keep = np.ones(r.shape, bool)
    coef = np.zeros(3)
    for _ in range(3):  # trimmed least squares: drop the largest residuals of the previous fit
        coef = np.linalg.lstsq(a[keep], r[keep], rcond=None)[0]
        dev = np.abs(r - a @ coef)
        keep = dev <= np.quantile(dev, 1.0 - clip_quantile)
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
    xyz = torch.stack([xn.float() * z, yn.float() * z, z], -1)
    ray = -xyz / torch.linalg.vector_norm(xyz, dim=-1, keepdim=True).clamp_min(1e-9)
    cos = (ray * torch.tensor(new_n, dtype=torch.float32)).sum(-1).clamp(-1.0, 1.0).abs()
    hit = frame.hit & (ok | ~on_plane)
    incidence = torch.where(ok, torch.rad2deg(torch.acos(cos)), torch.where(hit, frame.incidence_deg, 90.0))
    plane = Plane(normal=new_n, offset=new_d, inliers=frame.plane.inliers, candidates=frame.plane.candidates)
    return dataclasses.replace(frame, geometry=_replaned_geometry(g, intr, n, d, new_n, new_d, on_plane),
                               incidence_deg=incidence.float(), plane=plane, clean_depth=clean, hit=hit)  # fmt: skip


def _normalised(intr, height: int, width: int, shift_px: float = 0.0):
    """(H, W) float64 normalised image coordinates x_n, y_n of a camera (principal point ``shift_px`` left)."""
    xn = ((torch.arange(width, dtype=torch.float64) - (intr.cx - shift_px)) / intr.fx)[None, :].expand(height, width)
    yn = ((torch.arange(height, dtype=torch.float64) - intr.cy) / intr.fy)[:, None].expand(height, width)
    return xn, yn


def _plane_depth(normal, offset: float, xn, yn, pixels):
    """(z float32 (H, W) m, ok bool (H, W)): the depth of the plane n.X + d = 0 along each pixel's ray, on
    ``pixels`` where it lies in front of the camera."""
    inv = -(normal[0] * xn + normal[1] * yn + normal[2]) / offset
    ok = pixels & (inv > 1e-6)
    return torch.where(ok, 1.0 / inv.clamp_min(1e-6), torch.zeros_like(inv)).float(), ok


def _replaned_geometry(g, intr, n, d, new_n, new_d, on_plane):
    """The sensor's geometry with its plane pixels moved from plane (n, d) to (new_n, new_d) (image frame)."""
    b_r = g.registration_offset_m
    if g.registration is None:
        pixels = g.hit & on_plane
    else:  # the IR view's plane pixels: on the old plane (in the IR frame its offset is d - n_x b_r), facing as it
        pixels = g.hit & ((g.points.double() @ torch.tensor(n) + (d - n[0] * b_r)).abs() < 1e-3)
        pixels &= (g.normals.double() @ torch.tensor(n)) > 0.999
    xn, yn = _normalised(intr, *g.shape, g.registration_shift_px)
    z, ok = _plane_depth(new_n, new_d - new_n[0] * b_r, xn, yn, pixels)
    points = g.points.clone()
    normals = g.normals.clone()
    xyz = torch.stack([xn.float() * z, yn.float() * z, z], -1)
    points[ok] = xyz[ok]
    normals[ok] = torch.tensor(new_n, dtype=torch.float32)
    clean = torch.where(ok, z, g.clean_depth)
    return dataclasses.replace(g, points=points, normals=normals, clean_depth=clean, hit=g.hit & (ok | ~pixels))


def replane_all(sensor, frames, seed: int) -> list:
    """Every frame re-planed under ``sensor`` (see :func:`replane`)."""
    out = []
    with torch.no_grad():
        for f in frames:
            out.append(replane(f, simulate(sensor, f, seed)) if f.plane is not None else f)
    return out


#: Validity effects that a lower SNR mimics (both drop the pixels of low signal first): the base fit lowers

def replaned(sensor, frames, seed: int, steps: int = 1) -> list:
    """``frames`` with their support planes re-estimated under ``sensor`` (``steps`` Gauss-Newton steps)."""
    for _ in range(steps):
        frames = replane_all(sensor, frames, seed)
    return frames
