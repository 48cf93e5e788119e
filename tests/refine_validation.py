"""Validation scenes of ``refine``: LineMOD objects among clutter the refined scene does not hold, measured by an
independent sensor model (:mod:`tests.independent_sensor`, numpy; ddsgen supplies only the ray-cast geometry).

A scene (seeded) holds, in front of a tilted table at 0.75-0.95 m, 4 annotated LineMOD objects in random
orientations on a loose 2 x 2 grid, and what the annotation lacks:

* 2 unannotated distractors: LineMOD meshes not annotated in the scene, each beside an annotated object (their
  silhouettes touch or overlap it in the image);
* 1 occluder: a bar 0.10-0.15 m in front of one annotated object, hiding part of it.

The refined scene holds only the annotated objects (each started 3 deg / 8 mm off its true pose, about its
bounding-box centre, seeded) and the table at its true pose; ddsgen's sensor (the ``kinect_v1`` preset) is the
model. The real depth is the independent sensor's (disparity noise and 1/8 px quantisation, projector shadow).

A second layout, :func:`make_packed_scene`, is the clutter of a LineMOD-Occluded frame: the objects rest on the table
in stable poses, packed so that they touch and hide each other (visible shares 0-1), beside an unannotated LineMOD
object and a large box the refined scene lacks.

Split (never tune on the report scenes): seeds in ``TUNING_SEEDS`` / ``PACKED_TUNING_SEEDS`` are for choosing
settings; ``REPORT_SEEDS`` / ``PACKED_REPORT_SEEDS`` are the held-out scenes whose numbers are reported
(bench/bench_refine.py: all of them; tests: the first of each).
An object "ends worse" if its rotation error exceeds its start's (3 deg) or its translation error its start's
(8 mm).
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import torch


def _shared_linemod() -> Path:
    """The shared LineMOD data: ``shared/data/linemod_bop`` beside the nearest ancestor that has it (a checkout at
    /work/main or a worktree at /work/wt/NAME both find /work/shared)."""
    here = Path(__file__).resolve()
    for folder in here.parents:
        candidate = folder / "shared" / "data" / "linemod_bop"
        if candidate.is_dir():
            return candidate
    return here.parents[2] / "shared" / "data" / "linemod_bop"


LINEMOD = _shared_linemod()
TUNING_SEEDS = tuple(range(1000, 1008))
REPORT_SEEDS = tuple(range(8))  # 8 scenes x 4 annotated objects = 32 objects
#: The packed layout (:func:`make_packed_scene`): seeds 0-7 were looked at while choosing the acceptance's keep rule,
#: so they are tuning seeds too; 100-115 (64 objects) are reported.
PACKED_TUNING_SEEDS = tuple(range(1000, 1008)) + tuple(range(8))
PACKED_REPORT_SEEDS = tuple(range(100, 116))
ANNOTATED_PER_SCENE = 4
START = (3.0, 8.0)  # deg, mm
BASELINE_M, SHADOW_BIAS_M = 0.075, 0.005


def linemod_meshes() -> list:
    """[(obj_id, mesh in m)] of the shared LineMOD models, [] without the data."""
    from ddsgen.scene.scenelist import load_mesh

    models = sorted((LINEMOD / "models").glob("obj_*.ply"))
    return [(int(p.stem.split("_")[1]), load_mesh(str(p), 0.001, source=str(p))) for p in models]


def _rotation(rotvec) -> np.ndarray:
    from ddsgen.scene_gradients.poses import axis_angle_to_matrix

    return axis_angle_to_matrix(torch.tensor(np.asarray(rotvec, dtype=np.float64))).numpy()


def _pose(rotvec, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = _rotation(rotvec), t
    return T


@dataclasses.dataclass
class ValidationScene:
    """A measured cluttered scene and the start of its refinement.

    truth: FrameScene of everything (annotated objects first, then distractors and the occluder; the table).
    annotated: the annotated objects (true poses); start: the same at the perturbed start poses.
    obj_ids: the annotated objects' LineMOD obj_id; real: (H, W) float32 measured depth (m, 0 invalid), 640 x 480.
    visible: per annotated object, its pixels in the scene over its pixels cast alone ([] if not measured).
    """

    seed: int
    truth: object
    annotated: list
    start: list
    obj_ids: list
    real: np.ndarray
    visible: list = dataclasses.field(default_factory=list)  # per annotated object: its visible share


def make_scene(seed: int, meshes: list, intrinsics) -> ValidationScene:
    """The validation scene of ``seed`` (see the module docstring), measured by the independent sensor."""
    from ddsgen.scene import shapes
    from ddsgen.scene.sampling import FrameScene, PlacedObject

    rng = np.random.default_rng([seed, 65])
    depth = rng.uniform(0.75, 0.95)
    order = rng.permutation(len(meshes))
    chosen = [meshes[i] for i in order[:ANNOTATED_PER_SCENE]]
    spare = [meshes[i] for i in order[ANNOTATED_PER_SCENE:]]
    annotated = []
    for i, (obj_id, mesh) in enumerate(chosen):
        x = (i % 2 - 0.5) * 0.2 + rng.uniform(-0.02, 0.02)
        y = (i // 2 - 0.5) * 0.15 + rng.uniform(-0.02, 0.02)
        annotated.append(PlacedObject(i + 1, f"obj_{obj_id:06d}", f"obj_{obj_id:06d}", mesh,
                                      _pose(rng.normal(size=3) * 0.8, (x, y, depth + rng.uniform(-0.03, 0.03))), 0.6))  # fmt: skip
    clutter = []
    beside = rng.choice(ANNOTATED_PER_SCENE, size=2, replace=False)
    for j, k in enumerate(beside):  # a distractor touching an annotated object in the image, a little behind it
        obj_id, mesh = spare[j % len(spare)]
        T = annotated[k].world_T_obj
        side = np.array([math.copysign(1.0, T[0, 3]) * rng.uniform(0.06, 0.08), rng.uniform(-0.03, 0.03), 0.03])
        clutter.append(PlacedObject(10 + j, "distractor", f"obj_{obj_id:06d}", mesh,
                                    _pose(rng.normal(size=3), T[:3, 3] + side), 0.6))  # fmt: skip
    k = int(rng.integers(ANNOTATED_PER_SCENE))  # the occluder: a bar in front of one annotated object
    T = annotated[k].world_T_obj
    bar = shapes.make_shape("box", {"size": (0.03, 0.16, 0.02)})
    offset = np.array([rng.choice([-1.0, 1.0]) * rng.uniform(0.015, 0.03), 0.0, -rng.uniform(0.10, 0.15)])
    clutter.append(PlacedObject(20, "occluder", "shape:box", bar, _pose((0, 0, rng.uniform(-0.3, 0.3)), T[:3, 3] + offset), 0.6))
    table = PlacedObject(0, "table", "plane:3x3", shapes.plane_mesh(3.0, 3.0), _pose((-0.9, 0, 0), (0, 0.1, depth + 0.2)), 0.6)
    truth = FrameScene(annotated + clutter, [table], np.eye(4), 0, seed)
    return _measured(seed, truth, annotated, intrinsics, 66, rng)


def _resting_pose(rng, mesh_path: Path, table_T: np.ndarray, xy, yaw: float):
    """(4, 4) world pose of a LineMOD mesh resting on the table in one of its stable poses (drawn by probability),
    its footprint box centred at table coordinates ``xy``, turned by ``yaw`` about the table's normal; and its
    (K, 2) footprint polygon in table coordinates."""
    from ddsgen.scene.footprints import rest_poses

    poses, probabilities = rest_poses(str(mesh_path), 0.001, "stable")
    rest = poses[int(rng.choice(len(poses), p=probabilities))]
    placed = np.eye(4)
    placed[:3, 3] = -rest.offset
    turn = _pose((0, 0, yaw), (xy[0], xy[1], 0.0))
    c, s = math.cos(yaw), math.sin(yaw)
    footprint = rest.footprint @ np.array([[c, s], [-s, c]]) + np.asarray(xy)
    return table_T @ turn @ placed @ rest.rotation, footprint


def _box_on_table(table_T: np.ndarray, size, xy, yaw: float):
    """(4, 4) world pose of a box of ``size`` (m) standing on the table at ``xy``, and its (4, 2) footprint."""
    sx, sy, sz = size
    c, s = math.cos(yaw), math.sin(yaw)
    corners = np.array([[-sx, -sy], [sx, -sy], [sx, sy], [-sx, sy]]) / 2.0
    return table_T @ _pose((0, 0, yaw), (xy[0], xy[1], sz / 2.0)), corners @ np.array([[c, s], [-s, c]]) + xy


def make_packed_scene(seed: int, meshes: list, intrinsics) -> ValidationScene:
    """A cluttered scene as LineMOD-Occluded shows one: objects resting on the table in stable poses, packed so that
    they touch and hide each other from the oblique camera.

    4 annotated LineMOD objects, 1 unannotated LineMOD object and 1 large box without a mesh in the refined scene
    (0.08-0.12 x 0.05-0.08 x 0.12-0.18 m) are dropped, in random order, at random points of a 0.12 m disc on the
    table, each at least 3 mm from the others' footprints; the table is tilted 52 degrees towards the camera, its
    centre 0.75-0.95 m away. Measured by the independent sensor; starts 3 deg / 8 mm off (as :func:`make_scene`).
    """
    from ddsgen.scene import shapes
    from ddsgen.scene.footprints import polygons_separated
    from ddsgen.scene.sampling import FrameScene, PlacedObject


    rng = np.random.default_rng([seed, 67])
    depth = rng.uniform(0.75, 0.95)
    table_T = _pose((-0.9, 0, 0), (0, 0.05, depth)) @ np.diag([1.0, -1.0, -1.0, 1.0])  # z: the table's up
    order = rng.permutation(len(meshes))
    annotated_meshes = [meshes[i] for i in order[:ANNOTATED_PER_SCENE]]
    distractor = meshes[order[ANNOTATED_PER_SCENE]]
    box_size = (rng.uniform(0.08, 0.12), rng.uniform(0.05, 0.08), rng.uniform(0.12, 0.18))
    items = [("annotated", k) for k in range(ANNOTATED_PER_SCENE)] + [("distractor", 0), ("box", 0)]
    footprints, annotated, clutter = [], [None] * ANNOTATED_PER_SCENE, []
    for item in (items[i] for i in rng.permutation(len(items))):
        for _ in range(400):  # rejection sampling in the disc; the last draw is kept if none fits
            r, a = 0.12 * math.sqrt(rng.uniform()), rng.uniform(0, 2 * math.pi)
            xy, yaw = np.array([r * math.cos(a), r * math.sin(a)]), rng.uniform(-math.pi, math.pi)
            if item[0] == "box":
                T, footprint = _box_on_table(table_T, box_size, xy, yaw)
            else:
                obj_id, mesh = annotated_meshes[item[1]] if item[0] == "annotated" else distractor
                T, footprint = _resting_pose(rng, LINEMOD / "models" / f"obj_{obj_id:06d}.ply", table_T, xy, yaw)
            if all(polygons_separated(footprint, other, 0.003) for other in footprints):
                break
        footprints.append(footprint)
        if item[0] == "box":
            clutter.append(PlacedObject(20, "box", "shape:box", shapes.make_shape("box", {"size": box_size}), T, 0.6))
        elif item[0] == "distractor":
            clutter.append(PlacedObject(10, "distractor", f"obj_{obj_id:06d}", mesh, T, 0.6))
        else:
            annotated[item[1]] = PlacedObject(item[1] + 1, f"obj_{obj_id:06d}", f"obj_{obj_id:06d}", mesh, T, 0.6)
    table = PlacedObject(0, "table", "plane:3x3", shapes.plane_mesh(3.0, 3.0), table_T, 0.6)
    truth = FrameScene(annotated + clutter, [table], np.eye(4), 0, seed)
    return _measured(seed, truth, annotated, intrinsics, 68, rng)


def _measured(seed: int, truth, annotated: list, intrinsics, noise_stream: int, rng) -> ValidationScene:
    """The scene ``truth`` measured by the independent sensor (noise from rng([seed, noise_stream])), each annotated
    object started 3 deg / 8 mm off about its bounding-box centre (drawn from ``rng``), and its visible share."""
    from ddsgen.raycast import cast
    from ddsgen.scene_gradients.poses import perturb_pose

    from independent_sensor import measure

    hits = cast(truth, intrinsics, BASELINE_M, SHADOW_BIAS_M)
    intr = {"fx": intrinsics.fx, "fy": intrinsics.fy, "cx": intrinsics.cx, "cy": intrinsics.cy}
    real = measure(hits.depth.astype(np.float64), hits.hit & ~hits.shadow, np.zeros(hits.depth.shape), intr,
                   BASELINE_M, None, np.random.default_rng([seed, noise_stream]))  # fmt: skip
    start = []
    for o in annotated:
        centre = o.world_T_obj[:3, :3] @ o.mesh.bounds.mean(0) + o.world_T_obj[:3, 3]
        start.append(dataclasses.replace(o, world_T_obj=perturb_pose(o.world_T_obj, centre, *START, rng)))
    visible = [float((hits.instance == o.id).sum()) / max(hits.coverage.get(o.id, 0), 1) for o in annotated]
    return ValidationScene(seed, truth, annotated, start, [int(o.class_name[4:]) for o in annotated], real, visible)


def refine_scene(scene: ValidationScene, settings, margin_px: int = 32) -> list[dict]:
    """Refine the annotated objects of ``scene`` from their starts (a window around them, the table included).

    Returns per object: {seed, obj_id, start_deg, start_mm, deg, mm, worse, decision}."""
    from ddsgen.preset import Intrinsics, load_preset
    from ddsgen.scene.sampling import FrameScene
    from ddsgen.scene_gradients import RefinableScene, refine_poses
    from ddsgen.scene_gradients.poses import pose_difference
    from ddsgen.sensor.depth_sensor import DepthSensor

    preset = load_preset("kinect_v1")
    full = preset.intrinsics
    x0, y0, x1, y1 = _window(scene.start + scene.annotated, full, margin_px)
    window = Intrinsics(x1 - x0, y1 - y0, full.fx, full.fy, full.cx - x0, full.cy - y0)
    refined_scene = FrameScene(list(scene.start), list(scene.truth.background), np.eye(4), 0, scene.seed)
    refinable = RefinableScene(refined_scene, window, preset.baseline_m, preset.shadow_bias_m,
                               ir_margin_px=preset.ir_margin_right_px)  # fmt: skip
    sensor = DepthSensor(preset, intrinsics=window)
    result = refine_poses(sensor, refinable, torch.from_numpy(scene.real[y0:y1, x0:x1].copy()), settings)
    rows = []
    for k, (truth, start) in enumerate(zip(scene.annotated, scene.start)):
        start_deg, start_mm = pose_difference(start.world_T_obj, truth.world_T_obj)
        deg, mm = pose_difference(result.refined[k], truth.world_T_obj)
        decisions = getattr(result, "decisions", [])  # (absent from refine_poses before the acceptance existed)
        decision = decisions[k] if k < len(decisions) else None
        rows.append({"seed": scene.seed, "obj_id": scene.obj_ids[k], "start_deg": start_deg, "start_mm": start_mm,
                     "deg": deg, "mm": mm, "worse": bool(deg > start_deg + 1e-6 or mm > start_mm + 1e-6),
                     "kept": bool(decision is not None and decision.kept and not getattr(result, "kept_start", False)),
                     "decision": None if decision is None else decision.reason(),
                     "gain_sigmas": None if decision is None else decision.gain_sigmas,
                     "visible_estimated": result.visible_fraction[k] if k < len(result.visible_fraction) else None,
                     "candidates_mm": None if decision is None else decision.candidates_mm})  # fmt: skip
    return rows


def _window(objects, intrinsics, margin_px: int) -> tuple[int, int, int, int]:
    """(x0, y0, x1, y1): the image box of the objects' bounding-box corners plus a margin, inside the image."""
    corners = []
    for o in objects:
        lo, hi = o.mesh.bounds
        box = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
        corners.append(box @ o.world_T_obj[:3, :3].T + o.world_T_obj[:3, 3])
    X = np.concatenate(corners)
    u = intrinsics.fx * X[:, 0] / X[:, 2] + intrinsics.cx
    v = intrinsics.fy * X[:, 1] / X[:, 2] + intrinsics.cy
    x0, y0 = max(int(u.min()) - margin_px, 0), max(int(v.min()) - margin_px, 0)
    x1, y1 = min(int(math.ceil(u.max())) + margin_px, intrinsics.width), min(int(math.ceil(v.max())) + margin_px, intrinsics.height)
    return x0, y0, x1, y1


def summary(rows: list[dict]) -> dict:
    """Median rotation (deg) and translation (mm) error, share of objects worse than their start, object count."""
    return {"deg": float(np.median([r["deg"] for r in rows])), "mm": float(np.median([r["mm"] for r in rows])),
            "worse": float(np.mean([r["worse"] for r in rows])), "objects": len(rows)}  # fmt: skip


def run(seeds, settings, verbose: bool = True, layout: str = "grid") -> list[dict]:
    """Refine the scenes of ``seeds`` (``layout``: "grid", :func:`make_scene`; "packed", :func:`make_packed_scene`);
    prints one line per scene when verbose."""
    from ddsgen.preset import load_preset

    meshes, intrinsics = linemod_meshes(), load_preset("kinect_v1").intrinsics
    rows = []
    for seed in seeds:
        scene = (make_packed_scene if layout == "packed" else make_scene)(seed, meshes, intrinsics)
        found = refine_scene(scene, settings)
        for row, seen in zip(found, scene.visible):
            row["visible"] = seen
        rows += found
        if verbose:
            seen = [f" ({100 * r['visible']:.0f} % visible)" if "visible" in r else "" for r in found]
            print(f"  scene {seed}: " + ", ".join(f"obj_id {r['obj_id']} {r['deg']:.2f} deg {r['mm']:.2f} mm"
                                                    f"{' kept' if r['kept'] else ' start'}{v}"
                                                    for r, v in zip(found, seen)), flush=True)  # fmt: skip
    return rows


if __name__ == "__main__":  # tuning runs: python tests/refine_validation.py [seed ...]
    import sys

    from ddsgen.scene_gradients import RefineSettings

    sys.path.insert(0, str(Path(__file__).resolve().parent))
    torch.set_num_threads(1)
    import json

    packed = "--packed" in sys.argv
    dump = next((a[len("--json="):] for a in sys.argv[1:] if a.startswith("--json=")), None)
    chosen = [int(a) for a in sys.argv[1:] if not a.startswith("--")] or list(TUNING_SEEDS)
    rows = run(chosen, RefineSettings(), layout="packed" if packed else "grid")
    print(summary(rows))
    if dump:  # every object's row, for reading the decisions afterwards
        Path(dump).write_text(json.dumps(rows, indent=1, default=float))
