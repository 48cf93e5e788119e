"""SensorGeometry: the ray-cast scene as the sensor sees it (torch tensors, constant w.r.t. the sensor's parameters).

Built once per frame from a :class:`ddsgen.raycast.RayHits` (:meth:`SensorGeometry.from_hits`) and consumed by
:class:`ddsgen.sensor.depth_sensor.DepthSensor`; ray casting is not differentiable, so the geometry is fixed while
the sensor's parameters are fitted.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

from ddsgen.sensor.registration import cropped_index


@dataclass
class SensorGeometry:
    """The ray-cast scene as seen by the sensor (torch, constant w.r.t. the sensor parameters).

    points (H, W, 3) m camera frame; normals (H, W, 3) unit, facing the camera;
    albedo (H, W); hit (H, W) bool; shadow (H, W) bool (projector cannot see the point);
    clean_depth (H, W) m (0 where no hit).
    ir_margin: the same for the (H, m) strip the IR camera sees beyond the right edge
    (:mod:`ddsgen.sensor.ir_margin`), or None: then the IR image is the depth image's grid.
    registration: for depth registered to an RGB camera (:mod:`ddsgen.sensor.registration`), (H, W) int64:
    each output pixel's flat index into this (IR-frame) image, -1 where it gets no depth; the fields above
    are then the IR camera's view, whose principal point is ``registration_shift_px`` left of the output's and
    whose centre is ``registration_offset_m`` left (-x) of the output camera's. None: the output image is the
    IR camera's.
    speckle_scene: the geometry whose speckle this one shows, or None (its own). A copy of a real scene whose
    support plane was re-estimated (:mod:`ddsgen.diagnose.plane`) is the same real surface: its speckle stays that
    of the scene, not of our estimate of the plane's pose.
    """

    points: torch.Tensor
    normals: torch.Tensor
    albedo: torch.Tensor
    hit: torch.Tensor
    shadow: torch.Tensor
    clean_depth: torch.Tensor
    ir_margin: "SensorGeometry | None" = None
    registration: torch.Tensor | None = None
    registration_shift_px: float = 0.0
    registration_offset_m: float = 0.0
    speckle_scene: "SensorGeometry | None" = None
    # The (H, W + m) geometry whose columns this one and its margin are (views), or None: with_ir_margin() returns
    # it instead of concatenating. Not an init field, so dataclasses.replace() drops it.
    _whole: "SensorGeometry | None" = field(default=None, init=False, repr=False, compare=False)

    @classmethod
    def from_hits(cls, hits, device="cpu", ir_margin=None, registration=None, registration_shift_px: float = 0.0,
                  registration_offset_m: float = 0.0, width: int | None = None) -> "SensorGeometry":  # fmt: skip
        """From a :class:`ddsgen.raycast.RayHits` (numpy arrays); ``ir_margin``: the RayHits of the strip
        beyond the right edge (:func:`ddsgen.sensor.ir_margin.cast_margin`), or None; ``registration``: the
        (H, W) index map of :func:`ddsgen.sensor.registration.registration_index`, or None.

        ``width``: ``hits`` is the image widened by its margin strip (:func:`ddsgen.sensor.ir_margin.cast_widened`,
        (H, W + m) with W = ``width``): the geometry is its first W columns and the margin the rest, both views
        of the same tensors (no copy; :meth:`with_ir_margin` returns the whole). Not with ``ir_margin``."""

        def t(a, dtype=torch.float32):
            return torch.as_tensor(np.ascontiguousarray(a)).to(device=device, dtype=dtype)

        extra = dict(registration=None if registration is None else t(registration, torch.int64),
                     registration_shift_px=float(registration_shift_px),
                     registration_offset_m=float(registration_offset_m))  # fmt: skip
        arrays = {"points": t(hits.points), "normals": t(hits.normals), "albedo": t(hits.albedo),
                  "hit": t(hits.hit, torch.bool), "shadow": t(hits.shadow, torch.bool), "clean_depth": t(hits.depth)}
        if width is None or width >= hits.depth.shape[1]:
            return cls(**arrays, ir_margin=None if ir_margin is None else cls.from_hits(ir_margin, device), **extra)
        if ir_margin is not None:
            raise ValueError("from_hits: a widened cast carries its own margin; ir_margin must be None")
        whole = cls(**arrays)
        margin = cls(**{k: a[:, width:] for k, a in arrays.items()})
        geometry = cls(**{k: a[:, :width] for k, a in arrays.items()}, ir_margin=margin, **extra)
        geometry._whole = whole
        return geometry

    @property
    def shape(self) -> tuple[int, int]:
        return tuple(self.clean_depth.shape)

    _FIELDS = ("points", "normals", "albedo", "hit", "shadow", "clean_depth")

    def cropped(self, x0: int, y0: int, width: int, height: int) -> "SensorGeometry":
        """The window (x0, y0, width, height); its IR margin is the next columns of this geometry's IR image
        (as many as there are, up to this geometry's margin width); a registered output keeps the sources
        inside the same window of the IR image."""
        whole = self.with_ir_margin()
        rows = slice(y0, y0 + height)
        part = {k: getattr(whole, k)[rows, x0 : x0 + width].contiguous() for k in self._FIELDS}
        m = 0 if self.ir_margin is None else self.ir_margin.shape[1]
        end = min(x0 + width + m, whole.shape[1])
        margin = None
        if end > x0 + width:
            margin = SensorGeometry(**{k: getattr(whole, k)[rows, x0 + width : end].contiguous() for k in self._FIELDS})
        registration = None
        if self.registration is not None:
            registration = cropped_index(self.registration, self.shape[1], x0, y0, width, height)
        return SensorGeometry(**part, ir_margin=margin, registration=registration,
                              registration_shift_px=self.registration_shift_px,
                              registration_offset_m=self.registration_offset_m)  # fmt: skip

    def with_ir_margin(self) -> "SensorGeometry":
        """The geometry of the whole IR image: this one and its margin strip side by side, (H, W + m)."""
        m = self.ir_margin
        if m is None:
            return self
        if self._whole is not None:
            return self._whole
        return SensorGeometry(**{k: torch.cat([getattr(self, k), getattr(m, k)], dim=1) for k in self._FIELDS})
