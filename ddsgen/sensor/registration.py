"""Depth registered to the RGB camera: the device writes its depth in the colour camera's image.

Kinect V1 datasets (LineMOD, TUM RGB-D, and the PrimeSense IC-BIN frames) ship *registered* depth: the
device maps each IR-frame depth pixel into the RGB camera, whose image the ground-truth poses and
intrinsics refer to. The IR camera sits ``registration_ir_offset_m`` = b_r to the RGB camera's left
(its -x), so a point at depth Z is ``f b_r / Z`` px further right in the IR image than in the RGB
image; with the two principal points ``registration_shift_px`` = s apart:

    u_ir = u_rgb + f b_r / Z - s,    v_ir = v_rgb   (a pure x offset keeps rows and z)

Two things follow that an unregistered simulation lacks. The IR frame's blind left columns
(``output_left_border_px`` = L) become a band that narrows with depth, first valid column
L + s - f b_r / Z; and RGB-view pixels the IR camera does not see (background just right of a near
object) have no depth. Measured on the real LineMOD cat frame: first valid column 24.4 - 15.6 / Z
(median column per 5 cm depth bin, 0.9-1.85 m, 11 bins within 1 px but one), so f b_r = 15.6 px m
(b_r = 27 mm at f = 572 px; the Kinect's IR-RGB spacing is about 25 mm) and s = 24.4 - 8 = 16.4 px, or
17.4 px with the dense splat (:func:`splat_fill_index`), which fills the band's last column.

Model (:func:`ir_view`, :func:`registration_index`): the output camera (the user's pose and
intrinsics) is the RGB camera; the sensor simulates the IR camera's view (its own ray cast, pose
shifted by -b_r along x, cx - s) and each output pixel takes the IR depth at round(u_ir) when its
surface point is what the IR camera sees there (same depth within half a pixel's slope), else no
depth. Depth is gathered, not interpolated: the device's quantised levels survive, and the output
is differentiable in the IR-frame depth. The real device forward-maps its measured depth; mapping
back with the ray-cast depth differs by the noise's effect on the shift (f b_r dZ / Z^2, 0.05 px at 1 m)
and, where the matcher carried a near surface past its edge, by where that carry shows: one band further
on, beside the far surface, instead of beside the near one. :func:`forward_registration_index`
(``registration_forward_gap_px`` > 0; kinect_v1) maps forward as the device does, and the
real LineMOD cat fits it better (docs/model.md, registration); the map back remains the default of a preset
without the key, and the ray-cast index still tells the forward map's fill across rows which pixels the IR camera
saw.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import torch

from ddsgen.preset import Intrinsics
from ddsgen.sensor import registration_kernel

#: Depth agreement of an output pixel's point and the IR pixel it maps to, besides half a pixel's slope:
#: a relative part (m/m) and an absolute part (m), for the float32 ray casts.
_SAME_SURFACE_REL = 0.004
_SAME_SURFACE_ABS = 0.001
#: The slope part's cap (m/m).
_SLOPE_CAP = 0.1


def is_registered(preset) -> bool:
    """True when the preset's device writes depth registered to an RGB camera."""
    return preset.registration_ir_offset_m > 0.0 or preset.registration_shift_px != 0.0


def output_projector_x_m(preset) -> float:
    """The projector's x in the output camera's frame (m): +baseline from the IR camera, which sits at -b_r."""
    return float(preset.baseline_m) - float(preset.registration_ir_offset_m)


def _ir_camera(intrinsics: Intrinsics, preset) -> tuple[np.ndarray, Intrinsics]:
    """``(cam_T_ir, ir_intrinsics)``: the IR camera's pose in the output camera's frame (moved by -b_r along x)
    and its intrinsics (same size and focal lengths, cx - s)."""
    cam_T_ir = np.eye(4)
    cam_T_ir[0, 3] = -float(preset.registration_ir_offset_m)
    return cam_T_ir, dataclasses.replace(intrinsics, cx=intrinsics.cx - float(preset.registration_shift_px))


def ir_view(scene, intrinsics: Intrinsics, preset):
    """``(ir_scene, ir_intrinsics)``: the scene as the IR camera sees it, and that camera's intrinsics."""
    cam_T_ir, ir_intrinsics = _ir_camera(intrinsics, preset)
    ir_scene = dataclasses.replace(scene, world_T_cam=np.asarray(scene.world_T_cam, dtype=np.float64) @ cam_T_ir)
    return ir_scene, ir_intrinsics


def ir_camera_record(intrinsics: Intrinsics, preset) -> dict | None:
    """The IR camera of a registered preset as a manifest entry: ``{"intrinsics": ..., "cam_T_ir": 4x4}`` (the IR
    camera's pose in the output camera's frame, m), or None when the output image is the IR camera's."""
    if not is_registered(preset):
        return None
    cam_T_ir, ir_intrinsics = _ir_camera(intrinsics, preset)
    return {"intrinsics": ir_intrinsics.as_dict(), "cam_T_ir": cam_T_ir.tolist()}


def registration_index(hits, ir_hits, intrinsics: Intrinsics, preset) -> np.ndarray:
    """(H, W) int64: for each output pixel, the flat index (v * W + u) of the IR-frame pixel whose depth it
    shows, or -1 where the IR camera does not see its surface point (or it has none).

    Args:
        hits: the output (RGB) camera's :class:`~ddsgen.raycast.RayHits`, (H, W).
        ir_hits: the IR camera's, (H, W), cast with :func:`ir_view`; or wider (widened by the IR margin strip,
            :func:`ddsgen.sensor.ir_margin.cast_widened`): its first W columns are read.
        intrinsics: the output camera's.
    """
    height, width = hits.depth.shape
    ir_depth_image, ir_hit_image = ir_hits.depth[:, :width], ir_hits.hit[:, :width]
    b_r, shift, fx = float(preset.registration_ir_offset_m), float(preset.registration_shift_px), intrinsics.fx
    fast = registration_kernel.registration_index_c(hits.points, hits.normals, hits.hit, ir_depth_image, ir_hit_image, b_r,
                                                    fx, intrinsics.cx - shift, _SLOPE_CAP, _SAME_SURFACE_REL,
                                                    _SAME_SURFACE_ABS)  # fmt: skip
    if fast is not None:  # the same map, in one pass (csrc/registration.c)
        return fast
    x, y = hits.points[..., 0] + np.float32(b_r), hits.points[..., 1]  # the point in the IR camera's frame
    z = np.where(hits.hit, hits.points[..., 2], np.float32(1.0))
    column = np.rint(np.float32(fx) * x / z + np.float32(intrinsics.cx - shift)).astype(np.int64)
    inside = hits.hit & (column >= 0) & (column < width)
    flat = (np.arange(height, dtype=np.int64) * width)[:, None] + np.clip(column, 0, width - 1)
    ir_depth, ir_hit = np.take(ir_depth_image.ravel(), flat), np.take(ir_hit_image.ravel(), flat)
    # Half a pixel along the surface changes the depth by |dZ/du| / 2 = Z^2 |n_x| / (2 fx |n . P_ir|), capped (a
    # surface seen edge-on is no reason to accept whatever the IR pixel shows; fmin also takes the cap for 0/0).
    n = hits.normals
    facing = np.abs(n[..., 0] * x + n[..., 1] * y + n[..., 2] * z)
    with np.errstate(divide="ignore", invalid="ignore"):
        half_pixel = z * z * np.abs(n[..., 0]) / (np.float32(2.0 * fx) * facing)
    tolerance = np.fmin(half_pixel, np.float32(_SLOPE_CAP) * z) + np.float32(_SAME_SURFACE_REL) * z + _SAME_SURFACE_ABS
    seen = inside & ir_hit & (np.abs(ir_depth - z) <= tolerance)
    return np.where(seen, flat, -1)


def cropped_index(index: torch.Tensor, full_width: int, x0: int, y0: int, width: int, height: int) -> torch.Tensor:
    """The window (x0, y0, width, height) of an (H, W) registration index, as indices into the same window of
    the IR image (-1 where its source lies outside the window)."""
    part = index[y0 : y0 + height, x0 : x0 + width]
    row, col = torch.div(part, full_width, rounding_mode="floor") - y0, torch.remainder(part, full_width) - x0
    inside = (part >= 0) & (row >= 0) & (row < height) & (col >= 0) & (col < width)
    return torch.where(inside, row * width + col, torch.full_like(part, -1))


def register(image: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """(H, W) IR-frame image -> (H, W) output image: ``image`` at ``index``, 0 (False) where the index is -1.
    Differentiable in ``image``."""
    return register_images((image,), index)[0]


def register_images(images, index: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """:func:`register` for several (H, W) images through the same ``index``, which is prepared once (a frame
    registers six maps: the clamp and the mask cost as much as a gather each). Without gradients, one C pass."""
    fast = registration_kernel.register_images_c(images, index)
    if fast is not None:
        return fast
    safe, inside = index.clamp(min=0), index >= 0
    return tuple(torch.where(inside, gather_flat(image, safe), torch.zeros((), dtype=image.dtype, device=image.device))
                 for image in images)  # fmt: skip


def gather_flat(image: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """``image`` read at flat indices ``index`` (any shape, every entry in range): ``torch.take``'s values and
    gradient, through ``index_select`` (2-5x faster on the CPU for whole images)."""
    return image.reshape(-1).index_select(0, index.reshape(-1)).reshape(index.shape)


def splat_fill_index(valid: torch.Tensor) -> torch.Tensor:
    """(H, W) int64: for each pixel of a registered image, the flat index of the pixel whose depth it shows after
    the device's dense registration, -1 where none. OpenNI's registration (Apply1080 with dense registration)
    writes each depth to its target pixel and to the target's west, north and north-west neighbours, so a pixel
    without depth of its own shows that of its lower-right, lower or right neighbour (the later writers, in
    that order): holes shrink by a pixel from their right and lower sides, and 1-px cracks close. Real LineMOD
    cat, one pixel outside the silhouette: 97-100 % valid on every side, carrying the cat's depth above 78 %,
    left 57 %, right 48 %, below 39 %.

    Args:
        valid: (H, W) bool, the registered image's valid pixels.
    """
    height, width = valid.shape
    index = torch.arange(height * width, device=valid.device).reshape(height, width)
    rows, cols = torch.nonzero(~valid, as_tuple=True)  # only the holes (a few % of the pixels) look around
    padded = torch.nn.functional.pad(valid, (0, 1, 0, 1))  # beyond the last row and column: no depth
    source = torch.full_like(rows, -1)
    for dy, dx in ((0, 1), (1, 0), (1, 1)):  # lowest priority first: a later writer wins
        r, c = rows + dy, cols + dx
        source = torch.where(padded[r, c], r * width + c, source)
    index[rows, cols] = source
    return index


def dense_splat_index(index: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """(H, W) int64: the registration ``index`` after the device's dense splat (:func:`splat_fill_index` on the
    registered validity, then ``index`` read through it): each output pixel's IR source, its lower-right, lower or
    right neighbour's where it has none of its own, -1 where none of them has one.

    Args:
        index: (H, W) int64 flat IR-image index of each output pixel, -1 where none.
        valid: (H, W) bool, the IR image's valid pixels.
    """
    fast = registration_kernel.dense_splat_index_c(index.cpu().numpy(), valid.cpu().numpy())
    if fast is not None:  # the same map, in one pass (csrc/registration.c): ~6 ms of a 640 x 480 frame less
        return torch.from_numpy(fast).to(index.device)
    fill = splat_fill_index(register(valid, index))
    return torch.where(fill >= 0, gather_flat(index, fill.clamp(min=0)), -1)


def forward_registration_index(valid: torch.Tensor, depth: torch.Tensor, shift_px: float, focal_offset_px_m: float,
                               gap_px: int, fill_rows: int = 0, seen: torch.Tensor | None = None) -> torch.Tensor:  # fmt: skip
    """(H, W) int64: the IR image's depth mapped forward into the output (RGB) image, as the device does: for each
    output pixel the flat index of the IR pixel whose depth it shows, -1 where none.

    Each valid IR pixel (u, v) with measured depth Z goes to column rint(u + s - f b_r / Z) of row v; where several
    land on one pixel the nearest wins (a z-buffer). A run of at most ``gap_px`` empty pixels between two written
    pixels whose IR sources are neighbours in one IR row takes the nearer one's source (a rasteriser's gap fill:
    resampling cracks and narrow bands close). Unlike :func:`registration_index` (back by the ray-cast geometry),
    the near surface the matcher carried past a depth edge lands next to that surface, and the band right of it
    (f b_r (1/Z_near - 1/Z_far) px) stays a hole between the two surfaces when wider than ``gap_px``: real
    registered frames keep bands of 6 px and more open at 98 % of such edges (docs/model.md, registration).

    Args:
        valid: (H, W) bool, the IR image's valid pixels.
        depth: (H, W) m, the IR image's measured depth (read only, no gradient: the result is a selection).
        shift_px: s, ``registration_shift_px``; focal_offset_px_m: f b_r (px m).
        gap_px: the longest run closed (0 = none).
        fill_rows: then, in each column, a run of at most this many empty pixels between two written pixels takes
            the nearer one's source where ``seen`` is -1 (the IR camera does not see the point) or a valid IR pixel
            (the IR camera saw it, but its measured depth, carried from a near surface, went elsewhere). A map by
            rows leaves such runs along a near-horizontal depth edge (a table's back edge above the floor): its
            band, f b_r (1/Z_near - 1/Z_far) px in every row, overlaps the next row's by a few pixels that no
            row's fill reaches, a dashed line of short horizontal holes. Real frames show none: their isolated
            dropouts are as often horizontal as vertical (IC-BIN 0.58 vertical), the map by rows alone 0.19.
        seen: (H, W) int64, the ray-cast :func:`registration_index` (needed when ``fill_rows`` > 0).
    """
    if fill_rows > 0 and seen is None:
        raise ValueError("forward_registration_index: fill_rows > 0 needs the ray-cast index `seen`")
    height, width = valid.shape
    seen_np = seen.cpu().numpy() if fill_rows > 0 else None
    fast = registration_kernel.forward_index_c(valid.cpu().numpy(), depth.detach().cpu().numpy(), shift_px,
                                               focal_offset_px_m, gap_px, fill_rows, seen_np)  # fmt: skip
    if fast is not None:  # the same map, in one pass (csrc/registration.c)
        return torch.from_numpy(fast).to(valid.device)
    z_all = depth.detach().cpu().numpy().reshape(-1)
    valid_flat = valid.cpu().numpy().reshape(-1)
    fillable = None
    if fill_rows > 0:  # the IR camera saw the point validly or not at all
        fillable = (seen_np < 0) | valid_flat[np.clip(seen_np, 0, None)]
    source = np.flatnonzero(valid_flat & (z_all > 0))
    rows, cols = np.divmod(source, width)
    z = z_all[source]
    target = np.rint(cols + shift_px - focal_offset_px_m / z).astype(np.int64)
    inside = (target >= 0) & (target < width)
    source, z, key = source[inside], z[inside], rows[inside] * width + target[inside]
    # A z-buffer in one pass: per output pixel the minimum of (Z's float32 bits, source) packed into an int64
    # (positive floats order as their bits; depths compared in float32, the sensor's precision; of equal depths
    # the first source in row-major order wins). 10 ms a frame where a stable sort of the keys took 20.
    packed = (z.astype(np.float32).view(np.int32).astype(np.int64) << 32) | source
    nearest = np.full(height * width, _EMPTY, dtype=np.int64)
    np.minimum.at(nearest, key, packed)
    index = np.where(nearest == _EMPTY, -1, nearest & 0xFFFFFFFF)
    if gap_px > 0:  # along rows, between IR-row neighbours
        _fill_short_runs(index, z_all, width, gap_px, sources_in_one_row=True)
    index = index.reshape(height, width)
    if fill_rows > 0:  # along columns, where fillable
        by_column = index.T.reshape(-1)  # a copy: columns end to end
        _fill_short_runs(by_column, z_all, height, fill_rows, sources_in_one_row=False)
        index = np.where(fillable, by_column.reshape(width, height).T, index)
    return torch.from_numpy(index).to(valid.device)


_EMPTY = np.iinfo(np.int64).max  # an output pixel no IR pixel landed on (before the gap fills)


def _fill_short_runs(flat: np.ndarray, depth: np.ndarray, line_length: int, max_run: int,
                     sources_in_one_row: bool) -> None:  # fmt: skip
    """In place on lines of ``line_length`` laid end to end in ``flat`` (IR flat indices, -1 = empty): a run of at
    most ``max_run`` empty entries between two written ones of one line takes the nearer one's source (``depth``:
    flat IR depth). ``sources_in_one_row``: only where the two sources are neighbours in one IR row (of
    ``line_length`` pixels). Works on the empty entries only (a few % of them)."""
    empty = np.flatnonzero(flat < 0)
    if not len(empty):
        return
    run_start = np.ones(len(empty), dtype=bool)
    run_start[1:] = np.diff(empty) != 1
    starts = np.flatnonzero(run_start)
    first, last = empty[starts], empty[np.append(starts[1:] - 1, len(empty) - 1)]
    a, b, gap = first - 1, last + 1, last - first + 1  # the written entries around each run, its length
    # One line on both sides (a run touching either end of ``flat`` has a = -1 or b = len: never one line).
    take = (gap <= max_run) & ((a // line_length) == (b // line_length))
    a, gap, source_a, source_b = a[take], gap[take], flat[a[take]], flat[b[take]]
    if sources_in_one_row:
        take = (np.abs(source_b - source_a) == 1) & ((source_a // line_length) == (source_b // line_length))
        a, gap, source_a, source_b = a[take], gap[take], source_a[take], source_b[take]
    if not len(a):
        return
    chosen = np.where(depth[source_a] <= depth[source_b], source_a, source_b)
    starts = np.repeat(a + 1, gap)
    offsets = np.arange(int(gap.sum())) - np.repeat(np.cumsum(gap) - gap, gap)
    flat[starts + offsets] = np.repeat(chosen, gap)


def ir_frame_validity(depth_m: np.ndarray, preset) -> np.ndarray:
    """(H, W) bool: the IR-frame pixels a registered depth image (H, W, m, 0 = invalid; in the preset's camera)
    shows, each valid output pixel (u, v, Z) marking IR pixel (round(u + f b_r / Z - s), v): the map
    :func:`registration_index` follows, inverted. The device's IR-frame border bands (the preset's
    ``output_*_border_px``) are then measured on these maps as on an unregistered device's
    (:func:`~ddsgen.sensor.output_window.measure_device_window`)."""
    depth = np.asarray(depth_m, dtype=np.float64)
    height, width = depth.shape
    rows, cols = np.nonzero(depth > 0)
    shift = preset.focal_px * preset.registration_ir_offset_m / depth[rows, cols] - preset.registration_shift_px
    ir_cols = np.rint(cols + shift).astype(np.int64)
    inside = (ir_cols >= 0) & (ir_cols < width)
    seen = np.zeros((height, width), dtype=bool)
    seen[rows[inside], ir_cols[inside]] = True
    return seen
