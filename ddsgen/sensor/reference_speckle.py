"""The speckle of the device's stored reference image (``reference_speckle_contrast``).

A PrimeSense device does not match its IR image against the ideal dot pattern: it matches against a reference
image of the pattern captured on a plane at a known distance when the unit was calibrated, kept in its memory
(Khoshelham & Oude Elberink 2012). That capture carries the laser speckle of the calibration plane and the camera
noise of that moment, fixed for the life of the unit and unrelated to any scene. To the matcher it is noise on
the reference side: white per reference pixel, of the same size at every depth and independent of the scene's
signal-to-noise ratio, and spread by the overlapping 9 x 9 windows into disparity errors that neighbouring pixels
share down the columns as well as along the rows.

Modelled as a multiplicative factor ``1 + c g`` on the reference images (clipped at 0), ``g`` a standard normal
value per reference pixel, drawn once per unit of the device. The sub-pixel phases are the stored image shifted
by s / S px, so each phase carries the same values shifted with it: phase s, column j holds the reference at
u = j - pad - s / S and takes the value of the stored pixel nearest to u.

Measured (docs/noise_study.md, session 46): c = 0.3 gives the renders the real frames' grain (row / column
correlation 0.60 / 0.43 pooled over 16 renders, IC-BIN 0.60 / 0.42; the LineMOD cat at its ground-truth pose
0.59 / 0.40 against the real 0.62 / 0.43), at the price of more isolated holes. Off (0) in the stock presets.
"""

from __future__ import annotations

import numpy as np
import torch

from ddsgen.sensor.pattern import unit_seed

#: numpy seed of unit 0's reference speckle (another unit: [seed, unit]): a property of the unit, the same in
#: every process.
REFERENCE_SPECKLE_SEED = 0x5EF5


def reference_speckle_factor(phases: int, height: int, columns: int, contrast: float, unit: int = 0) -> torch.Tensor:
    """The factor the stored reference's speckle puts on each reference phase.

    Args:
        phases: S = 2^n_sub sub-pixel phases.
        height, columns: the reference images' size (H, W + pad).
        contrast: c, the speckle's standard deviation relative to the pattern's intensity (0: none).
        unit: which unit of the device (each has its own calibration capture).

    Returns:
        (S, H, columns) float32 >= 0; all ones for ``contrast`` 0.
    """
    if contrast <= 0:
        return torch.ones(phases, height, columns)
    rng = np.random.default_rng(unit_seed(REFERENCE_SPECKLE_SEED, unit))
    # One value per stored pixel; column 0 is the pixel left of the first reference column (phases past 1/2).
    stored = rng.standard_normal((height, columns + 1)).astype(np.float32)
    # Past half a pixel, u = j - pad - s/S is nearest to stored pixel j - pad - 1.
    past_half = (2 * np.arange(phases) > phases)[:, None, None]
    factor = np.where(past_half, stored[None, :, :-1], stored[None, :, 1:])
    return torch.from_numpy(np.clip(1.0 + contrast * factor, 0.0, None).astype(np.float32))
