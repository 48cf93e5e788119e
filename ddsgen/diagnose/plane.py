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
    on_plane = g.hit & (frame.instance == 0)
    use = on_plane & frame.region & sim.valid & frame.real_valid
    if int(use.sum()) < min_pixels:
        return frame
    intr = frame.intrinsics
    h, w = frame.shape
    xn = ((torch.arange(w, dtype=torch.float64) - intr.cx) / intr.fx)[None, :].expand(h, w)
    yn = ((torch.arange(h, dtype=torch.float64) - intr.cy) / intr.fy)[:, None].expand(h, w)
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
    inv = abc[2] + abc[0] * xn + abc[1] * yn
    ok = on_plane & (inv > 1e-6)
    z = torch.where(ok, 1.0 / inv.clamp_min(1e-6), torch.zeros_like(inv)).float()
    points = g.points.clone()
    normals = g.normals.clone()
    xyz = torch.stack([xn.float() * z, yn.float() * z, z], -1)
    points[ok] = xyz[ok]
    normals[ok] = torch.tensor(new_n, dtype=torch.float32)
    clean = torch.where(ok, z, g.clean_depth)
    geometry = dataclasses.replace(g, points=points, normals=normals, clean_depth=clean,
                                   hit=g.hit & (ok | ~on_plane))  # fmt: skip
    ray = -points / torch.linalg.vector_norm(points, dim=-1, keepdim=True).clamp_min(1e-9)
    cos = (ray * normals).sum(-1).clamp(-1.0, 1.0).abs()
    incidence = torch.where(geometry.hit, torch.rad2deg(torch.acos(cos)), torch.full_like(cos, 90.0))
    plane = Plane(normal=new_n, offset=new_d, inliers=frame.plane.inliers, candidates=frame.plane.candidates)
    return dataclasses.replace(frame, geometry=geometry, incidence_deg=incidence.float(), plane=plane)


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
