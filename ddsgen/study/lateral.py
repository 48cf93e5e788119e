"""Lateral noise (Nguyen, Izadi & Lovell 2012): how far the vertical edges of a flat board wander from a line.

Set-up (camera frame = world frame, OpenCV axes, as in :mod:`ddsgen.study.noise`): a flat board through (0, 0, z),
rotated by alpha about the vertical axis (its right side receding), tall enough to fill the view but only as wide
as places its two vertical edges :data:`EDGE_OFFSET` of the image width left and right of the principal point,
before a fronto-parallel wall :data:`WALL_BEHIND_M` behind its receding edge: each edge is an object's edge before
its background, the projector's shadow on the wall beside the left one.

Measured per (z, alpha) and frame, on the rows of the central half of the image: per row, the board's outermost
valid pixels within a few pixels of its two true edges (:func:`board_edges`); per edge, a straight line fitted to
those columns against the row (:func:`line_residuals`); the lateral noise is the root mean square of the rows'
distances from it, in pixels (Nguyen's definition), pooled over the frames. Also the edges' mean distance outside
the true edges (the fattening). A perfectly rendered straight edge has ~0.29 px of lateral noise from the pixel
grid alone (a uniform rounding error) when it is not exactly vertical; Nguyen measured 0.8 px at small angles,
growing towards grazing (:func:`nguyen_lateral_px`).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from ddsgen.preset import Intrinsics
from ddsgen.scene.sampling import FrameScene, PlacedObject
from ddsgen.sensor.depth_sensor import DepthSensor
from ddsgen.sensor.sensor_cast import cast_for_sensor
from ddsgen.study.noise import simulate_point, study_intrinsics

#: Each edge's image column: this share of the image width left / right of the principal point.
EDGE_OFFSET = 0.25
#: The wall stands this far (m) behind the board's receding edge: both edges are depth jumps of at least this much.
WALL_BEHIND_M = 1.0
#: An edge is looked for this many pixels either side of its true column (the matcher's fattening is a few px).
EDGE_REACH_PX = 16
#: Rows whose edge is farther than this many robust sigmas (at least 2 px) from the first line fit do not steer
#: the second fit; they still count in the residuals.
OUTLIER_SIGMAS = 5.0


def nguyen_lateral_px(angle_deg):
    """Nguyen, Izadi & Lovell 2012 lateral noise of a Kinect V1 (px): 0.8 + 0.035 theta / (pi/2 - theta).

    Independent of the distance in pixels (so growing linearly with it in metres); ``angle_deg`` in [0, 90).
    """
    theta = np.radians(np.asarray(angle_deg, dtype=float))
    return 0.8 + 0.035 * theta / (np.pi / 2 - theta)


def board_halves(z: float, angle_deg: float, intrinsics: Intrinsics) -> tuple[float, float]:
    """(left, right): the lengths (m) of the board's halves from (0, 0, z) along its in-plane x axis.

    Each half is as long as puts its vertical edge on the ray ``EDGE_OFFSET`` of the image width from the principal
    point (at most 3 z: at steep angles the receding edge's ray never meets the board and the half stops there).
    """
    a = math.radians(angle_deg)
    sin_a, cos_a = math.sin(a), math.cos(a)
    t = EDGE_OFFSET * intrinsics.width / intrinsics.fx  # the edges' rays: X / Z = -t and +t
    receding = cos_a - t * sin_a  # <= 0: the ray X / Z = t runs parallel to or away from the board
    right = min(t * z / receding, 3.0 * z) if receding > 0 else 3.0 * z
    return t * z / (cos_a + t * sin_a), right


def wall_depth(z: float, angle_deg: float, intrinsics: Intrinsics) -> float:
    """The depth (m) of the fronto-parallel wall behind the board: :data:`WALL_BEHIND_M` behind its receding edge."""
    return z + board_halves(z, angle_deg, intrinsics)[1] * math.sin(math.radians(angle_deg)) + WALL_BEHIND_M


def board_scene(z: float, angle_deg: float, intrinsics: Intrinsics, albedo: float):
    """A :class:`~ddsgen.scene.sampling.FrameScene`: a board of finite width at distance z, tilted by alpha, before
    a wall (:func:`wall_depth`) of the same albedo.

    The board passes through (0, 0, z) with in-plane x axis (cos a, 0, sin a) and normal (-sin a, 0, cos a); its
    halves are :func:`board_halves` long, and it is tall enough to fill the view.
    """
    import trimesh

    a = math.radians(angle_deg)
    sin_a, cos_a = math.sin(a), math.cos(a)
    left, right = board_halves(z, angle_deg, intrinsics)
    half_y = 0.6 * (z + right * sin_a) + 0.5 * z
    vertices = np.array([[-left, -half_y, 0.0], [right, -half_y, 0.0], [right, half_y, 0.0], [-left, half_y, 0.0]])
    mesh = trimesh.Trimesh(vertices=vertices, faces=np.array([[0, 1, 2], [0, 2, 3]]), process=False)
    world_T_obj = np.eye(4)
    world_T_obj[:3, 0] = [cos_a, 0.0, sin_a]
    world_T_obj[:3, 2] = [-sin_a, 0.0, cos_a]
    world_T_obj[:3, 3] = [0.0, 0.0, z]
    board = PlacedObject(1, "board", f"board:{left + right:g}x{2 * half_y:g}", mesh, world_T_obj, float(albedo))
    wall_z = wall_depth(z, angle_deg, intrinsics)
    size = 2.0 * wall_z  # wider than the view (the Kinect's is about 1.1 x 0.8 z)
    corners = np.array([[-size, -size, 0.0], [size, -size, 0.0], [size, size, 0.0], [-size, size, 0.0]])
    wall_mesh = trimesh.Trimesh(vertices=corners, faces=np.array([[0, 1, 2], [0, 2, 3]]), process=False)
    world_T_wall = np.eye(4)
    world_T_wall[2, 3] = wall_z
    wall = PlacedObject(0, "wall", f"plane:{2 * size:g}x{2 * size:g}", wall_mesh, world_T_wall, float(albedo))
    return FrameScene(objects=[board], background=[wall], world_T_cam=np.eye(4), frame_index=0, seed=0,
                      scene_name=f"board z={z:g} angle={angle_deg:g}")  # fmt: skip


def plane_depth(z: float, angle_deg: float, intrinsics: Intrinsics) -> np.ndarray:
    """(W,) float64: the depth (m) of the board's infinite plane along each image column (inf where the column's
    rays miss the plane): Z = z cos a / (cos a - x sin a), x = (u - cx) / fx."""
    a = math.radians(angle_deg)
    x = (np.arange(intrinsics.width) - intrinsics.cx) / intrinsics.fx
    denominator = math.cos(a) - x * math.sin(a)
    with np.errstate(divide="ignore"):
        return np.where(denominator > 1e-9, z * math.cos(a) / denominator, np.inf)


def edge_columns(z: float, angle_deg: float, intrinsics: Intrinsics) -> tuple[float, float]:
    """(left, right): the image columns (px, continuous) of the board's two vertical edges."""
    a = math.radians(angle_deg)
    left, right = board_halves(z, angle_deg, intrinsics)
    x_left = -left * math.cos(a) / (z - left * math.sin(a))
    x_right = right * math.cos(a) / (z + right * math.sin(a))
    return intrinsics.cx + intrinsics.fx * x_left, intrinsics.cx + intrinsics.fx * x_right


def board_edges(depth: np.ndarray, valid: np.ndarray, plane_z: np.ndarray, wall_z: float, true_left: float,
                true_right: float, reach: int = EDGE_REACH_PX) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """Per row, the board's outermost pixels near its true edges: the first board column within ``reach`` px of
    ``true_left`` and one past the last within ``reach`` px of ``true_right``.

    Holes on the board do not move an edge; a wall pixel misread as the board's near an edge does (it is lateral
    noise as a user sees it).

    Args:
        depth: (H, W) measured depth (m); valid: (H, W) bool.
        plane_z: (W,) the board plane's depth per column (:func:`plane_depth`); a valid pixel is the board's when
            its depth is nearer to it than to ``wall_z``, the wall's.
        true_left, true_right: the edges' columns (:func:`edge_columns`).

    Returns:
        (left, right), each (H,) float64: NaN in rows without a board pixel within reach of that edge.
    """
    on_board = valid & (np.abs(depth - plane_z[None, :]) < np.abs(depth - wall_z))
    width = on_board.shape[1]

    def window(centre):
        return max(int(math.floor(centre)) - reach, 0), min(int(math.ceil(centre)) + reach + 1, width)

    lo, hi = window(true_left)
    near_left = on_board[:, lo:hi]
    left = np.where(near_left.any(axis=1), lo + near_left.argmax(axis=1), np.nan)
    lo, hi = window(true_right)
    near_right = on_board[:, lo:hi]
    right = np.where(near_right.any(axis=1), hi - near_right[:, ::-1].argmax(axis=1), np.nan)
    return left, right


def line_residuals(rows: np.ndarray, columns: np.ndarray) -> np.ndarray:
    """Distances (px, along the row) of edge ``columns`` from the straight line column = a + b row fitted to them.

    Fitted by least squares, then again without the rows farther than :data:`OUTLIER_SIGMAS` robust sigmas (at
    least 2 px) from the first fit; every row's residual from the second line is returned. Needs >= 3 rows.
    """
    design = np.stack([np.ones_like(rows, dtype=np.float64), rows.astype(np.float64)], axis=1)
    coefficients = np.linalg.lstsq(design, columns, rcond=None)[0]
    residual = columns - design @ coefficients
    sigma = 1.4826 * np.median(np.abs(residual - np.median(residual)))
    keep = np.abs(residual) <= max(OUTLIER_SIGMAS * sigma, 2.0)
    if keep.sum() >= 3:
        coefficients = np.linalg.lstsq(design[keep], columns[keep], rcond=None)[0]
    return columns - design @ coefficients


@dataclasses.dataclass
class LateralPoint:
    """Lateral noise at one (z, alpha): root mean square distance (px) of each edge's rows from its line; and the
    fattening: how far (px, mean over the rows) each edge lies outside the board's true edge (the foreground a
    correlation window carries past an edge; negative: inside)."""

    z: float
    angle_deg: float
    left_px: float | None  # the near edge (the board's right side recedes)
    right_px: float | None
    rows: int  # measured rows per edge, summed over the frames
    left_fattening_px: float | None = None
    right_fattening_px: float | None = None

    @property
    def lateral_px(self) -> float | None:
        """Both edges pooled (their mean square), or the one measured."""
        values = [v for v in (self.left_px, self.right_px) if v is not None]
        return math.sqrt(sum(v * v for v in values) / len(values)) if values else None

    @property
    def fattening_px(self) -> float | None:
        """Both edges' fattening averaged, or the one measured."""
        values = [v for v in (self.left_fattening_px, self.right_fattening_px) if v is not None]
        return sum(values) / len(values) if values else None

    def as_json(self) -> dict:
        """The ``lateral`` entries of ``noise.json``: px, with Nguyen's value at this angle."""
        return {"z": self.z, "angle_deg": self.angle_deg, "lateral_px": self.lateral_px, "left_px": self.left_px,
                "right_px": self.right_px, "nguyen_px": float(nguyen_lateral_px(self.angle_deg)),
                "fattening_px": self.fattening_px}  # fmt: skip


class LateralAccumulator:
    """Pools the edge residuals of one (z, alpha) over its frames."""

    def __init__(self, z: float, angle_deg: float, intrinsics: Intrinsics):
        self.z, self.angle_deg = float(z), float(angle_deg)
        self.plane_z = plane_depth(z, angle_deg, intrinsics)
        self.wall_z = wall_depth(z, angle_deg, intrinsics)
        self.true_edges = edge_columns(z, angle_deg, intrinsics)
        height = intrinsics.height
        self.rows = np.arange(height // 4, height - height // 4)
        self.squares = {"left": [], "right": []}
        self.fattening = {"left": [], "right": []}

    def add(self, depth: np.ndarray, valid: np.ndarray) -> None:
        """One frame: depth (H, W) in m, valid (H, W) bool."""
        left, right = board_edges(depth, valid, self.plane_z, self.wall_z, *self.true_edges)
        for name, columns in (("left", left), ("right", right)):
            columns = columns[self.rows]
            measured = np.isfinite(columns)
            # An edge at the image border is the border's, not the board's.
            measured &= (columns > 0) & (columns < depth.shape[1])
            if measured.sum() >= 3:
                self.squares[name].append(line_residuals(self.rows[measured], columns[measured]) ** 2)
                # The measured boundary lies half a pixel before the first (after the last) board column.
                true_left, true_right = self.true_edges
                boundary = columns[measured] - 0.5
                outside = true_left - boundary if name == "left" else boundary - true_right
                self.fattening[name].append(outside)

    def result(self) -> LateralPoint:
        def rms(name):
            squares = self.squares[name]
            return math.sqrt(float(np.concatenate(squares).mean())) if squares else None

        def mean(name):
            values = self.fattening[name]
            return float(np.concatenate(values).mean()) if values else None

        rows = sum(len(s) for side in self.squares.values() for s in side)
        return LateralPoint(self.z, self.angle_deg, rms("left"), rms("right"), rows, mean("left"), mean("right"))


def run_lateral_study(preset, zs, angles_deg, frames: int = 4, seed: int = 0, rows: int | None = None,
                      albedo: float = 0.8, on_frame=None) -> list[LateralPoint]:  # fmt: skip
    """Render and measure the lateral noise at every (z, alpha) of the grid; K = ``frames`` noise seeds each.

    Arguments as :func:`ddsgen.study.noise.run_noise_study` (the same frame seeds, another scene: the board of
    :func:`board_scene`). Returns one :class:`LateralPoint` per (z, alpha), z-major.
    """
    intrinsics = study_intrinsics(preset, rows)
    sensor = DepthSensor(preset, intrinsics=intrinsics).eval()
    points = []
    for z in zs:
        for angle in angles_deg:
            _, geometry = cast_for_sensor(board_scene(z, angle, intrinsics, albedo), intrinsics, preset)
            accumulator = LateralAccumulator(z, angle, intrinsics)
            simulate_point(sensor, geometry, seed, z, angle, frames, accumulator.add, on_frame)
            points.append(accumulator.result())
    return points

