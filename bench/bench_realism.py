"""Realism benchmark: issue 12's hole, validity and quantisation statistics, real frames and simulated.

Prints `bench: NAME VALUE UNIT` lines (``ddsgen.depth_statistics.realism_statistics``):
  real_cat_*        the real LineMOD cat frame (../shared/data/linemod_bop/test/000006) in the compare region
                    (ddsgen.realscan.region: the pixels the modelled scene can explain; it depends on the
                    preset through the block size and the device's blind left columns)
  sim_cat_*         the same frame simulated at its ground-truth pose (ddsgen compare's region and seed 0)
  real_icbin_*      the nine real IC-BIN PrimeSense frames, whole image (min and max over the frames)
  real_tum_*        the real TUM RGB-D frame (Kinect V1, another scene at 1.5-9 m, depth in 1/5000 m), whole image
  *_flat_roughness_A_to_Bm   the disparity noise where flat, per depth bin, pooled over the frames (px;
                    ddsgen.surface_roughness.flat_roughness_by_depth); nguyen_* is Nguyen 2012's sigma_z read as
                    disparity with the preset's f b, sigma_z f b / z^2 at the bin's centre
  sim_render_*      frames of the built-in scene list (`ddsgen render PRESET -n 4`), whole image (min and max);
                    sim_render_frames_*: how many frames meet issue 12's per-frame targets (10-120 isolated
                    dropouts, their share of the invalid pixels <= 2 %, both)
  distreal_step_at_1m_mm   the level spacing of the real Kinect for Windows list distReal_mm.txt at 1 m

Usage: python bench/bench_realism.py [PRESET] [--frames N] [--pictures DIR]
(PRESET defaults to kinect_v1; --pictures writes side-by-side PNGs of real and simulated depth, and the flat
roughness against depth as a plot.)
Statistics of missing real data are skipped with a note.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import cv2
import numpy as np
import torch

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
DATA = ROOT.parent / "shared" / "data"

from ddsgen.depth_jumps import band_outcomes, registration_band_jumps  # noqa: E402
from ddsgen.depth_statistics import isolated_dropout_orientation, realism_statistics  # noqa: E402
from ddsgen.preset import load_preset  # noqa: E402
from ddsgen.study.noise import nguyen_sigma_px  # noqa: E402
from ddsgen.surface_roughness import flat_roughness_by_depth, surface_residuals  # noqa: E402

KEYS = {"valid_share": "", "corner_valid_share": "", "isolated_dropouts": "count",
        "isolated_dropout_share": "", "isolated_dropout_share_off_border": "", "isolated_dropout_mean_px": "px", "depth_step_at_1m_mm": "mm",
        "jump_holes_left": "", "jump_holes_right": "", "isolated_dropouts_per_1000_edge_px": "",
        "isolated_one_surface_share": "", "wide_band_hole_share": "", "narrow_band_slit_share": "", "isolated_vertical_share": "",
        "outline_jitter_px": "px", "flat_roughness_px": "px", "slanted_roughness_px": "px",
        "slant_roughness_ratio": "", "noise_correlation_row": "", "noise_correlation_column": ""}  # fmt: skip


def _print(name: str, stats: dict) -> None:
    for key, unit in KEYS.items():
        value = stats.get(key)
        if value is not None:
            print(f"bench: {name}_{key} {value:.4g} {unit}".rstrip(), flush=True)


def _print_range(name: str, all_stats: list[dict]) -> None:
    for key, unit in KEYS.items():
        values = [s[key] for s in all_stats if s.get(key) is not None]
        if values:
            print(f"bench: {name}_{key}_min {min(values):.4g} {unit}".rstrip(), flush=True)
            print(f"bench: {name}_{key}_max {max(values):.4g} {unit}".rstrip(), flush=True)


def colour_depth(depth_m: np.ndarray, z_lo: float, z_hi: float) -> np.ndarray:
    """(H, W, 3) uint8 BGR: depth colour-mapped between z_lo and z_hi (m), invalid (0) black."""
    scaled = np.clip((depth_m - z_lo) / max(z_hi - z_lo, 1e-6), 0.0, 1.0)
    image = cv2.applyColorMap((255 * scaled).astype(np.uint8), cv2.COLORMAP_TURBO)
    image[depth_m <= 0] = 0
    return image


def side_by_side(path: Path, left: np.ndarray, right: np.ndarray, labels: tuple[str, str]) -> None:
    """Two depth images (m) colour-mapped on one shared scale, next to each other, labelled."""
    both = np.concatenate([left[left > 0], right[right > 0]])
    z_lo, z_hi = (np.percentile(both, 1), np.percentile(both, 99)) if both.size else (0.0, 1.0)
    tiles = []
    for depth, label in zip((left, right), labels):
        tile = colour_depth(depth, z_lo, z_hi)
        cv2.putText(tile, label, (8, 24), cv2.FONT_HERSHEY_SIMPLEX, 0.7, (255, 255, 255), 2)
        tiles.append(tile)
    gap = np.full((tiles[0].shape[0], 8, 3), 255, np.uint8)
    cv2.imwrite(str(path), np.concatenate([tiles[0], gap, tiles[1]], axis=1))


def cat_frame(preset_name: str, pictures: Path | None) -> None:
    scene = DATA / "linemod_bop" / "test" / "000006"
    if not scene.is_dir():
        print(f"# {scene} absent: cat frame skipped", flush=True)
        return
    from ddsgen.realscan.inputs import load_inputs
    from ddsgen.realscan.simulate import simulate
    from ddsgen.sensor.depth_sensor import DepthSensor

    _, camera_preset, _, frames = load_inputs(preset_name, str(scene), progress=False)
    frame = frames[0]
    sensor = DepthSensor(camera_preset).eval()
    with torch.no_grad():
        out = simulate(sensor, frame, seed=0)
    region = frame.region.numpy()
    real = frame.real_depth.numpy()
    sim = out.depth.numpy()
    fb = frame.intrinsics.fx * camera_preset.baseline_m
    _print("real_cat", realism_statistics(real, real > 0, region, resolution_m=0.001, disparity_fb=fb))
    # The simulation is compared as the device writes it: millimetre PNG values.
    sim_mm = np.round(sim * 1000.0) / 1000.0
    _print("sim_cat", realism_statistics(sim_mm, out.valid.numpy(), region, resolution_m=0.001, disparity_fb=fb))
    if pictures is not None:
        side_by_side(pictures / "realism_cat.png", np.where(region, real, 0.0), np.where(region, sim_mm, 0.0),
                     ("real Kinect V1 (LineMOD cat)", f"ddsgen {preset_name}, GT pose"))  # fmt: skip


def _print_pooled(name: str, depths: list[np.ndarray]) -> None:
    """Pooled over frames (per frame the wide-band jumps and elongated dropouts are few, or none)."""
    # One pass of the jump finder per frame for both band statistics.
    kept, jumps, slits, narrow = np.sum([band_outcomes(*registration_band_jumps(d)) for d in depths], axis=0)
    print(f"bench: {name}_wide_bands_kept_open {kept} of {jumps}", flush=True)
    print(f"bench: {name}_narrow_bands_left_as_a_slit {slits} of {narrow}", flush=True)
    vertical, horizontal = np.sum([isolated_dropout_orientation(d > 0) for d in depths], axis=0)
    print(f"bench: {name}_isolated_vertical_of_elongated {vertical} of {vertical + horizontal}", flush=True)


def _print_roughness_by_depth(name: str, residuals: list, fb: float, nguyen: bool = False) -> list[dict]:
    """Flat roughness per depth bin, pooled over the frames' residuals (its rows); ``nguyen``: also Nguyen's curve."""
    rows = flat_roughness_by_depth(residuals)
    for row in rows:
        low, high = row["depth_m"]
        if row["roughness_px"] is not None:
            print(f"bench: {name}_flat_roughness_{low:g}_to_{high:g}m {row['roughness_px']:.4g} px "
                  f"({row['pixels']} pixels)", flush=True)
        if nguyen:
            print(f"bench: nguyen_{low:g}_to_{high:g}m {nguyen_sigma_px(0.5 * (low + high), fb):.4g} px", flush=True)
    return rows


def _roughness_inputs(depths: list[np.ndarray], fb: float) -> tuple[list, list[dict]]:
    """Each frame's surface residuals, computed once, and its realism statistics made with them."""
    residuals = [surface_residuals(d, fb, d > 0) for d in depths]
    return residuals, [realism_statistics(d, disparity_fb=fb, residuals=r) for d, r in zip(depths, residuals)]


def roughness_picture(path: Path, real_rows: list[dict], sim_rows: list[dict], preset_name: str, fb: float) -> None:
    """Flat roughness against depth: the real frames' bins, the renders' and Nguyen's curve, as disparity (px)."""
    from matplotlib.figure import Figure

    figure = Figure(figsize=(7, 4.2), dpi=110)
    axes = figure.add_subplot()
    for rows, label, style in ((real_rows, "real PrimeSense (IC-BIN, 9 frames)", "ks-"),
                               (sim_rows, f"ddsgen {preset_name}, rendered", "o-")):  # fmt: skip
        kept = [row for row in rows if row["roughness_px"] is not None]
        centres = [0.5 * sum(row["depth_m"]) for row in kept]
        half_widths = [0.5 * (row["depth_m"][1] - row["depth_m"][0]) for row in kept]
        axes.errorbar(centres, [row["roughness_px"] for row in kept], xerr=half_widths, fmt=style, capsize=2,
                      label=label)  # fmt: skip
    z = np.linspace(0.5, 2.2, 100)
    axes.plot(z, nguyen_sigma_px(z, fb), "--", color="grey", label="Nguyen 2012 sigma_z, as disparity")
    axes.set_xlabel("depth (m)")
    axes.set_ylabel("flat roughness (px of disparity)")
    axes.set_ylim(0, None)
    axes.set_title("Disparity noise where flat, against depth (15 x 15 px local fits)")
    axes.grid(alpha=0.3)
    axes.legend()
    figure.tight_layout()
    figure.savefig(path)


def _read_mm(path: Path) -> np.ndarray:
    return cv2.imread(str(path), cv2.IMREAD_UNCHANGED).astype(np.float64) / 1000.0


def icbin_frames() -> list[Path]:
    folder = DATA / "icbin_primesense_unpaired"
    return sorted(folder.glob("seq*/depth/*.png")) if folder.is_dir() else []


def real_icbin() -> list[dict]:
    """Prints the IC-BIN frames' statistics; returns their flat roughness by depth (empty without the frames)."""
    paths = icbin_frames()
    if not paths:
        print("# IC-BIN frames absent: skipped", flush=True)
        return []
    depths = [_read_mm(p) for p in paths]
    residuals, stats = _roughness_inputs(depths, ICBIN_FB)
    _print_range("real_icbin", stats)
    _print_pooled("real_icbin", depths)
    return _print_roughness_by_depth("real_icbin", residuals, ICBIN_FB)


TUM_DEPTH = DATA / "tum_rgbd_frame_open3d" / "TUM_depth.png"
TUM_UNITS_PER_M = 5000.0  # TUM RGB-D's depth PNG convention (its PROVENANCE.txt)
# f b (px m) for the roughness in disparity: a Kinect's 7.5 cm baseline with TUM's default focal length (its
# PROVENANCE.txt) and, for IC-BIN (no calibration shipped), a PrimeSense Carmine's nominal 550 px.
TUM_FB = 525.0 * 0.075
ICBIN_FB = 550.0 * 0.075


def real_tum() -> None:
    if not TUM_DEPTH.is_file():
        print("# TUM RGB-D frame absent: skipped", flush=True)
        return
    depth = cv2.imread(str(TUM_DEPTH), cv2.IMREAD_UNCHANGED).astype(np.float64) / TUM_UNITS_PER_M
    _print("real_tum", realism_statistics(depth, disparity_fb=TUM_FB))


def rendered(preset_name: str, n: int, pictures: Path | None, real_roughness: list[dict]) -> None:
    from ddsgen.runner import render_dataset

    with tempfile.TemporaryDirectory() as tmp:
        render_dataset(preset_name, None, n, tmp, workers=1, seed=0, progress=False)
        depths = [_read_mm(p) for p in sorted(Path(tmp, "depth").glob("*.png"))]
    preset = load_preset(preset_name)
    fb = preset.focal_px * preset.baseline_m
    residuals, stats = _roughness_inputs(depths, fb)
    _print_range("sim_render", stats)
    _print_pooled("sim_render", depths)
    roughness = _print_roughness_by_depth("sim_render", residuals, fb, nguyen=True)
    if pictures is not None and real_roughness:
        roughness_picture(pictures / "realism_roughness_by_depth.png", real_roughness, roughness, preset_name, fb)
    # Issue 12's per-frame targets for rendered frames: 10-120 isolated dropouts holding at most 2 % of the invalid
    # pixels (with --frames 16, seed 0: the frames docs/validation.md reports).
    counts = [10 <= s["isolated_dropouts"] <= 120 for s in stats]
    shares = [s["isolated_dropout_share"] is not None and s["isolated_dropout_share"] <= 0.02 for s in stats]
    print(f"bench: sim_render_frames_with_10_to_120_isolated {sum(counts)} of {len(stats)}", flush=True)
    print(f"bench: sim_render_frames_with_isolated_share_le_2pct {sum(shares)} of {len(stats)}", flush=True)
    print(f"bench: sim_render_frames_meeting_both {sum(c and s for c, s in zip(counts, shares))} of {len(stats)}",
          flush=True)
    # The same share off the blind border bands (real IC-BIN: 7 of 9 frames <= 2 %; the whole-frame share counts their
    # ~30,000 px registration border as invalid).
    off_border = [s["isolated_dropout_share_off_border"] <= 0.02 for s in stats]
    print(f"bench: sim_render_frames_with_isolated_share_off_border_le_2pct {sum(off_border)} of {len(stats)}",
          flush=True)
    paths = icbin_frames()
    if pictures is not None and paths and depths:
        side_by_side(pictures / "realism_render.png", _read_mm(paths[0]), depths[0],
                     ("real PrimeSense (IC-BIN)", f"ddsgen {preset_name}, rendered"))  # fmt: skip


def distreal_step() -> None:
    path = DATA / "kinect_v1_landau_simulator_data" / "distReal_mm.txt"
    if not path.is_file():
        print(f"# {path} absent: skipped", flush=True)
        return
    levels = np.unique(np.loadtxt(path).ravel()) / 1000.0
    near = levels[(levels > 0.95) & (levels < 1.05)]
    print(f"bench: distreal_step_at_1m_mm {1000 * np.mean(np.diff(near) / near[1:] ** 2):.4g} mm", flush=True)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("preset", nargs="?", default="kinect_v1")
    parser.add_argument("--frames", type=int, default=4)
    parser.add_argument("--pictures", type=Path, default=None)
    args = parser.parse_args()
    torch.set_num_threads(1)
    if args.pictures is not None:
        args.pictures.mkdir(parents=True, exist_ok=True)
    real_roughness = real_icbin()
    real_tum()
    distreal_step()
    cat_frame(args.preset, args.pictures)
    rendered(args.preset, args.frames, args.pictures, real_roughness)
    return 0


if __name__ == "__main__":
    sys.exit(main())
