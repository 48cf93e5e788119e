"""The registration maps in C (ddsgen/csrc/registration.c): one pass over the pixels instead of a dozen whole-image
numpy passes (~20 ms of a 640 x 480 frame).

:mod:`ddsgen.sensor.registration` calls :func:`registration_index_c` and :func:`forward_index_c` first and runs its
numpy definition when they return None (no C compiler, or ``DDSGEN_NO_C_KERNEL``); both give the same maps bit for
bit (tests/test_registration.py).
"""

from __future__ import annotations

import ctypes
import functools

import numpy as np
import torch

from ddsgen.ckernel import c_source, load_c_library


@functools.cache
def _library():
    # No -march=native and no FMA contraction: numpy's float32 and float64 operations, one by one.
    flags = ["-O2", "-ffp-contract=off", "-fPIC", "-shared", "-std=gnu11"]
    lib = load_c_library(c_source("ddsgen", "csrc", "registration.c"), "registration", flags, "registration",
                         "numpy path")  # fmt: skip
    if lib is not None:
        p, q, f, d = ctypes.c_void_p, ctypes.c_int64, ctypes.c_float, ctypes.c_double
        lib.ddsgen_registration_index.argtypes = [p, p, p, p, p, q, q, f, f, f, f, f, f, p]
        lib.ddsgen_registration_index.restype = None
        lib.ddsgen_forward_registration_index.argtypes = [p, p, q, q, d, f, q, q, p, p]
        lib.ddsgen_forward_registration_index.restype = None
        lib.ddsgen_dense_splat_index.argtypes = [p, p, q, q, p]
        lib.ddsgen_dense_splat_index.restype = None
        lib.ddsgen_register_images.argtypes = [p, q, q, p, p, p]
        lib.ddsgen_register_images.restype = None
    return lib


def _contiguous(array: np.ndarray, dtype) -> np.ndarray:
    """``array`` as a C-contiguous ``dtype`` array; a bool array read as uint8 without a copy."""
    array = np.ascontiguousarray(array)
    if array.dtype == np.bool_ and dtype == np.uint8:
        return array.view(np.uint8)
    return np.ascontiguousarray(array, dtype=dtype)


def registration_index_c(points: np.ndarray, normals: np.ndarray, hit: np.ndarray, ir_depth: np.ndarray,
                         ir_hit: np.ndarray, b_r: float, fx: float, column_offset: float, slope_cap: float,
                         same_surface_rel: float, same_surface_abs: float) -> np.ndarray | None:  # fmt: skip
    """:func:`ddsgen.sensor.registration.registration_index` from its arrays: ``points``, ``normals`` float32
    (H, W, 3) and ``hit`` (H, W) of the output view, ``ir_depth`` float32 and ``ir_hit`` (H, W) of the IR view;
    ``column_offset`` = cx - registration_shift_px. (H, W) int64, or None without the C library."""
    lib = _library()
    if lib is None:
        return None
    height, width = hit.shape
    arrays = (_contiguous(points, np.float32), _contiguous(normals, np.float32), _contiguous(hit, np.uint8),
              _contiguous(ir_depth, np.float32), _contiguous(ir_hit, np.uint8))  # fmt: skip
    out = np.empty((height, width), dtype=np.int64)
    lib.ddsgen_registration_index(*(a.ctypes.data for a in arrays), height, width, b_r, fx, column_offset, slope_cap,
                                  same_surface_rel, same_surface_abs, out.ctypes.data)  # fmt: skip
    return out


def forward_index_c(valid: np.ndarray, depth: np.ndarray, shift_px: float, focal_offset_px_m: float, gap_px: int,
                    fill_rows: int, seen: np.ndarray | None) -> np.ndarray | None:  # fmt: skip
    """:func:`ddsgen.sensor.registration.forward_registration_index` from numpy arrays (``valid`` (H, W) bool,
    ``depth`` float32 (H, W) m, ``seen`` (H, W) int64 the ray-cast index, or None when ``fill_rows`` is 0).
    (H, W) int64, or None without the C library."""
    lib = _library()
    if lib is None:
        return None
    height, width = valid.shape
    valid_u8, depth_f = _contiguous(valid, np.uint8), _contiguous(depth, np.float32)
    seen_c = None if seen is None else _contiguous(seen, np.int64)
    out = np.empty((height, width), dtype=np.int64)
    lib.ddsgen_forward_registration_index(valid_u8.ctypes.data, depth_f.ctypes.data, height, width, float(shift_px),
                                          float(focal_offset_px_m), int(gap_px), int(fill_rows),
                                          None if seen_c is None else seen_c.ctypes.data, out.ctypes.data)  # fmt: skip
    return out


def dense_splat_index_c(index: np.ndarray, valid: np.ndarray) -> np.ndarray | None:
    """:func:`ddsgen.sensor.registration.dense_splat_index` from numpy arrays (``index`` (H, W) int64, ``valid``
    (H, W) bool, the IR image's). (H, W) int64, or None without the C library."""
    lib = _library()
    if lib is None:
        return None
    height, width = index.shape
    index_c, valid_u8 = _contiguous(index, np.int64), _contiguous(valid, np.uint8)
    out = np.empty((height, width), dtype=np.int64)
    lib.ddsgen_dense_splat_index(index_c.ctypes.data, valid_u8.ctypes.data, height, width, out.ctypes.data)
    return out


def register_images_c(images, index: torch.Tensor) -> tuple[torch.Tensor, ...] | None:
    """:func:`ddsgen.sensor.registration.register_images` in one C pass (each image at ``index``, zero where it is
    -1), or None where the torch definition runs: a gradient wanted, a tensor off the CPU or of another element
    size than 1, 4 or 8 bytes, no C library."""
    wants_grad = torch.is_grad_enabled() and any(image.requires_grad for image in images)
    if (wants_grad or index.device.type != "cpu" or index.dtype != torch.int64
            or any(image.device.type != "cpu" or image.element_size() not in (1, 4, 8) for image in images)):  # fmt: skip
        return None
    lib = _library()
    if lib is None:
        return None
    flat = index.contiguous()
    if flat.numel() and int(flat.max()) >= min(image.numel() for image in images):
        raise IndexError("register_images: an index lies outside the IR image")
    sources = [image.detach().contiguous() for image in images]
    outs = [torch.empty(index.shape, dtype=image.dtype) for image in images]
    pointers = ctypes.c_void_p * len(images)
    lib.ddsgen_register_images(flat.data_ptr(), flat.numel(), len(images), pointers(*(s.data_ptr() for s in sources)),
                               (ctypes.c_int64 * len(images))(*(s.element_size() for s in sources)),
                               pointers(*(o.data_ptr() for o in outs)))  # fmt: skip
    return tuple(outs)
