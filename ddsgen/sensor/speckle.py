"""Laser speckle with the grain of the imaging optics, fixed to the scene.

A coherent (laser) projector lights an optically rough surface; the IR camera sees the
dots modulated by speckle: an interference pattern whose grain is set by the camera's
aperture (about the lens's point-spread function, 1-2 px on a Kinect V1) and which, for a
static scene and camera, does not change from frame to frame. Two things follow that a
fresh, independent draw per pixel and per frame gets wrong: neighbouring pixels of one dot
share their speckle factor (the dot is dimmed or brightened as a whole, its centre hardly
moves), and averaging frames of a static scene does not average the speckle away.

The model: a Gaussian random field band-limited by a Gaussian of sigma ``grain_px``
(white normal noise blurred and renormalised to unit variance), mapped through its normal
CDF and the Gamma quantile function so that every pixel's factor has exactly the
Gamma(shape, 1) marginal that Landau et al. 2016 fitted to a real Kinect (a Gaussian
copula). ``grain_px = 0`` gives the independent per-pixel draws of the paper's model.

The field is seeded by the scene: :func:`scene_seed` hashes the ray-cast geometry, so the
same static scene gives the same speckle in any frame, worker or process (:func:`scene_speckle`
draws it, memoised on the geometry).
"""

from __future__ import annotations

import ctypes
import functools
import hashlib
import math

import cv2
import numpy as np
import torch

from ddsgen.ckernel import load_exact_c_library
from ddsgen.tensor_memo import memoised

# Quantile table resolution (normal scores from -_Z_MAX to _Z_MAX); beyond it the table's ends
# are used (probability < 1e-9 per pixel).
_TABLE_SIZE = 4097
_Z_MAX = 6.0


@functools.lru_cache(maxsize=16)
def gamma_quantile_table(shape: float) -> tuple[np.ndarray, np.ndarray]:
    """(normal scores z, Gamma(shape, 1) quantiles at Phi(z)), both (_TABLE_SIZE,) float64.

    Built once per shape by bisection on the regularised lower incomplete gamma function
    (torch.special.gammainc), which is monotone in x.
    """
    z = torch.linspace(-_Z_MAX, _Z_MAX, _TABLE_SIZE, dtype=torch.float64)
    p = 0.5 * torch.erfc(-z / math.sqrt(2.0))
    a = torch.full_like(z, float(shape))
    lo = torch.zeros_like(z)
    hi = torch.full_like(z, float(shape) + 40.0 * math.sqrt(float(shape)) + 40.0)
    for _ in range(80):
        mid = 0.5 * (lo + hi)
        below = torch.special.gammainc(a, mid) < p
        lo = torch.where(below, mid, lo)
        hi = torch.where(below, hi, mid)
    return z.numpy(), (0.5 * (lo + hi)).numpy()


def correlated_normal(height: int, width: int, grain_px: float, rng: np.random.Generator) -> np.ndarray:
    """(H, W) float32 zero-mean, unit-variance Gaussian field with Gaussian correlation of sigma ``grain_px``.

    White noise blurred by a Gaussian kernel of sigma ``grain_px`` (reflecting borders), divided
    by the kernel's L2 norm so the variance stays 1. ``grain_px <= 0``: white noise.
    """
    white = rng.standard_normal(size=(height, width), dtype=np.float32)
    if grain_px <= 0:
        return white
    kernel = cv2.getGaussianKernel(2 * int(math.ceil(4 * grain_px)) + 1, grain_px, cv2.CV_64F).ravel()
    blurred = cv2.sepFilter2D(white, cv2.CV_32F, kernel, kernel, borderType=cv2.BORDER_REFLECT)
    return blurred / np.float32(np.sum(kernel**2))  # ||k (x) k||_2 = ||k||_2^2 for a separable kernel


def speckle_field(height: int, width: int, shape: float, grain_px: float, rng: np.random.Generator) -> np.ndarray:
    """(H, W) float32 speckle factors with the Gamma(shape, 1) marginal and the optics' grain.

    Args:
        shape: Gamma shape (Landau et al.: 4.54); the mean is ``shape``, the variance ``shape``.
        grain_px: correlation sigma of the field (camera px); 0 = independent per pixel.
        rng: the field's random generator (see :func:`scene_seed`).
    """
    normal = correlated_normal(height, width, grain_px, rng)
    _, quantiles = gamma_quantile_table(float(shape))
    table = quantiles.astype(np.float32)
    fast = _gamma_quantiles_c(normal, table)
    if fast is not None:  # the same factors in one C pass
        return fast
    # Linear interpolation on the table's uniform grid of normal scores (np.interp's search is 10x slower).
    position = np.clip(normal, np.float32(-_Z_MAX), np.float32(_Z_MAX))
    position += np.float32(_Z_MAX)
    position *= np.float32((_TABLE_SIZE - 1) / (2 * _Z_MAX))
    index = np.minimum(position.astype(np.int32), _TABLE_SIZE - 2)
    frac = position - index.astype(np.float32)
    low = np.take(table, index)  # np.take: several times faster than table[index] here, same values
    return low + (np.take(table, index + 1) - low) * frac


@functools.cache
def _library():
    p, q, f = ctypes.c_void_p, ctypes.c_int64, ctypes.c_float
    return load_exact_c_library("ddsgen", "speckle.c", "speckle", "numpy path",
                                {"ddsgen_gamma_quantiles": [p, q, f, f, p, q, p]})


def _gamma_quantiles_c(normal: np.ndarray, table: np.ndarray) -> np.ndarray | None:
    """:func:`speckle_field`'s table interpolation of the float32 scores ``normal`` in ddsgen/csrc/speckle.c, or None
    without the C library (or with ``DDSGEN_NO_C_KERNEL``)."""
    lib = _library()
    if lib is None:
        return None
    normal = np.ascontiguousarray(normal, dtype=np.float32)
    table = np.ascontiguousarray(table, dtype=np.float32)
    out = np.empty_like(normal)
    lib.ddsgen_gamma_quantiles(normal.ctypes.data, normal.size, float(np.float32(_Z_MAX)),
                               float(np.float32((_TABLE_SIZE - 1) / (2 * _Z_MAX))), table.ctypes.data, table.size,
                               out.ctypes.data)  # fmt: skip
    return out


def scene_seed(*arrays: torch.Tensor | np.ndarray) -> list[int]:
    """A seed for numpy's default_rng that depends only on the bytes of the given arrays.

    Used with the ray-cast geometry (e.g. hit points and hit mask), it makes the speckle a
    property of the scene: a static scene rendered in any frame by any worker gets the same field.
    """
    digest = hashlib.blake2b(digest_size=16)
    for array in arrays:
        a = array.detach().cpu().numpy() if isinstance(array, torch.Tensor) else np.asarray(array)
        digest.update(str(a.shape).encode())
        digest.update(np.ascontiguousarray(a).tobytes())
    raw = digest.digest()
    return [int.from_bytes(raw[i : i + 4], "little") for i in range(0, 16, 4)]


#: Speckle fields memoised per geometry object (its units and twins): a diagnosis simulates one frame hundreds of
#: times, and hashing its geometry and drawing the field cost ~11 % of a 640 x 480 simulation.
SCENE_SPECKLE_MEMO = 8


def scene_speckle(geometry, unit_salt: list[int], height: int, width: int, shape: float,
                  grain_px: float) -> np.ndarray:  # fmt: skip
    """(height, width) float32 speckle factors fixed to the scene: :func:`speckle_field` drawn from
    ``default_rng(scene_seed(geometry.points, geometry.hit) + unit_salt)``.

    Memoised on the ``geometry`` object (a :class:`~ddsgen.sensor.geometry.SensorGeometry`): an entry holds
    the very tensors it was drawn for and their version counters, so new tensors or an in-place change of the
    points or the hit mask draw anew. A geometry with a ``speckle_scene`` shows that geometry's field. The array
    returned may be shared: do not modify it.
    """
    if getattr(geometry, "speckle_scene", None) is not None:  # a re-estimated copy shows its scene's speckle
        geometry = geometry.speckle_scene
    points, hit = geometry.points, geometry.hit

    def draw() -> np.ndarray:
        rng = np.random.default_rng(scene_seed(points, hit) + list(unit_salt))
        return speckle_field(height, width, shape, grain_px, rng)

    key = (tuple(unit_salt), height, width, float(shape), float(grain_px))
    return memoised(geometry.__dict__.setdefault("_speckle_memo", {}), (points, hit), key, SCENE_SPECKLE_MEMO, draw)
