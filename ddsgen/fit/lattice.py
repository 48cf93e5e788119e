"""The device's disparity quantum, measured from the real depth's levels: what the depth shows directly is not fitted.

A structured-light device outputs disparity on a lattice of 2^-n px (Kinect V1: 1/8 px) and converts it with its own
f b, so its depth takes only the values z = f b / (k 2^-n). The levels show in a real frame whatever the scene: the
lattice coherence |mean exp(2 pi i (f b / s) / z)| over its valid pixels (:func:`~ddsgen.fit.fitting.lattice_coherence`)
is near 1 for the device's step s and near 0 for a coarser one, at the f b that puts the levels in phase.

:func:`measure_quantum` searches f b (the baseline within its fit bounds, the focal length held) for each level n in
:data:`LEVELS` and takes the *coarsest* level whose coherence reaches
:data:`~ddsgen.fit.fitting.LATTICE_MIN_COHERENCE` (a finer lattice holds every coarser one's levels, so it is coherent
too). The level measured on the fit frames is used only if the held-out frames, measured alone, give the same level;
otherwise the preset keeps its level, and the summary says why. The fit then judges the change with the rest on the
held-out gap (:mod:`ddsgen.fit.paired`).
"""

from __future__ import annotations


from ddsgen.fit.fitting import LATTICE_MIN_COHERENCE, baseline_grid, lattice_coherence
from ddsgen.realscan.simulate import FrameData

#: Sub-pixel levels n (lattice step 2^-n px) the measurement considers: 1/2 to 1/32 px.
LEVELS = (1, 2, 3, 4, 5)


def level_coherences(frames: list[FrameData], baseline_m: float, focal_scale: float = 1.0) -> dict[int, float]:
    """{n: highest lattice coherence over the baseline's fit bounds (:func:`~ddsgen.fit.fitting.baseline_grid`)} of
    the frames' real depth at step 2^-n px."""
    if not any(bool((f.region & f.real_valid).any()) for f in frames):
        return {n: 0.0 for n in LEVELS}
    out = {}
    for n in LEVELS:
        step = 2.0**-n
        grid, _ = baseline_grid(frames, baseline_m, step, focal_scale)
        out[n] = float(lattice_coherence(frames, grid / step, focal_scale).max())
    return out


def coarsest_coherent(coherences: dict[int, float]) -> int | None:
    """The coarsest level whose coherence reaches LATTICE_MIN_COHERENCE (None: no lattice in the depth)."""
    return next((n for n in sorted(coherences) if coherences[n] >= LATTICE_MIN_COHERENCE), None)


def measure_quantum(fit_frames: list[FrameData], held_out: list[FrameData], preset_level: int,
                    baseline_m: float, focal_scale: float = 1.0) -> dict:  # fmt: skip
    """The disparity quantum of the real depth, measured on the fit frames and confirmed on the held-out ones.

    Returns a dict: ``level`` (the level to use), ``preset_level``, ``measured_fit`` / ``measured_held_out`` (the
    coarsest coherent level of each part, None if none), ``coherence_fit`` / ``coherence_held_out`` ({n: coherence}),
    ``changed`` (bool) and ``reason`` (one sentence).
    """
    fit = level_coherences(fit_frames, baseline_m, focal_scale)
    held = level_coherences(held_out, baseline_m, focal_scale) if held_out else {}
    measured_fit, measured_held = coarsest_coherent(fit), coarsest_coherent(held) if held else None
    step = f"1/{2 ** preset_level} px"
    if measured_fit is None:
        changed, reason = False, f"no disparity lattice in the real depth (coherence < {LATTICE_MIN_COHERENCE:g}): " \
                                 f"the preset's {step} kept"  # fmt: skip
    elif measured_fit == preset_level:
        changed = False
        reason = f"the real depth lies on the preset's {step} lattice (coherence {fit[measured_fit]:.2f})"
    elif not held:
        changed, reason = False, (f"the fit frames show a 1/{2 ** measured_fit} px lattice, but no held-out frame "
                                  f"confirms it: the preset's {step} kept")  # fmt: skip
    elif measured_held != measured_fit:
        changed, reason = False, (f"the fit frames show a 1/{2 ** measured_fit} px lattice, the held-out frames do "
                                  f"not agree: the preset's {step} kept")  # fmt: skip
    else:
        changed = True
        reason = (f"measured from the depth levels: 1/{2 ** measured_fit} px (coherence {fit[measured_fit]:.2f} on the "
                  f"fit frames, {held[measured_fit]:.2f} held out; the preset's {step}: "
                  f"{held.get(preset_level, 0.0):.2f} held out)")  # fmt: skip
    return {"level": measured_fit if changed else preset_level, "preset_level": preset_level,
            "measured_fit": measured_fit, "measured_held_out": measured_held, "coherence_fit": fit,
            "coherence_held_out": held, "changed": changed, "reason": reason}  # fmt: skip
