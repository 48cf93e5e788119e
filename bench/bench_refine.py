"""Scene-gradient benchmark (issue 16): step time, synthetic pose recovery, the real LineMOD cat.

Prints `bench: NAME VALUE UNIT` lines:
  refine_step_640_sensor_ms, refine_step_640_geometry_ms   one forward + backward (depth loss + edge term) of a
                                                            640x480 frame with 8 objects and a support plane
                                                            (median of 5; wall and CPU time)
  synthetic_rotation_error_deg, synthetic_translation_error_mm   median over objects after `refine_poses`
                                                            from 3 deg / 10 mm off (8 frames x 4 shapes at
                                                            0.7 m), edge term off; synthetic_with_edges_*: on;
                                                            synthetic_floor_*: started at the true pose
                                                            (what the one "real" frame's noise leaves)
  synthetic_static_scene_*, synthetic_static_scene_floor_*  4 static scenes of the same 4 shapes, each seen from 4
                                                            camera poses (orbit of +-12 deg) and refined together
                                                            (`refine_static_scene`): median over the 16 objects
  synthetic_static_scene_linemod_*                          the same with 2 scenes of the 8 LineMOD meshes (below)
  synthetic_linemod_*, synthetic_linemod_floor_*             the same with the 8 LineMOD-Occluded meshes at
                                                            0.75-0.95 m, 640x480 (3 frames; needs the data)
  linemod_cat_rotation_error_deg, linemod_cat_translation_error_mm   the shared cat frame, pose perturbed by
                                                            3 deg / 8 mm, refined, vs the published pose
                                                            (median, range, 90th percentile over 20
                                                            perturbations, and how many end beyond 3 deg; skipped
                                                            without data)
  linemod_cat_drift_from_published                          the same refinement started at the published pose:
                                                            how far it moves (the floor of the metric above)
  refine_validation_rotation_error_deg, _translation_error_mm, _share_worse   the validation scenes of
                                                            tests/refine_validation.py (REPORT_SEEDS: 32 LineMOD
                                                            objects among unannotated distractors and occluders,
                                                            the independent sensor; 3 deg / 8 mm starts): median
                                                            errors and the share of objects ending worse than
                                                            their start (settings are chosen on TUNING_SEEDS)
  refine_validation_packed_*                                the same on the packed layout (PACKED_REPORT_SEEDS: 64
                                                            objects resting on the table, touching and hiding each
                                                            other, beside an unannotated object and a large box)
"""

from __future__ import annotations

import dataclasses
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

from ddsgen.preset import Intrinsics, load_preset  # noqa: E402
from ddsgen.raycast import cast  # noqa: E402
from ddsgen.scene import shapes  # noqa: E402
from ddsgen.scene.sampling import FrameScene, PlacedObject  # noqa: E402
from ddsgen.scene_gradients import RefinableScene, RefineSettings, refine_poses  # noqa: E402
from ddsgen.scene_gradients.poses import axis_angle_to_matrix, perturb_pose, pose_difference  # noqa: E402
from ddsgen.scene_gradients.edges import edge_loss, outline_points, real_edge_distance  # noqa: E402
from ddsgen.scene_gradients.hits import posed_geometry  # noqa: E402
from ddsgen.scene_gradients.refine import robust_depth_loss, simulate_depth  # noqa: E402
from ddsgen.scene_gradients.static_scene import refine_static_scene  # noqa: E402
from ddsgen.sensor.depth_sensor import DepthSensor  # noqa: E402
from ddsgen.sensor.geometry import SensorGeometry  # noqa: E402

from refine_validation import LINEMOD  # noqa: E402  (found from a checkout or a worktree)
SHAPES = [("box", {"size": (0.07, 0.055, 0.045)}), ("mug", {}), ("l_bracket", {}), ("box", {"size": (0.05, 0.09, 0.04)})]


def _pose(rotvec, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = axis_angle_to_matrix(torch.tensor(rotvec, dtype=torch.float64)).numpy()
    T[:3, 3] = t
    return T


def grid_scene(parts, rng: np.random.Generator, spread=(0.3, 0.2), depth=0.75, table_behind=0.15) -> FrameScene:
    """``parts`` [(name, mesh)] in random orientations on a grid (``spread`` m wide and high) at ``depth`` m,
    ``table_behind`` m in front of a tilted table plane."""
    objects = []
    cols = int(np.ceil(np.sqrt(len(parts) * 1.5)))
    rows = int(np.ceil(len(parts) / cols))
    for i, (name, mesh) in enumerate(parts):
        x = (i % cols - (cols - 1) / 2) * spread[0] / max(cols - 1, 1)
        y = (i // cols - (rows - 1) / 2) * spread[1] / max(rows - 1, 1)
        objects.append(PlacedObject(i + 1, name, name, mesh, _pose(rng.normal(size=3) * 0.8, (x, y, depth + 0.05 * (i % 3))),
                                    0.6))  # fmt: skip
    plane = PlacedObject(0, "table", "plane:3x3", shapes.plane_mesh(3.0, 3.0),
                         _pose((-0.9, 0, 0), (0, 0.1, depth + table_behind)), 0.6)  # fmt: skip
    return FrameScene(objects, [plane], np.eye(4), 0, 0)


def table_scene(n_objects: int, rng: np.random.Generator, spread=(0.3, 0.2), depth=0.75) -> FrameScene:
    """n procedural shapes (cycling through SHAPES) on the grid of :func:`grid_scene`."""
    parts = [(f"shape:{name}", shapes.make_shape(name, params or None))
             for name, params in (SHAPES[i % len(SHAPES)] for i in range(n_objects))]  # fmt: skip
    return grid_scene(parts, rng, spread, depth)


def step_time(gradient: str) -> tuple[float, float]:
    """(wall ms, CPU ms) of one default refinement step (depth loss + edge term, forward + backward),
    median of 5. The CPU time is what the step costs when the machine is shared (wall time is not)."""
    preset = load_preset("kinect_v1")
    scene = RefinableScene(table_scene(8, np.random.default_rng(0), spread=(0.5, 0.35), depth=0.9), preset.intrinsics,
                           preset.baseline_m, preset.shadow_bias_m)  # fmt: skip
    sensor = DepthSensor(preset)
    for p in sensor.parameters():
        p.requires_grad_(False)
    tensors = scene.cast()
    with torch.no_grad():
        real = sensor(SensorGeometry.from_hits(cast(scene.current_scene(), preset.intrinsics, 0.075, 0.005)), seed=1).depth
    distance = torch.from_numpy(real_edge_distance(real.numpy()))
    R, t = scene.poses()
    clean = posed_geometry(tensors, R, t, scene.poses.albedo).clean_depth.detach().numpy()
    outline = outline_points(tensors, [p.mesh for p in scene.parts], clean, scene.n_objects)
    wall, cpu = [], []
    for i in range(6):
        start, start_cpu = time.perf_counter(), time.process_time()
        R, t = scene.poses()
        depth, valid, geometry = simulate_depth(sensor, tensors, R, t, scene.poses.albedo, sensor.draw_noise(i), gradient)
        loss, _ = robust_depth_loss(depth, valid, geometry.clean_depth, real, 0.025, 0.003)
        loss = loss + edge_loss(outline, R, t, distance, preset.intrinsics).float()
        loss.backward()
        wall.append(time.perf_counter() - start)
        cpu.append(time.process_time() - start_cpu)
    return statistics.median(wall[1:]) * 1000.0, statistics.median(cpu[1:]) * 1000.0


def _linemod_meshes() -> list:
    """The shared LineMOD-Occluded object meshes (m), or [] without the data."""
    from ddsgen.scene.scenelist import load_mesh

    return [(p.stem, load_mesh(str(p), 0.001, source=str(p))) for p in sorted((LINEMOD / "models").glob("obj_*.ply"))]


def _recovery_setup(models: str):
    """(sensor, camera, meshes) of the synthetic cases: "shapes" in a 320x240 window (meshes None) or the
    LineMOD meshes at 640x480."""
    preset = load_preset("kinect_v1")
    full = preset.intrinsics
    intr = full if models == "linemod" else Intrinsics(320, 240, full.fx, full.fy, full.cx - 160, full.cy - 120)
    return DepthSensor(preset, intrinsics=intr), intr, _linemod_meshes() if models == "linemod" else None


def _truth_scene(meshes, rng: np.random.Generator) -> FrameScene:
    """The LineMOD grid (4 x 2, 0.13 m apart in x, 0.2 m in y, at 0.75-0.95 m) or 4 shapes at 0.7 m."""
    if meshes:
        return grid_scene(meshes, rng, spread=(0.39, 0.2), depth=rng.uniform(0.75, 0.95), table_behind=0.25)
    return table_scene(4, rng, spread=(0.22, 0.13), depth=0.7)


def _perturbed(objects, start, rng: np.random.Generator) -> list:
    """The objects with their poses ``start`` = (deg, mm) off, about their bounding-box centres."""
    moved = []
    for o in objects:
        centre = o.world_T_obj[:3, :3] @ o.mesh.bounds.mean(0) + o.world_T_obj[:3, 3]
        moved.append(dataclasses.replace(o, world_T_obj=perturb_pose(o.world_T_obj, centre, *start, rng)))
    return moved


def synthetic_recovery(frames: int = 8, edge_weight: float = 0.0, start=(3.0, 10.0),
                       models: str = "shapes") -> tuple[float, float]:  # fmt: skip
    """Median (deg, mm) error over objects after refining from poses ``start`` = (deg, mm) off the truth.

    models="shapes": 4 procedural shapes at 0.7 m in a 320x240 window; "linemod": the 8 LineMOD-Occluded
    meshes at 0.75-0.95 m, 640x480. start=(0, 0) starts at the truth: how far the noise of the one
    "real" frame moves the estimate (the floor of the metric).
    """
    sensor, intr, meshes = _recovery_setup(models)
    errors = []
    for frame in range(frames):
        rng = np.random.default_rng(100 + frame)
        truth = _truth_scene(meshes, rng)
        geometry = SensorGeometry.from_hits(cast(truth, intr, 0.075, 0.005))
        with torch.no_grad():
            real = sensor(geometry, seed=50 + frame).depth
        moved = _perturbed(truth.objects, start, rng)
        scene = RefinableScene(dataclasses.replace(truth, objects=moved), intr, 0.075, 0.005)
        result = refine_poses(sensor, scene, real, RefineSettings(edge_weight=edge_weight))
        found = [pose_difference(result.refined[k], o.world_T_obj) for k, o in enumerate(truth.objects)]
        errors += found
        print(f"  frame {frame}: " + ", ".join(f"{d:.2f} deg {m:.2f} mm" for d, m in found), flush=True)
    return float(np.median([e[0] for e in errors])), float(np.median([e[1] for e in errors]))


def orbit(azimuth_deg: float, elevation_deg: float, centre) -> np.ndarray:
    """world_T_cam of the camera turned about ``centre`` (m) by the given angles (world = the unturned camera)."""
    R = axis_angle_to_matrix(torch.tensor([np.radians(elevation_deg), np.radians(azimuth_deg), 0.0],
                                          dtype=torch.float64)).numpy()  # fmt: skip
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, np.asarray(centre) - R @ np.asarray(centre)
    return T


ORBIT = [(0, 0), (12, 0), (-12, 0), (0, 10)]


def static_scene_recovery(scenes: int = 4, start=(3.0, 10.0), models: str = "shapes") -> tuple[float, float]:
    """Median (deg, mm) error over objects of static scenes seen from the ``ORBIT`` camera poses and refined
    together from world poses ``start`` off the truth (the scenes and windows of ``synthetic_recovery``)."""
    sensor, intr, meshes = _recovery_setup(models)
    errors = []
    for index in range(scenes):
        rng = np.random.default_rng(100 + index)
        truth = _truth_scene(meshes, rng)
        moved = _perturbed(truth.objects, start, rng)
        views, reals = [], []
        for v, angles in enumerate(ORBIT):
            seen = dataclasses.replace(truth, world_T_cam=orbit(*angles, centre=(0.0, 0.0, 0.72 if meshes is None
                                                                          else truth.objects[0].world_T_obj[2, 3])))
            with torch.no_grad():
                reals.append(sensor(SensorGeometry.from_hits(cast(seen, intr, 0.075, 0.005)), seed=50 + 10 * index + v).depth)
            views.append(RefinableScene(dataclasses.replace(seen, objects=moved), intr, 0.075, 0.005))
        refine_static_scene(sensor, views, reals, RefineSettings(edge_weight=0.0))
        refined = [views[0].scene.world_T_cam @ T for T in views[0].object_poses()]
        found = [pose_difference(T, o.world_T_obj) for T, o in zip(refined, truth.objects)]
        errors += found
        print(f"  scene {index}: " + ", ".join(f"{d:.2f} deg {m:.2f} mm" for d, m in found), flush=True)
    return float(np.median([e[0] for e in errors])), float(np.median([e[1] for e in errors]))


def linemod_cat(perturbations: int = 20, gradient: str = "sensor") -> dict | None:
    """Errors vs the published pose of the shared cat after refining from that pose perturbed by 3 deg / 8 mm
    (``perturbations`` random draws) and from the published pose itself (its drift: the floor of this metric,
    the published pose being a few mm / deg off itself)."""
    if not LINEMOD.is_dir():
        return None
    from ddsgen.realscan.inputs import adopt_camera
    from ddsgen.realscan.simulate import _load_object_mesh
    from ddsgen.io.scanfolder import read_scan_folder
    from ddsgen.scene_gradients.scan import refine_scan_frame

    errors, drift = [], None
    for i in [-1, *range(perturbations)]:
        (frame,) = read_scan_folder(LINEMOD)
        preset, _ = adopt_camera(load_preset("kinect_v1"), [frame])
        published = [o.cam_T_obj.copy() for o in frame.objects]
        rng = np.random.default_rng(i) if i >= 0 else None
        for o in frame.objects if rng is not None else []:
            mesh = _load_object_mesh(o)
            centre = o.cam_T_obj[:3, :3] @ mesh.bounds.mean(0) + o.cam_T_obj[:3, 3]
            o.cam_T_obj = perturb_pose(o.cam_T_obj, centre, 3.0, 8.0, rng)
        r = refine_scan_frame(preset, frame, 0, RefineSettings(gradient=gradient))
        found = [pose_difference(r.result.refined[k], T) for k, T in enumerate(published)]
        if i < 0:
            drift = found[0]
        else:
            errors += found
        print(f"  {'from the published pose' if i < 0 else f'perturbation {i}'}: {found[0][0]:.2f} deg "
              f"{found[0][1]:.2f} mm (gap {r.result.gap_before_mm:.2f} -> {r.result.gap_after_mm:.2f} mm)", flush=True)
    deg, mm = np.array([e[0] for e in errors]), np.array([e[1] for e in errors])
    return {"deg": float(np.median(deg)), "mm": float(np.median(mm)), "deg_range": (float(deg.min()), float(deg.max())),
            "mm_range": (float(mm.min()), float(mm.max())), "drift": drift, "deg_p90": float(np.percentile(deg, 90)),
            "astray": int((deg > 3.0 + 1e-6).sum())}  # fmt: skip


def refine_validation(layout: str = "grid") -> dict | None:
    """Median errors and share of objects worse than their start on the report scenes of a layout ("grid" or
    "packed"), or None without data."""
    import refine_validation as validation

    if not LINEMOD.is_dir():
        return None
    seeds = validation.PACKED_REPORT_SEEDS if layout == "packed" else validation.REPORT_SEEDS
    return validation.summary(validation.run(seeds, RefineSettings(), verbose=False, layout=layout))


def main() -> None:
    torch.set_num_threads(2)
    for layout, name in (("grid", "refine_validation"), ("packed", "refine_validation_packed")):
        found = refine_validation(layout)
        if found is not None:
            print(f"bench: {name}_rotation_error_deg {found['deg']:.3f} deg ({found['objects']} objects)\n"
                  f"bench: {name}_translation_error_mm {found['mm']:.3f} mm\n"
                  f"bench: {name}_share_worse {100 * found['worse']:.1f} %", flush=True)  # fmt: skip
    for gradient in ("sensor", "geometry"):
        wall, cpu = step_time(gradient)
        print(f"bench: refine_step_640_{gradient}_ms {wall:.0f} ms (CPU time {cpu:.0f} ms)", flush=True)
    # Sim vs sim without the edge term (the simulated outlines differ from the clean ones, see
    # docs/scene_gradients.md), from 3 deg / 10 mm and from the truth (the floor: the one "real" frame's
    # noise), then with the edge term (the default, made for real depth) to show what it costs there.
    cases = [("synthetic", {}), ("synthetic_floor", {"start": (0.0, 0.0)}),
             ("synthetic_with_edges", {"edge_weight": RefineSettings().edge_weight})]
    if LINEMOD.is_dir():
        cases += [("synthetic_linemod", {"models": "linemod", "frames": 3}),
                  ("synthetic_linemod_floor", {"models": "linemod", "frames": 3, "start": (0.0, 0.0)})]
    cases += [("synthetic_static_scene", {"static": True}),
              ("synthetic_static_scene_floor", {"static": True, "start": (0.0, 0.0)})]
    if LINEMOD.is_dir():
        cases += [("synthetic_static_scene_linemod", {"static": True, "models": "linemod", "scenes": 2})]
    for name, kwargs in cases:
        if kwargs.pop("static", False):
            deg, mm = static_scene_recovery(**kwargs)
        else:
            deg, mm = synthetic_recovery(**kwargs)
        print(f"bench: {name}_rotation_error_deg {deg:.3f} deg\n"
              f"bench: {name}_translation_error_mm {mm:.3f} mm", flush=True)
    cat = linemod_cat()
    if cat is not None:
        print(f"bench: linemod_cat_rotation_error_deg {cat['deg']:.2f} deg (range {cat['deg_range'][0]:.2f}-"
              f"{cat['deg_range'][1]:.2f}, 90th percentile {cat['deg_p90']:.2f}, {cat['astray']} of the starts "
              f"beyond 3 deg)\nbench: linemod_cat_translation_error_mm {cat['mm']:.2f} mm (range "
              f"{cat['mm_range'][0]:.2f}-{cat['mm_range'][1]:.2f})\nbench: linemod_cat_drift_from_published "
              f"{cat['drift'][0]:.2f} deg {cat['drift'][1]:.2f} mm")  # fmt: skip


if __name__ == "__main__":
    main()
