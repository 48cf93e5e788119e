"""The IR camera's lens distortion, and the reference image the device recorded through that lens.

A structured-light device does not match against its pattern at infinity: it matches each IR window against a
*reference image* it recorded once, of its own pattern on a plane ``reference_distance_m`` = Z0 away, through its
own IR lens (Konolige & Mihelich's description of the Kinect: "the pattern is memorized at a known depth"). The lens
distorts radially; in normalised image coordinates a pixel at distorted position (x_d, y_d) looks along the ray

    x_u = x_d (1 + k1 r_d^2),   y_u = y_d (1 + k1 r_d^2),   r_d^2 = x_d^2 + y_d^2      (k1 > 0: barrel)

(the "distorted -> undistorted" form: explicit in the direction the simulation needs it). What follows:

* **The IR image is formed on the distorted grid**: each IR pixel sees along its bent ray
  (:meth:`IRLens.distorted_view` resamples the pinhole ray cast there).
* **A surface at another depth than Z0 shows the reference's dots off the matcher's rows.** Between the reference
  plane and a surface at Z, a dot moves along a row of the *undistorted* image by f b (1/Z - 1/Z0); the lens
  curves those rows, so on the sensor the dot also moves across rows, by about 2 k1 x y f b (1/Z - 1/Z0) px: zero
  along the image's central cross, largest in the corners, growing with the distance from Z0. A 9 x 9 window whose
  dots sit a pixel off its row finds no match: the device loses depth in the corners, on surfaces far from Z0, in
  scene-shaped patches (not in rings). The reference images (:meth:`IRLens.reference_phases`) are the recorded
  plane's, so the matcher meets exactly this.
* **The device corrects the rest**: its factory calibration knows the lens, converts the matched shift into the
  disparity of the undistorted rays (:meth:`IRLens.to_undistorted`) and writes depth on the undistorted grid, so a
  matched pixel's depth is right and the output image is a pinhole image (labels and poses need no warp).

With ``ir_lens_k1`` = 0 the stage does nothing (the reference at Z0 is then the reference at infinity shifted by
f b / Z0, which the matcher's disparity already is).
"""

from __future__ import annotations

import dataclasses
import functools
from typing import ClassVar, NamedTuple

import torch

from ddsgen.sensor.geometry import SensorGeometry
from ddsgen.sensor.ir import straight_through_round
from ddsgen.sensor.matcher import MatchResult
from ddsgen.sensor.pattern import PatternField
from ddsgen.sensor.stages import Stage

#: Neighbouring hit points interpolated across a pixel must lie within this share of their depth of one another
#: (one surface); elsewhere (an edge) the nearest pixel's point is taken, so no point is made up between surfaces.
_SAME_SURFACE_SHARE = 0.02
#: Fixed-point iterations of the undistorted -> distorted map (each gains about the factor k1 r^2 < 0.1).
_DISTORT_ITERATIONS = 30


def undistorted_px(u: torch.Tensor, v: torch.Tensor, k1: float, fx: float, fy: float, cx: float, cy: float):
    """Where the pinhole image of the ray that distorted pixel (u, v) sees lies: (u_u, v_u), px (same shapes)."""
    x, y = (u - cx) / fx, (v - cy) / fy
    scale = 1.0 + k1 * (x * x + y * y)
    return cx + fx * x * scale, cy + fy * y * scale


def distorted_px(u: torch.Tensor, v: torch.Tensor, k1: float, fx: float, fy: float, cx: float, cy: float):
    """The inverse of :func:`undistorted_px`: the distorted pixel (u_d, v_d) whose ray the pinhole pixel (u, v) is."""
    xu, yu = (u - cx) / fx, (v - cy) / fy
    x, y = xu, yu
    for _ in range(_DISTORT_ITERATIONS):
        scale = 1.0 + k1 * (x * x + y * y)
        x, y = xu / scale, yu / scale
    return cx + fx * x, cy + fy * y


class LensMaps(NamedTuple):
    """Index maps between a distorted (H, W) IR grid and the undistorted (H, W_out) grid (:func:`_lens_maps`)."""

    source_u: torch.Tensor  # (H, W) float64: the pinhole px each distorted pixel looks at
    source_v: torch.Tensor
    back: torch.Tensor  # (H, W_out) int64: flat index of the distorted pixel nearest to each undistorted pixel's ray
    back_u: torch.Tensor  # (H, W_out) float64: that distorted pixel's column
    back_v: torch.Tensor  # its row
    back_ray_u: torch.Tensor  # the pinhole column of its ray


@functools.lru_cache(maxsize=16)
def _lens_maps(height: int, width: int, out_width: int, k1: float, fx: float, fy: float, cx: float,
               cy: float) -> LensMaps:  # fmt: skip
    """The :class:`LensMaps` of a camera, built once per process and camera."""
    v, u = torch.meshgrid(torch.arange(height, dtype=torch.float64), torch.arange(width, dtype=torch.float64),
                          indexing="ij")  # fmt: skip
    source_u, source_v = undistorted_px(u, v, k1, fx, fy, cx, cy)
    du, dv = distorted_px(u[:, :out_width], v[:, :out_width], k1, fx, fy, cx, cy)
    col = du.round().long().clamp_(0, width - 1)
    row = dv.round().long().clamp_(0, height - 1)
    back_u, back_v = col.double(), row.double()
    return LensMaps(source_u, source_v, row * width + col, back_u, back_v,
                    undistorted_px(back_u, back_v, k1, fx, fy, cx, cy)[0])  # fmt: skip


def _resample_geometry(seen: SensorGeometry, source_u: torch.Tensor, source_v: torch.Tensor) -> SensorGeometry:
    """``seen`` (H, W) sampled at pinhole positions (source_u, source_v) (H, W): hit points bilinearly on one
    surface, the nearest pixel's at edges; normals, albedo and the masks of the nearest pixel; no hit outside."""
    height, width = seen.shape
    inside = (source_u >= 0) & (source_u <= width - 1) & (source_v >= 0) & (source_v <= height - 1)
    u0 = source_u.floor().clamp(0, width - 2)
    v0 = source_v.floor().clamp(0, height - 2)
    fu = (source_u - u0).clamp(0, 1).float()[..., None]
    fv = (source_v - v0).clamp(0, 1).float()[..., None]
    c0, r0 = u0.long(), v0.long()
    nearest = source_v.round().long().clamp(0, height - 1) * width + source_u.round().long().clamp(0, width - 1)

    def flat(name):
        tensor = getattr(seen, name)
        return tensor.reshape(height * width, *tensor.shape[2:])

    corners = [r0 * width + c0, r0 * width + c0 + 1, (r0 + 1) * width + c0, (r0 + 1) * width + c0 + 1]
    points = flat("points")
    z = points[:, 2]
    hit = flat("hit")
    z4 = torch.stack([torch.where(hit[c], z[c], torch.zeros_like(z[c])) for c in corners])
    one_surface = (z4 > 0).all(0) & (z4.amax(0) - z4.amin(0) < _SAME_SURFACE_SHARE * z4.amax(0))
    top = points[corners[0]] * (1 - fu) + points[corners[1]] * fu
    bottom = points[corners[2]] * (1 - fu) + points[corners[3]] * fu
    blended = top * (1 - fv) + bottom * fv
    resampled_points = torch.where(one_surface[..., None], blended, points[nearest])
    resampled_hit = hit[nearest] & inside
    out = {
        "points": resampled_points * resampled_hit[..., None],
        "normals": flat("normals")[nearest],
        "albedo": flat("albedo")[nearest] * resampled_hit,
        "hit": resampled_hit,
        "shadow": flat("shadow")[nearest] & resampled_hit,
    }
    out["clean_depth"] = out["points"][..., 2].contiguous()
    return SensorGeometry(**out, speckle_scene=seen.speckle_scene)


@dataclasses.dataclass(frozen=True)
class IRLens(Stage):
    """The IR lens's radial distortion ``k1`` and the distance ``reference_distance_m`` (m) of the plane the device's
    reference image was recorded on (module docstring). A stage of :class:`~ddsgen.sensor.depth_sensor.DepthSensor`,
    between the ray cast and the IR image; inactive when ``k1`` is 0."""

    stage: ClassVar[str] = "ir_lens"
    keys: ClassVar[tuple[str, ...]] = ("ir_lens_k1", "reference_distance_m")

    k1: float
    reference_distance_m: float

    @classmethod
    def settings(cls, preset) -> dict:
        return {"k1": float(preset.ir_lens_k1), "reference_distance_m": float(preset.reference_distance_m)}

    @property
    def active(self) -> bool:
        return self.k1 != 0.0

    def usable(self, intrinsics, ir_shift_px: float, block: int) -> torch.Tensor:
        """(H, W) bool: the pixels of a window (a crop, a fit's tile; ``intrinsics`` its camera) the window's own IR
        image can match. A pixel's depth comes from the distorted pixel nearest to its ray; that pixel's matching
        window (``block`` px, plus one) must lie inside the window, and so must the rays its corners look along (the
        cast holds nothing beyond). ``ir_shift_px``: a registered device's IR principal point lies this far left of
        the output's. Without distortion: the window less a border of ``block // 2 + 1`` px."""
        width, height = int(intrinsics.width), int(intrinsics.height)
        fx, fy, cy = float(intrinsics.fx), float(intrinsics.fy), float(intrinsics.cy)
        cx = float(intrinsics.cx) - float(ir_shift_px)
        reach = block // 2 + 1
        v, u = torch.meshgrid(torch.arange(height, dtype=torch.float64), torch.arange(width, dtype=torch.float64),
                              indexing="ij")  # fmt: skip
        du, dv = distorted_px(u, v, self.k1, fx, fy, cx, cy) if self.active else (u, v)

        def inside(a, b):
            return (a >= 0) & (a <= width - 1) & (b >= 0) & (b <= height - 1)

        usable = torch.ones(height, width, dtype=torch.bool)
        for corner_u in (du - reach, du + reach):
            for corner_v in (dv - reach, dv + reach):
                usable &= inside(corner_u, corner_v)
                usable &= inside(*undistorted_px(corner_u, corner_v, self.k1, fx, fy, cx, cy))
        return usable

    def distorted_view(self, seen: SensorGeometry, fx: float, fy: float, cx: float, cy: float) -> SensorGeometry:
        """The IR camera's view on its distorted grid: ``seen`` (the pinhole cast of the IR image, (H, W + m),
        principal point (cx, cy) px) resampled where each distorted pixel's ray lands."""
        height, width = seen.shape
        maps = _lens_maps(height, width, width, self.k1, float(fx), float(fy), float(cx), float(cy))
        return _resample_geometry(seen, maps.source_u, maps.source_v)

    def reference_phases(self, field: PatternField, width: int, height: int, pad: int, n_sub: int, fx: float,
                         fy: float, cx: float, cy: float, baseline_m: float) -> torch.Tensor:  # fmt: skip
        """The recorded reference, as the matcher reads it: (2^n_sub, height, width + pad) float32.

        Column j of phase s holds what the device recorded at distorted pixel u = j - pad - s/S + f b / Z0 (the
        plane at Z0 seen through the lens), so that a shift of d px against it is the disparity d of the matcher's
        reference at infinity; without distortion it is that reference exactly."""
        shift = fx * baseline_m / self.reference_distance_m
        phases = 2**n_sub
        v, u = torch.meshgrid(torch.arange(height, dtype=torch.float64),
                              torch.arange(width + pad, dtype=torch.float64) - pad, indexing="ij")  # fmt: skip
        out = []
        for s in range(phases):
            on_plane_u, on_plane_v = undistorted_px(u - s / phases + shift, v, self.k1, fx, fy, cx, cy)
            # The plane point on that ray, seen from the projector b to the right: f b / Z0 px further left.
            out.append(field.sample((on_plane_u - shift).float(), on_plane_v.float()))
        return torch.stack(out).contiguous()

    def to_undistorted(self, result: MatchResult, images: tuple[torch.Tensor, ...], out_width: int, fx: float,
                       fy: float, cx: float, cy: float, baseline_m: float,
                       quantum_px: float | None = None) -> tuple[MatchResult, tuple]:  # fmt: skip
        """The match on the distorted (H, W + m) grid written on the undistorted (H, ``out_width``) grid, each
        pixel taking the distorted pixel nearest to its ray, with the disparity converted as the device's
        calibration does: a shift d matched at distorted pixel (u, v) pairs the rays of (u, v) and of the
        reference pixel (u - d + f b / Z0, v), so the disparity of the undistorted rays is
        f (x_u(u, v) - x_u(u - d + f b / Z0, v)) + f b / Z0, then put on the device's ``quantum_px`` lattice
        (straight-through; None: left for a later stage). ``images``: other (H, W + m) maps to carry along."""
        height, width = result.disparity.shape
        maps = _lens_maps(height, width, out_width, self.k1, float(fx), float(fy), float(cx), float(cy))

        def gather(tensor):
            return None if tensor is None else tensor.reshape(-1)[maps.back]

        fields = {f.name: gather(getattr(result, f.name)) for f in dataclasses.fields(result)}
        shift = fx * baseline_m / self.reference_distance_m
        d = fields["disparity"]
        dtype = d.dtype
        reference_u, _ = undistorted_px(maps.back_u.to(dtype) - d + shift, maps.back_v.to(dtype), self.k1, fx, fy, cx,
                                        cy)  # fmt: skip
        disparity = torch.where(d > 0, maps.back_ray_u.to(dtype) - reference_u + shift, d)
        if quantum_px is not None:
            disparity = straight_through_round(disparity / quantum_px) * quantum_px
        fields["disparity"] = disparity
        return MatchResult(**fields), tuple(gather(image) for image in images)


@functools.lru_cache(maxsize=8)
def recorded_reference(lens: IRLens, field: PatternField, width: int, height: int, pad: int, n_sub: int, fx: float,
                       fy: float, cx: float, cy: float, baseline_m: float) -> torch.Tensor:  # fmt: skip
    """:meth:`IRLens.reference_phases`, built once per process, lens, pattern field and camera (the device's
    recording is a constant of the device: it is made with the preset's focal length and baseline, not fitted ones)."""
    return lens.reference_phases(field, width, height, pad, n_sub, fx, fy, cx, cy, baseline_m)

