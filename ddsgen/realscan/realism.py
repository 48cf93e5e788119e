"""Hole, validity and quantisation statistics of real and simulated frames, side by side.

The statistics are :func:`ddsgen.depth_statistics.realism_statistics` (valid share, corner
valid share, isolated dropouts and their share of the invalid pixels, depth step at 1 m),
computed on full frames (a ``--crop`` simulation is pasted back into its frame, so "corners"
are the image's corners) over these pixel sets:

* ``real.region`` and ``sim.region``: the compare region (modelled geometry visible and
  plausible; with ``--region objects`` the objects' pixels only);
* ``real.whole_frame``: every pixel of the real image;
* ``sim.modelled``: for the simulation the whole frame means the modelled region only, every
  pixel where modelled geometry is hit; elsewhere it has no depth by construction.

Aggregates are the mean, min and max over frames of each statistic.

Besides, ``edges``: the objects' outlines in real and simulated depth against the ray-cast silhouette, inside the
compare region (:mod:`ddsgen.silhouette_edges`: how far the edges lie outside it, and how ragged they are); and,
with the sensor's baseline, ``flat_roughness_by_depth``: the disparity noise where flat, per depth bin, pooled over
the frames, real and simulated, in the compare region (:class:`ddsgen.surface_roughness.FlatRoughnessPool`: exact up
to 200,000 residuals per bin, a uniform sample of them beyond).
"""

from __future__ import annotations

import math

import numpy as np

from ddsgen.depth_statistics import STATISTIC_LABELS, realism_statistics
from ddsgen.realscan.realfolder import round_like
from ddsgen.silhouette_edges import edge_statistics
from ddsgen.surface_roughness import FlatRoughnessPool, flat_residuals_by_depth, surface_residuals

SCOPES = {
    "real.region": "real frame, compare region (modelled, visible, plausible pixels)",
    "real.whole_frame": "real frame, every pixel of the image",
    "sim.region": "simulated frame, compare region",
    "sim.modelled": "simulated frame: its whole frame is the modelled region only (pixels where modelled geometry "
                    "is hit; the simulation has no depth elsewhere; with --crop, inside the crop window less the "
                    "border the matcher cannot reach)",
}  # fmt: skip
STATISTICS = tuple(STATISTIC_LABELS)
EDGE_LABELS = {
    "edge_rows": "GT silhouette rows measured",
    "edge_fattening_px": "  depth edge outside it (px)",
    "edge_jitter_px": "  depth edge jitter (px rms)",
}


def full_frame(array, frame, fill=0) -> np.ndarray:
    """(H, W) of the uncropped image: a prepared frame's (h, w) array pasted at its crop box.

    Args:
        array: (h, w) tensor or array of a :class:`~ddsgen.realscan.simulate.FrameData` (cropped or not).
        frame: the FrameData (its ``crop`` and ``full_intrinsics``).
        fill: value outside the crop.
    """
    array = np.asarray(array)
    full = frame.full_intrinsics or frame.intrinsics
    if array.shape == (full.height, full.width):
        return array
    x0, y0, w, h = frame.crop
    out = np.full((full.height, full.width), fill, dtype=array.dtype)
    out[y0 : y0 + h, x0 : x0 + w] = array
    return out


def frame_realism(frame, sim, region: np.ndarray, real_depth_m: np.ndarray, real_resolution_m: float,
                  crop_border_px: int = 0, baseline_m: float | None = None) -> dict:  # fmt: skip
    """The statistics of one frame, real and simulated (see the module docstring).

    Args:
        frame: :class:`~ddsgen.realscan.simulate.FrameData`.
        sim: its :class:`~ddsgen.sensor.depth_sensor.SensorOutput` (depth, valid (h, w)).
        region: bool (h, w), the compare region of ``frame``.
        real_depth_m: float32 (H, W) the whole real image, metres, 0 = invalid.
        real_resolution_m: the rounding unit of the real values (PNG: its depth_scale; EXR: 0).
        crop_border_px: with ``--crop``, the border of the crop window the matcher cannot reach
            (half a block + 1 px; the compare region leaves it out too), not counted as modelled.
        baseline_m: the sensor's baseline, for the roughness in disparity (f b / z with the frame's f; None: no
            roughness statistics).
    """
    region = full_frame(region, frame, False)
    hit = np.asarray(frame.hit).copy()
    if crop_border_px:
        b = crop_border_px
        hit[:b], hit[-b:], hit[:, :b], hit[:, -b:] = False, False, False, False
    modelled = full_frame(hit, frame, False)
    sim_depth = full_frame(sim.depth.detach(), frame, 0.0)
    sim_valid = full_frame(sim.valid, frame, False)
    real = np.asarray(real_depth_m, dtype=np.float32)
    real_valid = real > 0
    clean = full_frame(np.asarray(frame.clean_depth), frame, 0.0)
    instance = full_frame(np.asarray(frame.instance), frame, 0)
    fb = frame.intrinsics.fx * baseline_m if baseline_m else None
    real_residuals = sim_residuals = None
    if fb:
        # In the compare region the simulation's roughness is measured as the real values are stored (rounded to
        # their unit: at 0.5 m a millimetre's rounding alone is 0.05 px of disparity noise); computed once here for
        # realism_statistics and for the pooled flat roughness by depth (aggregate()).
        stored = round_like(sim_depth, real_resolution_m)
        real_residuals = surface_residuals(real, fb, real_valid, region)
        sim_residuals = surface_residuals(stored, fb, sim_valid, region)
    # Otherwise the simulation's depth is used as computed (float, as in its EXR): exact levels, not rounded.
    statistics = {
        "name": frame.name,
        "real": {"region": realism_statistics(real, real_valid, region, real_resolution_m, fb, real_residuals),
                 "whole_frame": realism_statistics(real, real_valid, None, real_resolution_m, fb)},
        "sim": {"region": realism_statistics(sim_depth, sim_valid, region, 0.0, fb, sim_residuals),
                "modelled": realism_statistics(sim_depth, sim_valid, modelled, 0.0, fb)},
        "edges": {"real": edge_statistics(real, real_valid, clean, instance, region),
                  "sim": edge_statistics(sim_depth, sim_valid, clean, instance, region)},
    }  # fmt: skip
    if fb:
        statistics["flat_residuals_by_depth"] = {"real": flat_residuals_by_depth(real_residuals),
                                                 "sim": flat_residuals_by_depth(sim_residuals)}  # fmt: skip
    return statistics


def aggregate(per_frame: list[dict], roughness: dict[str, FlatRoughnessPool] | None = None) -> dict:
    """``{"scopes", "frames", "aggregate": {"real.region": {stat: {mean, min, max}}, ...}}`` (JSON-ready); with
    ``roughness`` (:func:`roughness_pools`, fed every frame) also ``"flat_roughness_by_depth": {"real": rows, "sim":
    rows}``."""
    summary = {}
    for scope in SCOPES:
        side, where = scope.split(".")
        summary[scope] = {}
        for stat in STATISTICS:
            values = [f[side][where][stat] for f in per_frame if f[side][where][stat] is not None]
            summary[scope][stat] = _spread(values)
    edges = {side: {stat: _spread([f["edges"][side][stat] for f in per_frame]) for stat in EDGE_LABELS}
             for side in ("real", "sim")}  # fmt: skip
    frames = [{"name": f["name"], **{side: {where: {k: _r(v) for k, v in stats.items()}
                                            for where, stats in f[side].items()} for side in ("real", "sim")},
               "edges": {side: {k: _r(v) for k, v in stats.items()} for side, stats in f["edges"].items()}}
              for f in per_frame]  # fmt: skip
    result = {"scopes": SCOPES, "statistics": list(STATISTICS), "aggregate": summary, "edges": edges, "frames": frames}
    by_depth = {side: pool.rows() for side, pool in (roughness or {}).items()}
    if any(row["pixels"] for rows in by_depth.values() for row in rows):
        result["flat_roughness_by_depth"] = {
            side: [{"depth_m": row["depth_m"], "roughness_px": _r(row["roughness_px"]), "pixels": row["pixels"]}
                   for row in rows]
            for side, rows in by_depth.items()
        }  # fmt: skip
    return result


def roughness_pools() -> dict[str, FlatRoughnessPool]:
    """``{"real": pool, "sim": pool}``: feed each frame's :func:`frame_realism` ``"flat_residuals_by_depth"`` with
    :func:`pool_frame_roughness`, then pass them to :func:`aggregate` (bounded memory for any number of frames)."""
    return {"real": FlatRoughnessPool(), "sim": FlatRoughnessPool()}


def pool_frame_roughness(statistics: dict, pools: dict[str, FlatRoughnessPool]) -> dict:
    """Move one frame's flat residuals out of its :func:`frame_realism` dict into ``pools``; returns the dict."""
    flat = statistics.pop("flat_residuals_by_depth", None)
    if flat is not None:
        for side, pool in pools.items():
            pool.add(flat[side])
    return statistics


def _spread(values: list) -> dict | None:
    """{mean, min, max} of the values that are not None, or None."""
    values = [v for v in values if v is not None]
    return {"mean": _r(np.mean(values)), "min": _r(min(values)), "max": _r(max(values))} if values else None


def _r(x, nd=5):
    if x is None:
        return None
    if isinstance(x, int | np.integer):
        return int(x)
    x = float(x)
    return round(x, nd) if math.isfinite(x) else None


def _cell(spread: dict | None, whole: bool) -> str:
    """One table cell: mean [min-max], 22 characters wide; counts (``whole``) without decimals."""
    if spread is None:
        return f"{'-':>22s}"
    if whole:
        return f"{spread['mean']:>8.1f} [{spread['min']:.0f}-{spread['max']:.0f}]".rjust(22)
    return f"{spread['mean']:>8.3f} [{spread['min']:.3f}-{spread['max']:.3f}]".rjust(22)


def table(realism: dict) -> str:
    """Plain-text table: one row per statistic, columns real/sim on the region and whole frame (mean [min-max]);
    the outline rows' statistics (measured in the region) in the two region columns."""
    columns = ("real.region", "sim.region", "real.whole_frame", "sim.modelled")
    lines = [f"{'realism (mean [min-max])':31s}" + "".join(f"{c:>22s}" for c in columns)]
    for stat in STATISTICS:
        cells = [_cell(realism["aggregate"][scope][stat], stat == "isolated_dropouts") for scope in columns]
        lines.append(f"{STATISTIC_LABELS[stat]:31s}" + "".join(cells))
    for stat, label in EDGE_LABELS.items():
        edges = realism.get("edges", {})
        cells = [_cell(edges.get(side, {}).get(stat), stat == "edge_rows") for side in ("real", "sim")]
        lines.append(f"{label:31s}" + "".join(cells))
    by_depth = realism.get("flat_roughness_by_depth")
    if by_depth:
        lines.append("flat roughness by depth (px, pixels measured; real and sim in the compare region)")
        for real_row, sim_row in zip(by_depth["real"], by_depth["sim"]):
            if real_row["roughness_px"] is None and sim_row["roughness_px"] is None:
                continue
            low, high = real_row["depth_m"]
            cells = [f"{row['roughness_px']:.3f} ({row['pixels']})" if row["roughness_px"] is not None else "-"
                     for row in (real_row, sim_row)]  # fmt: skip
            lines.append(f"{f'  {low:g}-{high:g} m':31s}" + "".join(cell.rjust(22) for cell in cells))
    return "\n".join(lines)
