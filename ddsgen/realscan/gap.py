"""How far is the simulation from a real sensor: the headline gap, its parts, the report (figures: compare_plots).

The headline metric (``gap``, millimetres)
------------------------------------------
For each frame, on its comparison region R (modelled geometry visible and plausible, see
:mod:`ddsgen.realscan.simulate`), with the simulation run at a fixed noise seed:

    gap_f = D_f + G_f + V_f                                    (mm)

* D_f -- **systematic depth error**: mean Huber (delta 5 mm) of the masked local mean of
  sim - real (clipped to +-50 mm) over pixels valid in both, in a window spanning 1.5 deg of
  view (15 px at 640 x 480, at least 5 px; :func:`ddsgen.realscan.losses.local_window`). The
  local mean keeps what is systematic (bias, scale, distortion, edge and shadow structure,
  pixel locking over a surface) and averages away what is independent from one scan to the
  next (noise, whose blobs are a matching block wide, and isolated mismatches), which no
  simulator can reproduce pixel for pixel.
* G_f -- **noise-texture mismatch**: Huber of the difference between the mean |Sobel| of
  (sim - clean) and of (real - clean), per 0.25 m depth bin, pixel-weighted.
* V_f -- **validity disagreement**: 100 mm x mean over R of the squared difference of the
  local valid rates (same window) of sim and real: where one sensor has depth and the other
  has none, the disagreement costs like a gross depth error.

D_f counts only the pixels of R nearer than the depth the sensor resolves
(:func:`ddsgen.realscan.losses.resolved_depth_m`: beyond it one disparity quantum is a depth step larger
than the 50 mm clip; Kinect V1 at 1/8 px: 4.14 m). There a depth error is 0 or clipped whatever
the sensor does, and its noise, growing as z^2, would outweigh the near surfaces' evidence; G_f and
V_f still count those pixels.

    gap = mean over frames of gap_f.

These are exactly the loss terms of :mod:`ddsgen.realscan.losses` (so ``fit`` minimises what
``compare`` reports). Two independent noise draws of the *same* sensor do not score 0:
``noise_floor`` is the gap between the simulation and twins of it
(:func:`~ddsgen.realscan.simulate.simulate_twin`: other units of the same model, each with its own noise
draw and its own scene-fixed speckle and dot positions, as the real unit has), averaged over at
least four units in all (one frame: four twins; four frames or more: one each), since one unit's
draw on one frame scatters by tens of percent; ``excess = gap - noise_floor`` is the part a
better model could remove.

Parts reported besides: bias (median) and spread (1.4826 MAD) of sim - real, and of real -
clean and sim - clean, binned by clean depth, incidence angle and image radius; validity
confusion (both valid / real only / sim only / neither) as fractions of R; and the local patches
(:mod:`ddsgen.realscan.local_patches`: where the real depth lies off by more than another unit's) with the gap, floor
and excess without them.
"""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import numpy as np
import torch

from ddsgen.atomic import atomic_write_text
from ddsgen.errors import InputError
from ddsgen.realscan.gap_report import BELOW_FLOOR, GapReport
from ddsgen.realscan.gap_report import round_or_none as _r
from ddsgen.realscan.local_patches import patch_gap, patch_line, patch_summary
from ddsgen.realscan.losses import GAP_WEIGHTS, depth_compared, frame_loss, local_window
from ddsgen.realscan.plots import plot_bins, plot_residuals
from ddsgen.realscan.realism import table as realism_table
from ddsgen.realscan.simulate import FrameData, simulate, simulate_twin, twin_draws

DEPTH_EDGES_M = (0.0, 0.6, 0.8, 1.0, 1.2, 1.4, 1.7, 2.0, 2.5, 3.0, 4.0, 8.0)
INCIDENCE_EDGES_DEG = (0.0, 15.0, 30.0, 45.0, 60.0, 75.0, 90.01)
RADIUS_EDGES = (0.0, 0.2, 0.4, 0.6, 0.8, 1.01)
MIN_BIN_PIXELS = 20


def _robust(values: np.ndarray) -> tuple[float, float]:
    if values.size == 0:
        return float("nan"), float("nan")
    med = float(np.median(values))
    return med, float(1.4826 * np.median(np.abs(values - med)))


def region_mask(frame: FrameData, region: str) -> torch.Tensor:
    if region == "objects":
        return frame.object_region
    if region == "all":
        return frame.region
    raise ValueError(f"region must be 'all' or 'objects', got {region!r}")


def _with_region(frame: FrameData, region: str) -> FrameData:
    return frame if region == "all" else dataclasses.replace(frame, region=region_mask(frame, region))


def _confusion(sim_valid, real_valid, region) -> dict:
    n = max(int(region.sum()), 1)
    return {
        "both_valid": _r(int((region & sim_valid & real_valid).sum()) / n),
        "real_only": _r(int((region & ~sim_valid & real_valid).sum()) / n),
        "sim_only": _r(int((region & sim_valid & ~real_valid).sum()) / n),
        "neither": _r(int((region & ~sim_valid & ~real_valid).sum()) / n),
    }


def frame_gap(sim, frame: FrameData, region: str = "all") -> dict:
    """Gap terms and parts of one simulated frame (see the module docstring)."""
    f = _with_region(frame, region)
    with torch.no_grad():
        terms = frame_loss(sim, f, GAP_WEIGHTS)
    mask = f.region
    both = depth_compared(f) & sim.valid & f.real_valid
    err = ((sim.depth - f.real_depth)[both] * 1000.0).numpy()
    bias, spread = _robust(err)
    return {
        "name": frame.name,
        "gap": _r(terms["total"]),
        "depth_mm": _r(terms["depth"]),
        "gradient_mm": _r(terms["gradient"]),
        "validity_mm": _r(terms["validity"]),
        "pixel_huber_mm": _r(terms["pixel"]),
        "bias_mm": _r(bias),
        "spread_mm": _r(spread),
        "pixels": int(mask.sum()),
        "confusion": _confusion(sim.valid, f.real_valid, mask),
        "pose_error_mm": _r(frame.pose_error_mm),
    }


def _bins(rows: dict[str, np.ndarray], key: str, edges) -> list[dict]:
    x = rows[key]
    out = []
    for lo, hi in zip(edges[:-1], edges[1:]):
        sel = (x >= lo) & (x < hi)
        if int(sel.sum()) < MIN_BIN_PIXELS:
            continue
        both = sel & rows["sim_valid"] & rows["real_valid"]
        entry = {"low": lo, "high": hi, "pixels": int(sel.sum()), "both_valid": int(both.sum()),
                 "real_valid_rate": _r(rows["real_valid"][sel].mean()),
                 "sim_valid_rate": _r(rows["sim_valid"][sel].mean())}  # fmt: skip
        for name, a, b in (("gap", "sim", "real"), ("real", "real", "clean"), ("sim", "sim", "clean")):
            bias, spread = _robust((rows[a][both] - rows[b][both]) * 1000.0)
            entry[f"{name}_bias_mm"], entry[f"{name}_spread_mm"] = _r(bias), _r(spread)
        out.append(entry)
    return out


def gap(sensor, frames: list[FrameData], *, region: str = "all", seed: int = 0, noise_floor: bool = True,
        keep_maps: bool = False, progress: bool = False, on_frame=None) -> GapReport:  # fmt: skip
    """The headline gap between ``sensor`` and the real scans of ``frames``, with its parts.

    Args:
        sensor: a :class:`~ddsgen.sensor.depth_sensor.DepthSensor` (not modified).
        frames: from :func:`ddsgen.realscan.simulate.prepare_frames`.
        region: ``"all"`` (every modelled, plausible pixel) or ``"objects"`` (only the objects').
        seed: noise seed of the simulation (the floor's twin: see :func:`~ddsgen.realscan.simulate.simulate_twin`).
        noise_floor: also compute the gap between the simulation and other units of ``sensor``: at least
            ``FLOOR_DRAWS`` unit draws in all (:func:`~ddsgen.realscan.simulate.twin_draws` per frame).
        keep_maps: keep per-frame depth maps in ``GapReport.maps`` (for residual plots).
        progress: show a progress bar.
        on_frame: called as ``on_frame(frame, sim, patches)`` (FrameData, SensorOutput, (H, W) bool mask of the
            local patches or None without the floor) after each frame's simulations, to save or draw it without
            keeping every frame in memory.

    Returns:
        :class:`GapReport`.
    """
    from tqdm import tqdm

    if region == "objects" and not any(bool(f.object_region.any()) for f in frames):
        raise InputError(f"--region objects: no annotated object is visible in any of the {len(frames)} frame(s) "
                         f"({frames[0].name}{', ...' if len(frames) > 1 else ''}): check the poses")  # fmt: skip
    per_frame, floors, maps, patches = [], [], [], []
    objects_only = []  # with region "all": (gap, floor) of the annotated objects alone, per frame that shows one
    draws = twin_draws(len(frames))
    rows = {k: [] for k in ("depth", "incidence", "radius", "sim", "real", "clean", "sim_valid", "real_valid")}
    totals = {"both_valid": 0, "real_only": 0, "sim_only": 0, "neither": 0}
    n_total = 0
    with torch.no_grad():
        for frame in tqdm(frames, desc="compare", unit="frame", disable=not progress, leave=False):
            sim = simulate(sensor, frame, seed)
            per_frame.append(frame_gap(sim, frame, region))
            if noise_floor:
                floors.append([])
                others = [simulate_twin(sensor, frame, seed, draw) for draw in range(draws)]
                for other in others:
                    twin = dataclasses.replace(frame, real_depth=other.depth, real_valid=other.valid)
                    floors[-1].append(frame_gap(sim, twin, region)["gap"] or 0.0)
                per_frame[-1]["noise_floor"] = _r(np.mean(floors[-1]))
                patches.append(patch_gap(sim, _with_region(frame, region), others, local_window(frame.intrinsics.fx)))
                if region == "all" and bool(frame.object_region.any()):
                    objects_only.append(_objects_only(sim, frame, others))
            if on_frame is not None:
                on_frame(frame, sim, patches[-1].patches.mask if noise_floor else None)
            mask = region_mask(frame, region)
            rows["depth"].append(frame.clean_depth[mask].numpy())
            rows["incidence"].append(frame.incidence_deg[mask].numpy())
            rows["radius"].append(frame.radius[mask].numpy())
            rows["sim"].append(sim.depth[mask].numpy())
            rows["real"].append(frame.real_depth[mask].numpy())
            rows["clean"].append(frame.clean_depth[mask].numpy())
            rows["sim_valid"].append(sim.valid[mask].numpy())
            rows["real_valid"].append(frame.real_valid[mask].numpy())
            n = int(mask.sum())
            for key, value in per_frame[-1]["confusion"].items():
                totals[key] += (value or 0.0) * n
            n_total += n
            if keep_maps:
                maps.append({"name": frame.name, "sim": sim.depth.numpy().copy(), "real": frame.real_depth.numpy(),
                             "sim_valid": sim.valid.numpy().copy(), "region": mask.numpy()})  # fmt: skip
    cat = {k: np.concatenate(v) if v else np.zeros(0) for k, v in rows.items()}
    both = cat["sim_valid"] & cat["real_valid"] if n_total else np.zeros(0, bool)
    bias, spread = _robust((cat["sim"][both] - cat["real"][both]) * 1000.0) if n_total else (float("nan"),) * 2
    parts = {
        "depth_mm": _r(np.mean([f["depth_mm"] or 0.0 for f in per_frame])),
        "gradient_mm": _r(np.mean([f["gradient_mm"] or 0.0 for f in per_frame])),
        "validity_mm": _r(np.mean([f["validity_mm"] or 0.0 for f in per_frame])),
        "bias_mm": _r(bias),
        "spread_mm": _r(spread),
        "confusion": {k: _r(v / max(n_total, 1)) for k, v in totals.items()},
        "pixels": n_total,
        "bins": {
            "depth_m": _bins(cat, "depth", DEPTH_EDGES_M),
            "incidence_deg": _bins(cat, "incidence", INCIDENCE_EDGES_DEG),
            "radius": _bins(cat, "radius", RADIUS_EDGES),
        },
    }
    headline = float(np.mean([f["gap"] or 0.0 for f in per_frame])) if per_frame else float("nan")
    floor_draws = [float(v) for v in np.mean(floors, axis=0)] if floors else []
    floor = float(np.mean(floor_draws)) if floors else float("nan")
    objects = None
    if objects_only:
        object_gap, object_floor = (float(np.mean(v)) for v in zip(*objects_only))
        objects = {"gap": _r(object_gap), "noise_floor": _r(object_floor), "excess": _r(object_gap - object_floor),
                   "frames": len(objects_only)}  # fmt: skip
    return GapReport(gap=headline, noise_floor=floor, frames=per_frame, parts=parts, region=region, maps=maps,
                     noise_floor_draws=floor_draws, local=patch_summary(patches, headline, floor) if patches else None,
                     objects=objects)  # fmt: skip


def _objects_only(sim, frame: FrameData, others) -> tuple[float, float]:
    """(gap, noise floor) of one frame on its annotated objects' pixels alone (mm), from the simulation and the
    twins already made for the whole region."""
    floor = []
    for other in others:
        twin = dataclasses.replace(frame, real_depth=other.depth, real_valid=other.valid)
        floor.append(frame_gap(sim, twin, "objects")["gap"] or 0.0)
    return frame_gap(sim, frame, "objects")["gap"] or 0.0, float(np.mean(floor))


# ------------------------------------------------------------------------------------------ output


def table(report: GapReport, title: str = "") -> str:
    """A short plain-text table of the headline and its parts."""
    p = report.parts
    c = p["confusion"]
    lines = [title] if title else []
    lines += lead_lines(report)
    draws = report.noise_floor_draws
    over = f" over {len(draws)} units: {min(draws):.2f}-{max(draws):.2f}" if len(draws) > 1 else ""
    lines += [
        f"gap ({report.region} region)       {report.gap:8.2f} mm   (noise floor {report.noise_floor:.2f} mm{over}; "
        f"excess {report.excess:.2f} mm)",
    ]
    if report.excess < 0:
        lines.append("  " + BELOW_FLOOR)
    if report.local:
        lines.append(patch_line(report.local))
    lines += [
        f"  systematic depth D     {p['depth_mm']:8.2f} mm",
        f"  noise texture    G     {p['gradient_mm']:8.2f} mm",
        f"  validity         V     {p['validity_mm']:8.2f} mm",
        f"sim - real: bias {_mm(p['bias_mm'], '+.2f')}, spread {_mm(p['spread_mm'], '.2f')} over {p['pixels']} px",
        f"validity: both {c['both_valid']:.3f}  real only {c['real_only']:.3f}  sim only {c['sim_only']:.3f}  "
        f"neither {c['neither']:.3f}",
        "depth bin (m)   px     bias   spread  real-valid sim-valid",
    ]
    for b in p["bins"]["depth_m"]:
        lines.append(f"  {b['low']:.1f}-{b['high']:.1f}  {b['pixels']:7d} {_f(b['gap_bias_mm']):>7} "
                     f"{_f(b['gap_spread_mm']):>7}   {b['real_valid_rate']:.3f}     {b['sim_valid_rate']:.3f}")  # fmt: skip
    if report.realism:
        lines.append(realism_table(report.realism))
    return "\n".join(lines)


#: Share of the excess the local patches must carry for compare to lead with "scene the model lacks".
MOSTLY_SCENE = 0.5


def lead_lines(report: GapReport) -> list[str]:
    """What the gap is made of, said before the figures: when local patches (scene the model lacks: clutter,
    surfaces the scene list does not hold) carry most of the excess, or the annotated objects alone are much
    closer than the whole region, the first line says so and gives the objects-only figure."""
    if report.region != "all" or report.objects is None or not math.isfinite(report.excess) or report.excess <= 0:
        return []
    objects, carried = report.objects, (report.local or {}).get("carried", 0.0)
    if carried < MOSTLY_SCENE and objects["excess"] > MOSTLY_SCENE * report.excess:
        return []
    why = (f"local patches (scene the model lacks) carry {100 * carried:.0f} % of the excess" if carried >= MOSTLY_SCENE
           else "the annotated objects alone are much closer")  # fmt: skip
    return [f"most of this gap is not the sensor: {why}; on the annotated objects alone the gap is "
            f"{objects['gap']:.2f} mm (noise floor {objects['noise_floor']:.2f} mm, excess {objects['excess']:.2f} mm; "
            f"--region objects measures only them)"]  # fmt: skip


def _f(x):
    return "-" if x is None else f"{x:+.1f}"


def _mm(x, spec: str) -> str:
    """``x`` mm formatted by ``spec``, or "-" where no pixel was valid in both (None)."""
    return "-" if x is None else f"{x:{spec}} mm"


def write_report(report: GapReport, folder: str | Path, name: str = "comparison") -> list[Path]:
    """Write ``NAME.json`` and the PNG plots (binned bias/spread/validity; residual maps) into ``folder``."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    out = [folder / f"{name}.json"]
    atomic_write_text(out[0], json.dumps(report.to_dict(), indent=1) + "\n")
    out.append(plot_bins(report, folder / f"{name}_bins.png"))
    if report.maps:
        out.append(plot_residuals([report], folder / f"{name}_residuals.png", ["residual (sim - real)"]))
    return out
