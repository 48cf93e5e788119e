"""An independent measurement model for the blind diagnose tests: scans that ddsgen's sensor did not make.

ddsgen's diagnosis was tuned on ddsgen's own renders; a test that hides an effect with ddsgen's effect classes
and finds it with the same classes only checks that the code agrees with itself. Here the "real" scans come from
a small structured-light measurement model written in numpy from the literature, sharing nothing with
``ddsgen.sensor`` but the ray-cast geometry (clean depth, surface normals, projector shadow):

* disparity ``d = f b / z`` of the clean depth (pinhole stereo with baseline b);
* Gaussian disparity noise (sigma in px, :data:`NOISE_PX` unless a device gives its own) and quantisation to 1/8 px
  (or a device's own step), as the Kinect V1 reports it (Khoshelham & Oude Elberink 2012: depth resolution
  ~ z^2 / (8 f b));
* no depth where the projector cannot light the surface (shadow), where nothing was hit, or beyond the range;
* the hidden effect, written from its textbook formula:

  - ``lens_distortion``: Brown's radial model of the IR lens, x_d = x_u (1 + k1 r_u^2) in normalised image
    coordinates; a pixel sees the scene point of its undistorted position (nearest sample: no mixing across
    edges), and the dot pattern it matches is displaced by f (x_d - x_u) along the baseline, which the
    disparity reads as d + f (x_d - x_u);
  - ``lens_warp``: the IR lens bends each pixel's ray while the depth along it stays right (the reference pattern
    was captured through the same lens, so the dots' displacement cancels): Fitzgibbon's one-parameter division
    model, a pixel at normalised x_d sees the scene point of x_u = x_d / (1 + lambda r_d^2) (nearest sample; beyond
    the cast image, its border) and measures that point's disparity unchanged -- the geometry is warped, no
    disparity is biased;
  - ``disparity_offset``: a mis-registered reference pattern, d + delta;
  - ``grazing_dropout``: no depth where the incidence angle exceeds a limit (dots smeared beyond recognition);
  - ``grazing_dropout_projector``: the same limit on the angle at the *projector* (between the surface normal and
    the ray to the projector, b to the camera's right): the light that does not come back is the projector's, and
    its angle is not the one ddsgen's library effect uses (the camera's);
  - ``edge_dropout``: no depth within w px of a depth discontinuity (|dz| > 5 % z between 4-neighbours);
  - ``row_bias`` (not in ddsgen's library): a vertical misalignment of projector and camera, a disparity bias
    growing with the square of the normalised row, d + a y^2 / y_max^2.
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
from scipy.ndimage import distance_transform_edt

SUBPIXEL = 8  # disparity steps per pixel
NOISE_PX = 0.05  # disparity noise (px)
RANGE_M = (0.4, 4.5)


def depth_discontinuities(z: np.ndarray, relative: float = 0.05) -> np.ndarray:
    """Pixels on either side of a 4-neighbour depth step larger than ``relative`` of the nearer depth (or hit/miss)."""
    edge = np.zeros(z.shape, bool)
    for axis in (0, 1):
        a, b = np.moveaxis(z, axis, 0)[1:], np.moveaxis(z, axis, 0)[:-1]
        near = np.minimum(np.where(a > 0, a, b), np.where(b > 0, b, a))
        step = ((np.abs(a - b) > relative * near) & (a > 0) & (b > 0)) | ((a > 0) != (b > 0))
        view = np.moveaxis(edge, axis, 0)
        view[1:] |= step
        view[:-1] |= step
    return edge


def measure(clean: np.ndarray, lit: np.ndarray, incidence_deg: np.ndarray, intr: dict, baseline_m: float,
            effect: dict | None, rng: np.random.Generator,
            projector_incidence_deg: np.ndarray | None = None, noise_px: float = NOISE_PX,
            subpixel: int = SUBPIXEL) -> np.ndarray:  # fmt: skip
    """Measured depth (m, 0 = invalid) of one frame: clean depth (H, W) m, lit (H, W) bool (hit and not in the
    projector's shadow), incidence (H, W) deg at the camera and (for ``grazing_dropout_projector``) at the projector,
    intrinsics dict (fx, fy, cx, cy), the hidden ``effect``; the device's disparity noise (px) and steps per pixel."""
    fx, fy, cx, cy = intr["fx"], intr["fy"], intr["cx"], intr["cy"]
    h, w = clean.shape
    fb = fx * baseline_m
    disparity = np.where(lit & (clean > 0), fb / np.maximum(clean, 1e-6), 0.0)
    name = effect["name"] if effect else None
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    xd, yd = (u - cx) / fx, (v - cy) / fy
    if name == "lens_distortion":
        xu, yu = xd.copy(), yd.copy()
        for _ in range(20):  # invert x_d = x_u (1 + k1 r_u^2) by fixed-point iteration
            factor = 1.0 + effect["k1"] * (xu * xu + yu * yu)
            xu, yu = xd / factor, yd / factor
        map_u, map_v = (xu * fx + cx).astype(np.float32), (yu * fy + cy).astype(np.float32)
        seen = cv2.remap(disparity.astype(np.float32), map_u, map_v, cv2.INTER_NEAREST, borderValue=0.0)
        disparity = np.where(seen > 0, seen + fx * (xd - xu), 0.0)
    elif name == "lens_warp":
        factor = 1.0 + effect["division_lambda"] * (xd * xd + yd * yd)
        map_u, map_v = (xd / factor * fx + cx).astype(np.float32), (yd / factor * fy + cy).astype(np.float32)
        # Beyond the cast image the scene goes on: the border pixel's value stands in for it.
        disparity = cv2.remap(disparity.astype(np.float32), map_u, map_v, cv2.INTER_NEAREST,
                              borderMode=cv2.BORDER_REPLICATE).astype(np.float64)  # fmt: skip
    elif name == "disparity_offset":
        disparity = np.where(disparity > 0, disparity + effect["offset_px"], 0.0)
    elif name == "row_bias":
        disparity = np.where(disparity > 0, disparity + effect["amplitude_px"] * (yd / np.abs(yd).max()) ** 2, 0.0)
    valid = disparity > 0
    if name == "grazing_dropout":
        valid &= incidence_deg <= effect["angle_deg"]
    elif name == "grazing_dropout_projector":
        valid &= projector_incidence_deg <= effect["angle_deg"]
    elif name == "edge_dropout":
        valid &= distance_transform_edt(~depth_discontinuities(clean)) > effect["width_px"]
    noisy = disparity + noise_px * rng.standard_normal(disparity.shape)
    quantised = np.round(noisy * subpixel) / subpixel
    depth = np.where(valid & (quantised > 0), fb / np.maximum(quantised, 1e-6), 0.0)
    return np.where((depth >= RANGE_M[0]) & (depth <= RANGE_M[1]), depth, 0.0).astype(np.float32)


def remeasure_folder(folder: Path, frames, baseline_m: float, effect: dict | None, seed: int,
                     noise_px: float = NOISE_PX, subpixel: int = SUBPIXEL) -> None:  # fmt: skip
    """Overwrite the depth files of a scan folder with :func:`measure` of its prepared ``frames`` (same order)."""
    from ddsgen.io.exr import write_exr
    from ddsgen.io.png import write_depth_png

    records = [json.loads(line) for line in (folder / "manifest.jsonl").read_text().splitlines()]
    for i, (record, frame) in enumerate(zip(records, frames)):
        g = frame.geometry
        lit = (g.hit & ~g.shadow).numpy()
        depth = measure(g.clean_depth.numpy().astype(np.float64), lit, frame.incidence_deg.numpy(),
                        record["intrinsics"], baseline_m, effect, np.random.default_rng([seed, i]),
                        projector_incidence(g.points.numpy(), g.normals.numpy(), baseline_m), noise_px,
                        subpixel)  # fmt: skip
        write_depth_png(folder / record["depth"], depth, record["depth_scale"])
        if record.get("depth_exr"):
            write_exr(folder / record["depth_exr"], depth)


def projector_incidence(points: np.ndarray, normals: np.ndarray, baseline_m: float) -> np.ndarray:
    """(H, W) angle (deg) between each surface normal and the ray from the point to the projector at (b, 0, 0) in
    the camera's frame (m); 90 where there is no surface (zero normal)."""
    to_projector = np.array([baseline_m, 0.0, 0.0]) - points
    length = np.maximum(np.linalg.norm(to_projector, axis=-1), 1e-9)
    cos = np.abs(np.sum(normals * to_projector, axis=-1)) / length
    return np.degrees(np.arccos(np.clip(cos, 0.0, 1.0)))
