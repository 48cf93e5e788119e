"""Sample one frame's scene: which objects, where they rest, where the camera is.

World frame: z up, the ground plane is z = 0, the clutter is dropped around the
origin, an optional floor lies ``depth`` below the ground (which is then a table top), an
optional back wall stands at y = +distance facing -y (on the floor if there is one). The camera pose
``world_T_cam`` has OpenCV axes (x right, y down, z forward) and looks at the clutter.

Randomness of frame ``i`` comes only from ``(seed, i)`` (and the scene list):

* the scene (template) a frame uses is ``scene_list.scene_for_frame(i)``, no randomness;
* the object layout is shared by the frames of one block (``frames`` consecutive frames,
  like one BOP scene seen from several views) and drawn from
  ``default_rng([seed, block_start, 1])``;
* the camera pose is drawn from ``default_rng([seed, i])``.

So any worker can build frame ``i`` alone, in any order, and get the same scene.

Objects are dropped without interpenetration: each rests on the ground in a stable
pose of its convex hull (or upright, as modelled) with its lowest point at z = 0 and a
random yaw; its footprint (the 2-D convex hull of its vertices seen from above) must
keep ``min_gap`` from every footprint already placed (separating-axis test, :mod:`ddsgen.scene.footprints`), from
the wall and from the ground's edges (nothing hangs over a table's edge), else the
position is redrawn (``max_tries`` times, then the object is left out). Objects that
extend only upwards from disjoint convex footprints cannot touch.
"""

from __future__ import annotations

import dataclasses
import functools
import math

import numpy as np

from ddsgen.scene import shapes
from ddsgen.scene.distractors import DistractorSpec
from ddsgen.scene.footprints import Footprint, footprints_separated, rest_poses
from ddsgen.scene.object_spec import ObjectSpec
from ddsgen.scene.scenelist import SceneList, SceneSpec

UP = np.array([0.0, 0.0, 1.0])


@dataclasses.dataclass
class PlacedObject:
    """A mesh placed in the world. ``id`` >= 1 for objects (instance mask value), 0 for background."""

    id: int
    class_name: str
    mesh_ref: str  # file path, "shape:NAME(params)", or "plane:WxH" for background
    mesh: object  # trimesh.Trimesh, object frame, metres
    world_T_obj: np.ndarray  # (4, 4) float64
    albedo: float
    mesh_scale: float = 1.0  # file units -> metres (what a reader of mesh_ref must apply)


@dataclasses.dataclass
class FrameScene:
    """Everything the ray caster needs for one frame."""

    objects: list[PlacedObject]
    background: list[PlacedObject]
    world_T_cam: np.ndarray  # (4, 4) float64, OpenCV camera axes
    frame_index: int
    seed: int
    scene_name: str = ""
    scene_index: int = 0

    @property
    def cam_T_world(self) -> np.ndarray:
        return invert_pose(self.world_T_cam)

    def cam_T_obj(self, placed: PlacedObject) -> np.ndarray:
        return self.cam_T_world @ placed.world_T_obj


def invert_pose(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid 4x4 transform."""
    R, t = T[:3, :3], T[:3, 3]
    out = np.eye(4)
    out[:3, :3] = R.T
    out[:3, 3] = -R.T @ t
    return out


def _rot_z(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    T = np.eye(4)
    T[:2, :2] = [[c, -s], [s, c]]
    return T


def _translation(xyz) -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = xyz
    return T


# ----------------------------------------------------------------------------------------------------------------
# Layout (shared by the frames of one block) and camera (per frame)


def _uniform(rng: np.random.Generator, lo_hi) -> float:
    lo, hi = lo_hi
    return float(lo) if lo == hi else float(rng.uniform(lo, hi))


def _pick(rng: np.random.Generator, pool: tuple[ObjectSpec, ...], unique: bool, used: set[int]) -> int | None:
    weights = np.array([0.0 if (unique and i in used) else o.weight for i, o in enumerate(pool)])
    if weights.sum() <= 0:
        return None
    return int(rng.choice(len(pool), p=weights / weights.sum()))


@functools.lru_cache(maxsize=8)
def _layout(scene: SceneSpec, seed: int, block_start: int):
    """(objects, background, target-box) of one block; cached per process (pure function of its arguments)."""
    rng = np.random.default_rng([seed, block_start, 1])
    clutter = scene.clutter
    count = int(rng.integers(clutter.count[0], clutter.count[1] + 1))
    half = np.asarray(clutter.area) / 2.0
    wall_y = scene.wall.distance if scene.wall is not None else math.inf
    # The ground's half extent less the gap (x, y): footprints stay on it.
    ground_half = np.full(2, math.inf)
    if scene.ground is not None:
        ground_half = np.asarray(scene.ground.size) / 2.0 - clutter.min_gap
    placed: list[tuple[PlacedObject, Footprint]] = []
    used: set[int] = set()

    def fits(footprint: Footprint) -> bool:
        return _footprint_fits(footprint, wall_y, ground_half, [other for _, other in placed], clutter.min_gap)

    for _ in range(count):
        index = _pick(rng, scene.objects, clutter.unique, used)
        if index is None:
            break
        spec = scene.objects[index]
        dropped = _drop(rng, spec, np.zeros(2), half, clutter.max_tries, fits)
        if dropped is None:
            continue  # no room: leave this one out
        used.add(index)
        world_T_obj, albedo, world_footprint = dropped
        obj = PlacedObject(
            id=len(placed) + 1,
            class_name=spec.class_name,
            mesh_ref=spec.mesh_ref,
            mesh=spec.mesh(),
            world_T_obj=world_T_obj,
            albedo=albedo,
            mesh_scale=spec.scale,
        )
        placed.append((obj, world_footprint))

    # Albedos drawn in this order (ground, wall, floor): scene lists without a floor keep their random streams.
    background = []
    if scene.ground is not None:
        background.append(_plane_object("ground", scene.ground.size, np.eye(4), _uniform(rng, scene.ground.albedo)))
    if scene.wall is not None:
        wall = scene.wall
        # plane in x-y (normal +z) -> rotate +90 deg about x: (x, y, 0) -> (x, 0, y), normal -> -y
        T = np.eye(4)
        T[:3, :3] = [[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]]
        bottom = -scene.floor.depth if scene.floor is not None else 0.0
        T[:3, 3] = [0.0, wall.distance, bottom + wall.height / 2.0]
        background.append(_plane_object("wall", (wall.width, wall.height), T, _uniform(rng, wall.albedo)))
    if scene.floor is not None:
        floor_T = _translation([0.0, 0.0, -scene.floor.depth])
        background.append(_plane_object("floor", scene.floor.size, floor_T, _uniform(rng, scene.floor.albedo)))

    for group_index, group in enumerate(scene.distractors):
        background.extend(_distractors(scene, group, np.random.default_rng([seed, block_start, 2, group_index]),
                                       [footprint for _, footprint in placed]))  # fmt: skip

    objects = [obj for obj, _ in placed]
    if objects:
        corners = np.concatenate([_world_bounds(o) for o in objects])
        lo, hi = corners.min(axis=0), corners.max(axis=0)
        target = (lo + hi) / 2.0
    else:
        target = np.zeros(3)
    return tuple(objects), tuple(background), target


def _footprint_fits(footprint: Footprint, wall_y: float, half_extent: np.ndarray, others, gap: float) -> bool:
    """True where a world footprint keeps ``gap`` from the wall at y = ``wall_y``, lies within ``+-half_extent``
    (x, y; the surface's half size less the gap) and keeps ``gap`` from every footprint of ``others``."""
    polygon = footprint.polygon
    return (polygon[:, 1].max() <= wall_y - gap and not np.any(np.abs(polygon) > half_extent)
            and all(footprints_separated(footprint, other, gap) for other in others))  # fmt: skip


def _drop(rng: np.random.Generator, spec: ObjectSpec, centre: np.ndarray, half: np.ndarray, max_tries: int, fits,
          base_z: float = 0.0, max_height: float = math.inf):  # fmt: skip
    """Drop one object of ``spec``: a resting pose, a yaw and an albedo, then positions uniform in ``centre`` +-
    ``half`` (x, y; m) until ``fits(footprint)`` (a world :class:`Footprint`). Returns ``(world_T_obj, albedo,
    footprint)`` with the object's lowest point at ``base_z``, or None (no room in ``max_tries``, or the drawn
    pose is taller than ``max_height``)."""
    poses, probs = rest_poses(spec.mesh_ref, spec.scale, spec.rest)
    pose = poses[int(rng.choice(len(poses), p=probs))] if len(poses) > 1 else poses[0]
    yaw = float(rng.uniform(0.0, 2.0 * math.pi))
    c, s = math.cos(yaw), math.sin(yaw)
    footprint = pose.footprint @ np.array([[c, s], [-s, c]])  # rotate rows by yaw
    albedo = _uniform(rng, spec.albedo)
    if pose.height > max_height:
        return None
    for _try in range(max_tries):
        xy = centre + rng.uniform(-half, half)
        world_footprint = Footprint.of(footprint + xy)
        if fits(world_footprint):
            world_T_obj = _translation([xy[0], xy[1], base_z]) @ _rot_z(yaw) @ _translation(-pose.offset) @ pose.rotation
            return world_T_obj, albedo, world_footprint
    return None


def _distractors(scene: SceneSpec, group: DistractorSpec, rng: np.random.Generator,
                 clutter: list[Footprint]) -> list[PlacedObject]:  # fmt: skip
    """One distractor group's objects (background, id 0): footprints apart from each other and from the clutter's
    (``clutter``: world footprints), inside the surface they stand on and in front of the wall. On the floor
    they stay off the table's footprint and below its top (taller poses are left out), so they never hide the
    table top from a camera above it."""
    wall_y = scene.wall.distance if scene.wall is not None else math.inf
    gap = group.min_gap
    taken = list(clutter)
    if group.surface == "floor":
        base_z, max_height = -scene.floor.depth, scene.floor.depth - gap
        bounds = np.asarray(scene.floor.size) / 2.0 - gap
        if scene.ground is not None:
            gx, gy = np.asarray(scene.ground.size) / 2.0
            table = np.array([[-gx, -gy], [gx, -gy], [gx, gy], [-gx, gy]])
            taken.append(Footprint.of(table))  # the table's footprint
    else:
        base_z, max_height = 0.0, math.inf
        bounds = np.asarray(scene.ground.size) / 2.0 - gap

    def fits(footprint: Footprint) -> bool:
        return _footprint_fits(footprint, wall_y, bounds, taken, gap)

    centre, half = np.asarray(group.centre), np.asarray(group.area) / 2.0
    placed = []
    for _ in range(int(rng.integers(group.count[0], group.count[1] + 1))):
        spec = group.objects[_pick(rng, group.objects, False, set())]
        dropped = _drop(rng, spec, centre, half, group.max_tries, fits, base_z, max_height)
        if dropped is None:
            continue
        world_T_obj, albedo, world_footprint = dropped
        taken.append(world_footprint)
        placed.append(PlacedObject(0, spec.class_name, spec.mesh_ref, spec.mesh(), world_T_obj, albedo, spec.scale))
    return placed


def _plane_object(name: str, size, world_T_obj: np.ndarray, albedo: float) -> PlacedObject:
    """A background rectangle (id 0) of ``size`` (width, height) m, in its own x-y plane."""
    sx, sy = size
    return PlacedObject(0, name, f"plane:{sx:g}x{sy:g}", shapes.plane_mesh(sx, sy), world_T_obj, albedo)


def _world_bounds(obj: PlacedObject) -> np.ndarray:
    lo, hi = obj.mesh.bounds
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    return corners @ obj.world_T_obj[:3, :3].T + obj.world_T_obj[:3, 3]


def look_at(eye, target, up=UP, roll: float = 0.0) -> np.ndarray:
    """``world_T_cam`` with OpenCV axes: z towards ``target``, x right, y down (image), rolled by ``roll`` rad."""
    eye, target = np.asarray(eye, dtype=float), np.asarray(target, dtype=float)
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-9:  # looking straight along up: pick any right vector
        x = np.cross(z, [0.0, 1.0, 0.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    if roll:
        c, s = math.cos(roll), math.sin(roll)
        x, y = c * x + s * y, -s * x + c * y
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = x, y, z, eye
    return T


def sample_camera(scene: SceneSpec, target: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """A camera pose around ``target`` following the scene's camera rule."""
    cam = scene.camera
    look = np.asarray(target, dtype=float) + rng.uniform(-cam.look_at_jitter, cam.look_at_jitter, size=3)
    distance = _uniform(rng, cam.distance)
    elevation = math.radians(_uniform(rng, cam.elevation_deg))
    azimuth = math.radians(_uniform(rng, cam.azimuth_deg))
    roll = math.radians(_uniform(rng, cam.roll_deg))
    direction = np.array(
        [math.cos(elevation) * math.sin(azimuth), -math.cos(elevation) * math.cos(azimuth), math.sin(elevation)]
    )
    return look_at(look + distance * direction, look, roll=roll)


def sample_frame(scene_list: SceneList, frame_index: int, seed: int) -> FrameScene:
    """The scene of frame ``frame_index``: a pure function of ``(scene_list, frame_index, seed)``."""
    frame_index, seed = int(frame_index), int(seed)
    if seed < 0:
        raise ValueError(f"seed must be >= 0, got {seed}")
    scene_index, block_start = scene_list.scene_for_frame(frame_index)
    scene = scene_list.scenes[scene_index]
    objects, background, target = _layout(scene, seed, block_start)
    world_T_cam = sample_camera(scene, target, np.random.default_rng([seed, frame_index]))
    copy = lambda p: dataclasses.replace(p, world_T_obj=p.world_T_obj.copy())  # noqa: E731
    return FrameScene(
        objects=[copy(o) for o in objects],
        background=[copy(b) for b in background],
        world_T_cam=world_T_cam,
        frame_index=frame_index,
        seed=seed,
        scene_name=scene.name,
        scene_index=scene_index,
    )
