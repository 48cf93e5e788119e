"""Losses between a simulated frame and a real one (torch, differentiable in the simulation).

All terms are computed on one frame's comparison region (see
:mod:`ddsgen.realscan.simulate`) and are in **millimetres** (validity terms: rates x
:data:`VALIDITY_MM`), so they add up and read like depth errors.

* :func:`huber` -- the paper's robust penalty, ~e^2/(2 delta) below delta, ~|e| above.
* ``depth``: Huber of the depth error sim - real on pixels valid in both (clipped to
  +-:data:`CLIP_MM`), after a masked ``k x k`` local mean. Two scans of the same surface by
  the same sensor have independent noise; a per-pixel loss is minimised by a *noise-free*
  simulation (E|a - b| grows with the spread of either), so per-pixel fitting drives noise
  parameters to zero. The local mean keeps what is systematic (bias, scale, distortion,
  pixel locking over a surface) and averages the independent noise down by ~k; the clip
  bounds what one mismatched or flying pixel can add to a window.
* The window ``k`` (:func:`local_window`) spans a fixed viewing angle,
  :data:`LOCAL_WINDOW_DEG`, not a fixed number of pixels: "systematic" means "the same over a
  patch of the scene", and the disparity noise of a structured-light sensor is correlated
  over its matching block (9 px), so a 5-px window at 640 px keeps whole noise blobs -- at
  640 x 480 the gap between two noise draws of one sensor fell from 1.67 to 0.65 mm with a
  15-px window while the bias of a 0.3-px disparity offset stayed.
* ``gradient``: Sobel-gradient term. The roughness ``mean |Sobel(z - z_clean)|`` of sim
  and real is compared per depth bin (Huber of the difference) -- the distributional form
  of the paper's gradient loss, which matches the *amount* of depth noise and pixel locking
  rather than its (random) per-pixel values.
* ``validity``: squared difference of the local (k x k) valid rates of sim (soft validity,
  differentiable where the sensor's validity is) and real, on the region, priced at
  :data:`VALIDITY_MM`: a patch where one sensor has depth and the other has none costs like
  a gross depth error (a flying pixel), not like a few millimetres of noise.
* ``pixel`` (weight 0 by default): the paper's per-pixel Huber, for completeness.

The depth term counts only pixels nearer than the depth the sensor resolves (:func:`resolved_depth_m`:
beyond it one step of the output's disparity quantum is a larger depth step than :data:`CLIP_MM`,
so a pixel's error there is 0 or clipped, and the local mean says on which side of a level the noise
landed rather than how far the sensor is off). Such far surfaces still count in the gradient and
validity terms.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import cv2
import torch
import torch.nn.functional as F

from ddsgen.sensor.box_filter import box_mean, erode, opencv_can_filter
from ddsgen.tensor_memo import memoised

#: Huber threshold (mm).
HUBER_DELTA_MM = 5.0
#: Local-mean window of the depth and validity terms: this viewing angle (deg) ...
LOCAL_WINDOW_DEG = 1.5
#: ... and at least this many px (odd).
LOCAL_WINDOW = 5
#: Per-pixel depth errors are clipped to +- this (mm) before the local mean.
CLIP_MM = 50.0
#: A validity-rate difference of 1 costs like this depth error (mm).
VALIDITY_MM = 100.0
#: Depth bins of the roughness statistic (m).
ROUGHNESS_BIN_M = 0.25


def resolved_depth_m(fb_px_m: float, step_px: float) -> float:
    """Depth (m) up to which one disparity quantum of the output (``step_px``, px) is a depth step of at most
    :data:`CLIP_MM`: the step is z^2 step / (f b), so z = sqrt(CLIP_MM f b / step). Kinect V1 (f b = 572.41 px x
    0.075 m): 4.14 m at 1/8 px, 2.93 m at 1/4 px. ``fb_px_m``: focal length (px) times baseline (m)."""
    return math.sqrt(CLIP_MM / 1000.0 * fb_px_m / step_px)


def depth_compared(frame) -> torch.Tensor:
    """(H, W) bool: the pixels of ``frame``'s comparison region whose depth values count (the depth term, the
    per-pixel term, local patches): its region nearer than ``frame.resolved_depth_m`` (by the clean depth, so the
    same pixels for every model)."""
    return frame.region & (frame.clean_depth <= frame.resolved_depth_m)


def local_window(focal_px: float) -> int:
    """The local window (odd, px) spanning :data:`LOCAL_WINDOW_DEG` for a camera of focal length ``focal_px``
    (15 px for the Kinect's 580 px, :data:`LOCAL_WINDOW` below ~190 px)."""
    k = int(round(focal_px * math.tan(math.radians(LOCAL_WINDOW_DEG))))
    return max(LOCAL_WINDOW, k + 1 - k % 2)


@dataclass(frozen=True)
class LossWeights:
    """Weights of the loss terms (all terms are in mm)."""

    depth: float = 1.0
    gradient: float = 1.0
    validity: float = 1.0
    pixel: float = 0.0
    #: Fitting: on the support plane, the depth error's part that a plane shift or tilt explains is not
    #: evidence about the sensor (:func:`without_plane_pose`), and neither is its noise texture when the
    #: objects show enough of theirs (:func:`texture_pixels`). ``compare`` keeps both (False).
    plane_nuisance: bool = False


#: The weights ``fit`` uses: the support plane's pose is a nuisance (see :func:`without_plane_pose`).
FIT_WEIGHTS = LossWeights(plane_nuisance=True)


def snr_search_weights(plane_nuisance: bool = False) -> LossWeights:
    """The terms the 1-D SNR search (:func:`ddsgen.fit.fitting.search_snr`) and its uncertainty judge: validity
    and noise texture, no depth; ``plane_nuisance`` as the fit's own weights."""
    return LossWeights(depth=0.0, gradient=1.0, validity=1.0, plane_nuisance=plane_nuisance)


def huber(x: torch.Tensor, delta: float = HUBER_DELTA_MM) -> torch.Tensor:
    """Elementwise Huber penalty in the units of ``x``: x^2/(2 delta) for |x| <= delta, |x| - delta/2 beyond."""
    a = x.abs()
    return torch.where(a <= delta, 0.5 * x * x / delta, a - 0.5 * delta)


def masked_local_mean(x: torch.Tensor, mask: torch.Tensor, k: int = LOCAL_WINDOW,
                      support: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:  # fmt: skip
    """Mean of ``x`` over the masked pixels of each k x k window.

    ``support``: the mask's support (below) when already known (it is computed otherwise).

    Returns:
        (mean (H, W), support (H, W) = fraction of the window that is masked).
    """
    num = box_mean((x * mask.to(x.dtype))[None, None], k)[0, 0]
    if support is None:
        support = box_mean(mask.to(x.dtype)[None, None], k)[0, 0]
    return num / support.clamp_min(1e-6), support


_SOBEL_X = torch.tensor([[-1.0, 0.0, 1.0], [-2.0, 0.0, 2.0], [-1.0, 0.0, 1.0]]) / 8.0


def sobel(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(gx, gy) Sobel derivatives (per px, normalised) of an (H, W) image, replicate border.

    Without a gradient to carry (CPU), OpenCV's correlation computes the same (a convolution took ~12 ms at
    640 x 480, the hottest op of an evaluation)."""
    if opencv_can_filter(x):
        image = x.detach().numpy()
        return tuple(torch.from_numpy(cv2.filter2D(image, -1, kernel.numpy().astype(image.dtype),
                                                   borderType=cv2.BORDER_REPLICATE))
                     for kernel in (_SOBEL_X, _SOBEL_X.T))  # fmt: skip
    k = torch.stack([_SOBEL_X, _SOBEL_X.T])[:, None].to(x)
    g = F.conv2d(F.pad(x[None, None], (1, 1, 1, 1), mode="replicate"), k)[0]
    return g[0], g[1]


def roughness(depth_error_mm: torch.Tensor, mask: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-pixel |Sobel| magnitude of a depth error image and the pixels where it is defined."""
    gx, gy = sobel(torch.where(mask, depth_error_mm, torch.zeros_like(depth_error_mm)))
    return gx.abs() + gy.abs(), erode(mask)


def without_plane_pose(err_mm: torch.Tensor, frame, both: torch.Tensor) -> torch.Tensor:
    """The depth error (H, W, mm) with, on the support plane's pixels, its part affine in disparity removed.

    The table plane is not known: it was fitted to the real depth (:mod:`ddsgen.realscan.simulate`), and a
    plane stays a plane in (u, v, disparity) space, so any disparity error affine in (u, v) -- an
    offset, a tilt -- is explained as well by moving the plane as by the sensor (the plane's pose is a
    nuisance). On the plane's pixels (``both`` & instance 0) the error in disparity units, ``err / z^2``
    (f b cancels), minus its least-squares fit ``a + b u + c v`` is what the sensor must explain;
    the objects, placed by their ground-truth poses, keep their whole error. Differentiable (a 3 x 3 solve).

    The normal equations are summed over whole images under the plane's mask as matrix-vector products
    (boolean indexing costs a nonzero() and a gather per image: 10 ms a call at 640 x 480, a third of
    :func:`frame_loss`); the 3 x 3 system is solved in float64.
    """
    plane = both & (frame.instance == 0)
    if int(plane.sum()) < 50:
        return err_mm
    linear, quadratic = _affine_basis(*err_mm.shape, err_mm.dtype)
    on_plane = plane.reshape(-1)
    weight = on_plane.to(err_mm.dtype)
    n, su, sv = linear @ weight
    suu, suv, svv = quadratic @ weight
    normal = torch.stack([torch.stack([n, su, sv]), torch.stack([su, suu, suv]), torch.stack([sv, suv, svv])])
    # Off the plane z may be 0: the clamp keeps the division finite (a NaN would reach the gradient through where).
    z2 = (frame.real_depth.reshape(-1).to(err_mm.dtype) ** 2).clamp_min(1e-6)
    r = torch.where(on_plane, err_mm.reshape(-1).clamp(-CLIP_MM, CLIP_MM) / z2, 0.0)
    coef = torch.linalg.solve(normal.double(), (linear @ r).double()).to(err_mm.dtype)
    explained = torch.where(on_plane, (coef @ linear) * z2, 0.0)
    return err_mm - explained.reshape(err_mm.shape)


@functools.lru_cache(maxsize=8)
def _affine_basis(height: int, width: int, dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor]:
    """(3, H*W) rows 1, u, v and (3, H*W) rows u^2, u v, v^2 of every pixel (row-major; u = column / W,
    v = row / H): the least-squares plane's basis and its products. Shared, never written to."""
    v, u = torch.meshgrid(torch.arange(height, dtype=torch.float64) / height,
                          torch.arange(width, dtype=torch.float64) / width, indexing="ij")  # fmt: skip
    linear = torch.stack([torch.ones_like(u), u, v]).reshape(3, -1)
    quadratic = torch.stack([u * u, u * v, v * v]).reshape(3, -1)
    return linear.to(dtype), quadratic.to(dtype)


#: With ``plane_nuisance``, the noise texture is judged on the objects alone when they have this many pixels.
MIN_OBJECT_TEXTURE_PX = 200


def texture_pixels(both: torch.Tensor, frame, plane_nuisance: bool) -> torch.Tensor:
    """The pixels (H, W bool) whose noise texture (roughness) is compared: ``both``, or with ``plane_nuisance``
    its object pixels when there are at least :data:`MIN_OBJECT_TEXTURE_PX`.

    Why: the support plane is placed where the *input* sensor's disparity errors put it, and a slanted plane's
    quantised disparity is a staircase whose steps follow its slope, so its roughness depends on the plane's
    pose, not only on the sensor's noise. Measured (hidden device, 160 x 120, at its true SNR and distortion
    field): the plane's roughness 7-9 % higher in the rendered "real" frames than in the simulation, the
    objects' equal within 2 %; searched on all pixels, eta_c came out 15-19 % low, on the objects 3-13 %.
    """
    if not plane_nuisance or frame.plane is None:
        return both
    objects = both & (frame.instance > 0)
    return objects if int(objects.sum()) >= MIN_OBJECT_TEXTURE_PX else both


def masked_mean(x: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Mean of ``x`` over the pixels of ``mask`` (same shape): a masked sum, no boolean indexing (which costs a
    nonzero() and a gather per call). Differentiable in ``x``."""
    return torch.where(mask, x, torch.zeros_like(x)).sum() / mask.sum().clamp_min(1)


def binned_roughness_gap(r_sim: torch.Tensor, r_real: torch.Tensor, z: torch.Tensor, ok: torch.Tensor,
                         zero: torch.Tensor) -> torch.Tensor:  # fmt: skip
    """Pixel-weighted mean over depth bins (:data:`ROUGHNESS_BIN_M`, bins of >= 20 px) of the Huber of the
    difference of the mean roughness of sim and real (mm) over the pixels of ``ok``; ``zero`` when no bin has
    20 px. Inputs: (H, W) roughness maps (mm), clean depth ``z`` (m) and the bool mask ``ok``.

    The bins' roughness difference is summed in one scatter, not sim and real apart (a scatter over a whole
    image costs ~1.3 ms at 640 x 480; more on a real image, whose neighbours fall in the same bin)."""
    bins = torch.floor(torch.where(ok, z, torch.zeros_like(z)) / ROUGHNESS_BIN_M).long().reshape(-1)
    bins = bins - bins.min()
    weight = ok.reshape(-1).to(r_sim.dtype)
    count = torch.bincount(bins, weights=weight)
    difference = torch.zeros(count.numel(), dtype=r_sim.dtype, device=r_sim.device).index_add(
        0, bins, (r_sim - r_real).reshape(-1) * weight)
    used = count >= 20
    if not bool(used.any()):
        return zero
    n = count[used]
    per_bin = huber(difference[used] / n)
    return (n * per_bin).sum() / n.sum()


#: Real sides of the validity term memoised (:func:`_real_local_validity`); an entry holds two (H, W) images.
REAL_VALIDITY_MEMO = 32
_real_validity_memo: dict = {}


def _real_local_validity(real_valid: torch.Tensor, region: torch.Tensor, k: int,
                         dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor]:  # fmt: skip
    """``(support, rate)``, both (H, W): the share of each k x k window in ``region`` and the real valid rate over it
    (:func:`masked_local_mean` of ``real_valid``). Constant for a frame, whose real side the fit and the diagnosis
    compare with hundreds of simulations, so memoised (:func:`~ddsgen.tensor_memo.memoised`: new masks or an
    in-place change compute anew). Shared results: do not modify."""
    rate, support = memoised(_real_validity_memo, (real_valid, region), (k, dtype, str(region.device)),
                             REAL_VALIDITY_MEMO, lambda: masked_local_mean(real_valid.to(dtype), region, k))
    return support, rate


def frame_loss(sim, frame, weights: LossWeights = LossWeights()) -> dict[str, torch.Tensor]:
    """Loss terms of one simulated frame against its real scan.

    Args:
        sim: :class:`~ddsgen.sensor.depth_sensor.SensorOutput` (H, W).
        frame: :class:`~ddsgen.realscan.simulate.FrameData` of the same (H, W).
        weights: term weights.

    Returns:
        dict of 0-d tensors: ``depth``, ``gradient``, ``validity``, ``pixel`` (mm) and ``total``
        (the weighted sum). Terms with nothing to compare are 0.
    """
    region = frame.region
    real = frame.real_depth * 1000.0
    clean = frame.clean_depth * 1000.0
    simd = sim.depth * 1000.0
    measured = region & sim.valid & frame.real_valid
    both = measured & depth_compared(frame)
    k = local_window(frame.intrinsics.fx)
    zero = simd.sum() * 0.0
    terms = {"depth": zero, "gradient": zero, "validity": zero, "pixel": zero}
    if bool(both.any()):
        err = torch.where(both, simd - real, torch.zeros_like(simd))
        if weights.plane_nuisance and frame.plane is not None:
            err = torch.where(both, without_plane_pose(err, frame, both), err)
        local, support = masked_local_mean(err.clamp(-CLIP_MM, CLIP_MM), both, k)
        keep = both & (support >= 0.3)
        if bool(keep.any()):
            terms["depth"] = masked_mean(huber(local), keep)
        # Reported even at weight 0 (compare), but then without a graph to back-propagate through.
        terms["pixel"] = masked_mean(huber(err if weights.pixel else err.detach()), both)
    if bool(measured.any()):
        textured = texture_pixels(measured, frame, weights.plane_nuisance)
        r_sim, ok = roughness(simd - clean, textured)  # both roughness maps are defined on the same pixels
        r_real, _ = roughness(real - clean, textured)
        if bool(ok.any()):
            terms["gradient"] = binned_roughness_gap(r_sim, r_real, frame.clean_depth, ok, zero)
    if bool(region.any()):
        support, lr = _real_local_validity(frame.real_valid, region, k, simd.dtype)
        soft = sim.valid_soft.to(simd.dtype)
        ls, _ = masked_local_mean(soft, region, k, support)
        terms["validity"] = VALIDITY_MM * masked_mean((ls - lr) ** 2, region)
    terms["total"] = (weights.depth * terms["depth"] + weights.gradient * terms["gradient"]
                      + weights.validity * terms["validity"] + weights.pixel * terms["pixel"])  # fmt: skip
    return terms


#: The gap's terms: depth, gradient and validity at weight 1 (the per-pixel term is reported, not summed).
GAP_WEIGHTS = LossWeights(depth=1.0, gradient=1.0, validity=1.0, pixel=0.0)


def frame_gap_mm(sim, frame) -> float:
    """The headline gap (mm) of one simulated frame (a ``SensorOutput``) against its real frame (a
    :class:`~ddsgen.realscan.simulate.FrameData`), as :func:`ddsgen.realscan.gap.frame_gap` reports it, without its
    parts."""
    with torch.no_grad():
        total = float(frame_loss(sim, frame, GAP_WEIGHTS)["total"])
    return round(total, 4) if math.isfinite(total) else 0.0
