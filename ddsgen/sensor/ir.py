"""IR image formation: what the IR camera captures when the projector lights the scene.

    signal = albedo * eta_c * Pi(proj(P)) * max(0, n.l) / ||P - t_p||_mm^2 * (1 - S)

where Pi is the pattern in units of LIT_DOT_INTENSITY / 255 per 8-bit value.
    I      = quantise(clip(signal * speckle + ambient + read_noise))

with the projector a pinhole of the camera's intrinsics at t_p = (+b, 0, 0) in the
camera frame (docs/model.md, "Camera and ray cast"), so a hit point P = (X, Y, Z) lands on projector pixel
u_p = fx (X - b) / Z + cx, v_p = fy Y / Z + cy. Sampling the pattern field there is
bilinear, so the image is differentiable in b and f. Noise constants follow Landau
et al. 2016 (Kinect V1): speckle ~ Gamma(shape, scale) multiplicative, read noise
~ N(mean, std) additive, in IR counts.

Noise draws come from numpy Generators, as unit-scale samples (Gamma(shape, 1),
N(0, 1)) that are then scaled by the (differentiable) noise parameters: bit-identical
on any worker, and reparameterised for gradients. The read noise is fresh per frame;
the speckle may carry the optics' grain and be fixed to the scene
(:mod:`ddsgen.sensor.speckle`).

Two fall-offs toward the image corners multiply the signal (off with exponent 0): the
projector's beam profile cos^m of the angle between the projector's axis and its ray
to the point, and the IR lens's vignetting cos^n of the camera ray's angle (n = 4 is
the natural cos^4 law of a thin lens).

Detector noise: read noise N(mean, std) and, optionally, photon shot noise whose variance
is the light in counts divided by the photo-electrons per count (the camera's gain).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from ddsgen.sensor.ir_kernel import render_ir_c
from ddsgen.sensor.pattern import PatternField
from ddsgen.sensor.speckle import speckle_field

# Intensity of a fully lit dot (8-bit pattern value 255) in the units eta_c multiplies.
# Chosen so that the paper's eta_c = 1.5e6 (counts * mm^2) reproduces Landau et al.'s
# fit to a real Kinect V1, I = 5.90e8 * cos / r_mm^2 counts for a lit dot:
# 5.90e8 / 1.5e6 = 393 per lit dot. (With 1 unit per 8-bit value, a dot at 3 m gave
# ~26 counts against 10.4 counts of read noise, and a plane at 3 m was only 50 % valid.)
LIT_DOT_INTENSITY = 5.90e8 / 1.5e6
PATTERN_UNIT = LIT_DOT_INTENSITY / 255.0


@dataclass
class IRNoise:
    """Unit-scale noise draws for one frame (constants w.r.t. the sensor parameters).

    speckle_unit: (H, W) ~ Gamma(shape, 1); read_unit: (H, W) ~ N(0, 1).
    """

    speckle_unit: torch.Tensor
    read_unit: torch.Tensor

    def columns(self, width: int) -> "IRNoise":
        """The draws of the first ``width`` columns (drawn for the IR image with its margin; see
        :meth:`ddsgen.sensor.depth_sensor.DepthSensor.draw_noise`)."""
        if self.read_unit.shape[1] == width:
            return self
        if self.read_unit.shape[1] < width:
            raise ValueError(f"noise drawn for {self.read_unit.shape[1]} columns, the IR image has {width}: "
                             "draw it with DepthSensor.draw_noise")  # fmt: skip
        return IRNoise(self.speckle_unit[:, :width], self.read_unit[:, :width])

    @classmethod
    def draw(cls, height: int, width: int, speckle_shape: float, rng: np.random.Generator, device="cpu",
             speckle_grain_px: float = 0.0, speckle: np.ndarray | None = None) -> "IRNoise":
        """Draw a frame's noise.

        Args:
            rng: the frame's generator (read noise; the speckle too unless ``speckle`` is given).
            speckle_grain_px: correlation sigma of the speckle (camera px); 0 = independent per pixel.
            speckle: (height, width) float32 speckle factors fixed to the scene
                (:func:`ddsgen.sensor.speckle.scene_speckle`; copied, not drawn).
        """
        if speckle is not None:
            speckle = np.array(speckle, dtype=np.float32)  # a copy: the scene's field may be memoised
        elif speckle_grain_px <= 0:
            speckle = rng.gamma(speckle_shape, 1.0, size=(height, width)).astype(np.float32)
        else:
            speckle = speckle_field(height, width, speckle_shape, speckle_grain_px, rng)
        read = rng.standard_normal(size=(height, width)).astype(np.float32)
        return cls(torch.from_numpy(speckle).to(device), torch.from_numpy(read).to(device))


def straight_through_round(x: torch.Tensor) -> torch.Tensor:
    """round(x) forward, identity gradient (the sensor's ADC)."""
    if not x.requires_grad:  # the same values (x + (round(x) - x) is exact, and -0.0 + 0.0 is +0.0), 2 passes fewer
        return torch.round(x).add_(0.0)
    return x + (torch.round(x) - x).detach()


def projector_coordinates(points: torch.Tensor, fx, fy, cx, cy, baseline) -> tuple[torch.Tensor, torch.Tensor]:
    """Projector pixel (u_p, v_p) of camera-frame points; projector at (+b, 0, 0), same orientation.

    Args:
        points: (H, W, 3) metres, camera frame; z > 0 where valid (z is clamped to avoid 1/0).
        fx, fy, cx, cy: intrinsics (px), floats or 0-d tensors.
        baseline: b (m), float or 0-d tensor.

    Returns:
        u_p, v_p: (H, W) projector pixel coordinates.
    """
    x, y, z = points.unbind(-1)
    z = z.clamp_min(1e-6)
    return fx * (x - baseline) / z + cx, fy * y / z + cy


def _power(base: torch.Tensor, exponent: float) -> torch.Tensor:
    """base ** exponent; whole exponents up to 8 by multiplication (a generic pow is exp(log) per element)."""
    if float(exponent).is_integer() and 1 <= exponent <= 8:
        out, square, n = None, base, int(exponent)
        while n:
            if n & 1:
                out = square if out is None else out * square
            n >>= 1
            if n:
                square = square * square
        return out
    return base**exponent


def render_ir(
    points: torch.Tensor,
    normals: torch.Tensor,
    albedo: torch.Tensor,
    lit: torch.Tensor,
    field: PatternField,
    fx,
    fy,
    cx,
    cy,
    baseline,
    emitted_intensity,
    ambient,
    speckle_scale,
    read_noise_mean,
    read_noise_std,
    noise: IRNoise | None,
    ir_bits: int = 10,
    quantise: bool = True,
    projector_falloff_exponent: float = 0.0,
    vignetting_exponent: float = 0.0,
    electrons_per_count: float = 0.0,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Simulate the IR camera image.

    Args:
        points: (H, W, 3) hit points (m, camera frame).
        normals: (H, W, 3) unit normals facing the camera.
        albedo: (H, W) IR reflectance in [0, 1].
        lit: (H, W) float {0, 1}: 1 where there is a hit that the projector sees (1 - shadow).
        field: the projector's pattern field.
        fx, fy, cx, cy, baseline: camera/projector geometry (px, m); tensors for gradients.
        emitted_intensity: eta_c (counts * mm^2 per unit of dot intensity; a lit dot is
            LIT_DOT_INTENSITY units).
        ambient: ambient IR level (counts), added to every pixel.
        speckle_scale, read_noise_mean, read_noise_std: noise parameters (counts).
        noise: unit noise draws (H, >= W: only the first W columns are used), or None for the noise-free image.
        ir_bits: ADC bit depth; the image is clipped to [0, 2^bits - 1] and, if ``quantise``,
            rounded to whole counts (straight-through gradient) when ``noise`` is given.
        quantise: round to whole counts (False only for finite-difference gradient checks).
        projector_falloff_exponent: m of the projector beam profile cos^m(angle off the projector's axis).
        vignetting_exponent: n of the IR lens's fall-off cos^n(angle off the camera's axis).
        electrons_per_count: photo-electrons per IR count; > 0 adds photon shot noise (variance
            = light / electrons_per_count counts^2) to the read noise; 0: read noise only.

    Returns:
        ir: (H, W) IR image in counts.
        clean_signal: (H, W) the noise-free projector signal (counts, before ambient), for
            effects and diagnostics.
    """
    fast = render_ir_c(points, normals, albedo, lit, field, fx, fy, cx, cy, baseline, emitted_intensity, ambient,
                       speckle_scale, read_noise_mean, read_noise_std, noise, ir_bits, quantise,
                       projector_falloff_exponent, vignetting_exponent, electrons_per_count, PATTERN_UNIT)  # fmt: skip
    if fast is not None:  # in C where no gradient is taken (ir_kernel: the same operations, exact square roots)
        return fast
    u_p, v_p = projector_coordinates(points, fx, fy, cx, cy, baseline)
    pattern = field.sample(u_p, v_p) * PATTERN_UNIT
    # The ray to the projector (b - x, -y, -z), by components: no (H, W, 3) temporaries.
    x, y, z_raw = points.unbind(-1)
    to_projector_x = baseline - x
    yy_zz = y * y + z_raw * z_raw
    distance_sq_m = (to_projector_x * to_projector_x + yy_zz).clamp_min(1e-12)
    distance_m = distance_sq_m.sqrt()
    nx, ny, nz = normals.unbind(-1)
    cos_incidence = ((nx * to_projector_x - ny * y - nz * z_raw) / distance_m).clamp_min(0.0)
    signal = albedo * emitted_intensity * pattern * cos_incidence / (distance_sq_m * 1e6) * lit
    z = z_raw.clamp_min(1e-6)
    if projector_falloff_exponent:
        signal = signal * _power((z / distance_m).clamp(0.0, 1.0), projector_falloff_exponent)
    if vignetting_exponent:
        camera_distance = (x * x + yy_zz).sqrt().clamp_min(1e-6)
        signal = signal * _power((z / camera_distance).clamp(0.0, 1.0), vignetting_exponent)
    if noise is None:
        return signal + ambient, signal
    noise = noise.columns(signal.shape[1])  # draws for a wider IR image (an IR margin) serve its first columns
    # Speckle is a property of the coherent laser light only; ambient light is incoherent.
    light = signal * (noise.speckle_unit * speckle_scale) + ambient
    noise_std = read_noise_std
    if electrons_per_count > 0:
        # Photon shot noise (Poisson in electrons, Gaussian at these counts) adds to the read noise's variance.
        noise_std = torch.sqrt(read_noise_std**2 + light.clamp_min(0.0) / electrons_per_count)
    ir = light + read_noise_mean + noise_std * noise.read_unit
    ir = ir.clamp(0.0, 2.0**ir_bits - 1.0)
    if quantise:
        ir = straight_through_round(ir)
    return ir, signal
