"""Contact sheet of a dataset: what a render (or a folder of real scans) contains, readable at a glance.

One row per shown frame, three panels at the frame's aspect ratio:

* **depth**, colour-mapped (turbo) over one range shared by every row and labelled in metres by
  the colour bar at the bottom; invalid pixels (depth 0) are black, a colour turbo never takes;
* **IR**, auto-exposed: shown as ddsgen writes it (:mod:`ddsgen.io.ir_png`: the frame's 99.9th
  percentile white, square-root encoded); IR PNGs without ``ir_white_counts`` in their record
  (older renders, linear counts) are exposed and encoded the same way here;
* **instances**: the instance mask, one colour per object, background black, with each object's
  bounding box and class name (from the manifest; BOP: from ``mask_visib/`` and ``scene_gt``, or
  without masks the box of each mesh projected with its ground-truth pose, over the depth in grey).

Panels missing from a folder (real scans have no IR; BOP has no instance mask without
``mask_visib/``) say so instead of an image. The title names the sensor preset (``sensor.yaml``),
the folder and the frame ids. The layout is computed in pixels (:class:`Panel`) so that callers
and tests know where each panel sits in the PNG. Drawing uses matplotlib's object API (no pyplot
state) and the sheet is written atomically; same folder, same bytes.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from ddsgen.atomic import atomic_path
from ddsgen.errors import InputError
from ddsgen.io.bop_writer import scans_folder
from ddsgen.io.ir_png import encode_ir, ir_white_counts
from ddsgen.io.manifest import RUN_FILE
from ddsgen.io.png import read_png8, read_png16
from ddsgen.io.scan_frame import ScanFrame
from ddsgen.io.scanfolder import read_scan_folder
from ddsgen.scene.meshes import load_mesh

#: Frames shown by default (evenly spaced over the dataset, first and last included).
DEFAULT_FRAMES = 4
#: Panels are shown at the frame's resolution, scaled to a width in this range (px).
MIN_PANEL_WIDTH_PX, MAX_PANEL_WIDTH_PX = 320, 480
#: Layout of the sheet (px): outer margin, gap between panels, title band, panel-title band, colour bar band.
MARGIN_PX, GAP_PX, TITLE_PX, LABEL_PX, COLORBAR_PX = 12, 10, 46, 24, 84
DPI = 100
PANEL_KINDS = ("depth", "ir", "instances")
#: Share of the valid depths left out at either end of the shared colour range (outliers, far background).
DEPTH_RANGE_QUANTILES = (0.005, 0.995)


@dataclasses.dataclass(frozen=True)
class Panel:
    """Where one panel sits in the sheet: pixel box ``[x0, x1) x [y0, y1)`` (x right, y down) of frame ``frame``."""

    kind: str
    frame: int
    x0: int
    y0: int
    x1: int
    y1: int


@dataclasses.dataclass
class SheetFrame:
    """What one row shows. depth: float32 (H, W) m, 0 = invalid; ir: uint8 (H, W) display-ready IR or None;
    ir_white_counts: counts shown white, if known; instances: int (H, W) ids (0 = background) or None;
    boxes: [(id, class, x, y, w, h)] px."""

    frame: int
    depth: np.ndarray
    ir: np.ndarray | None
    ir_white_counts: float | None
    instances: np.ndarray | None
    boxes: list[tuple]


def choose_frames(count: int, wanted: int) -> list[int]:
    """Indices of ``wanted`` frames evenly spaced over ``count`` (first and last included), ascending."""
    if wanted >= count:
        return list(range(count))
    return sorted({int(round(i)) for i in np.linspace(0, count - 1, wanted)})


def _ddsgen_row(folder: Path, scan: ScanFrame) -> SheetFrame:
    record = scan.record or {}
    shape = (scan.intrinsics.height, scan.intrinsics.width)
    ir = instances = None
    white = record.get("ir_white_counts")
    if record.get("ir") and (folder / record["ir"]).is_file():
        ir = read_png8(folder / record["ir"], shape)
        if white is None:  # linear counts of an older render: expose and encode as ddsgen writes IR now
            ir = encode_ir(ir, ir_white_counts(ir, 255.0))
    if record.get("mask") and (folder / record["mask"]).is_file():
        instances = read_png16(folder / record["mask"], shape).astype(np.int64)
    boxes = [(int(o["id"]), str(o["class"]), *(int(v) for v in o["bbox"])) for o in record.get("objects", [])
             if o.get("bbox") and o["bbox"][2] > 0 and o["bbox"][3] > 0]  # fmt: skip
    return SheetFrame(scan.frame, scan.depth, ir, white, instances, boxes)


def projected_box(obj, intrinsics, shape: tuple[int, int]) -> tuple[int, int, int, int] | None:
    """(x, y, w, h) px of the object's mesh projected with its pose, clipped to the image; None if out of view."""
    mesh = load_mesh(obj.mesh_path, obj.mesh_scale)
    points = mesh.vertices @ obj.cam_T_obj[:3, :3].T + obj.cam_T_obj[:3, 3]
    points = points[points[:, 2] > 1e-3]
    if not len(points):
        return None
    u = intrinsics.fx * points[:, 0] / points[:, 2] + intrinsics.cx
    v = intrinsics.fy * points[:, 1] / points[:, 2] + intrinsics.cy
    x0, x1 = int(np.clip(u.min(), 0, shape[1])), int(np.clip(np.ceil(u.max()), 0, shape[1]))
    y0, y1 = int(np.clip(v.min(), 0, shape[0])), int(np.clip(np.ceil(v.max()), 0, shape[0]))
    return (x0, y0, x1 - x0, y1 - y0) if x1 > x0 and y1 > y0 else None


def _bop_row(scan: ScanFrame) -> SheetFrame:
    """BOP: instances from ``mask_visib/IMAGE_K.png`` (object k of scene_gt is instance k + 1) when present,
    else (real scans such as LineMOD's test split) boxes of the meshes projected with their poses."""
    scene = Path(scan.source_depth_path).parent.parent
    shape = (scan.intrinsics.height, scan.intrinsics.width)
    instances, boxes = None, []
    for k, obj in enumerate(scan.objects):
        path = scene / "mask_visib" / f"{scan.frame:06d}_{k:06d}.png"
        if not path.is_file():
            continue
        visible = read_png8(path, shape) > 0  # BOP masks: 8-bit, 0 / 255
        instances = np.zeros(shape, np.int64) if instances is None else instances
        instances[visible] = obj.id
        if visible.any():
            ys, xs = np.nonzero(visible)
            x, y = int(xs.min()), int(ys.min())
            boxes.append((obj.id, obj.class_name, x, y, int(xs.max()) - x + 1, int(ys.max()) - y + 1))
    if instances is None:
        for obj in scan.objects:
            box = projected_box(obj, scan.intrinsics, shape)
            if box is not None:
                boxes.append((obj.id, obj.class_name, *box))
    return SheetFrame(scan.frame, scan.depth, None, None, instances, boxes)


def preset_name(folder: Path) -> str | None:
    """The ``name`` of the folder's ``sensor.yaml`` (a ddsgen render), or None."""
    import yaml

    path = folder / "sensor.yaml"
    if not path.is_file():
        return None
    try:
        data = yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError):
        return None
    return str(data["name"]) if isinstance(data, dict) and data.get("name") else None


def load_rows(folder: str | Path, frames: int = DEFAULT_FRAMES) -> tuple[str, list[SheetFrame]]:
    """(title, rows) of the contact sheet of ``folder`` (ddsgen scan folder or BOP layout).

    Raises:
        InputError: not a scan folder, no frames, unreadable images, ``frames`` < 1.
    """
    if frames < 1:
        raise InputError(f"--frames: must be >= 1, got {frames}")
    folder = Path(folder)
    scans = read_scan_folder(folder)
    picked = [scans[i] for i in choose_frames(len(scans), frames)]
    root = folder.parent if folder.name == "manifest.jsonl" else folder
    rows = [_ddsgen_row(root, s) if s.layout == "ddsgen" else _bop_row(s) for s in picked]
    name = preset_name(root) or (picked[0].layout if picked else "scans")
    ids = ", ".join(str(r.frame) for r in rows)
    title = f"{name}: {root.resolve().name}/ -- frame{'s' if len(rows) > 1 else ''} {ids} of {len(scans)}"
    return title, rows


def depth_range(rows: list[SheetFrame]) -> tuple[float, float]:
    """Shared colour range (m) of the rows' valid depths, widened outward to 0.1 m steps."""
    valid = np.concatenate([r.depth[r.depth > 0].ravel() for r in rows]) if rows else np.zeros(0)
    if valid.size == 0:
        return 0.0, 1.0
    lo, hi = np.quantile(valid, DEPTH_RANGE_QUANTILES)
    lo, hi = np.floor(lo * 10.0) / 10.0, np.ceil(hi * 10.0) / 10.0
    return float(lo), float(max(hi, lo + 0.1))


def layout(rows: int, width: int, height: int) -> tuple[tuple[int, int], list[list[tuple[int, int, int, int]]], tuple]:
    """Pixel layout: (sheet (W, H), per row the (x0, y0, x1, y1) box of each panel, colour bar box)."""
    scale = float(np.clip(1.0, MIN_PANEL_WIDTH_PX / width, MAX_PANEL_WIDTH_PX / width))
    pw, ph = max(1, round(width * scale)), max(1, round(height * scale))
    sheet_w = 2 * MARGIN_PX + len(PANEL_KINDS) * pw + (len(PANEL_KINDS) - 1) * GAP_PX
    boxes = []
    for r in range(rows):
        y0 = TITLE_PX + r * (LABEL_PX + ph + GAP_PX) + LABEL_PX
        boxes.append([(MARGIN_PX + c * (pw + GAP_PX), y0, MARGIN_PX + c * (pw + GAP_PX) + pw, y0 + ph)
                      for c in range(len(PANEL_KINDS))])  # fmt: skip
    bar_y0 = TITLE_PX + rows * (LABEL_PX + ph + GAP_PX) + 6
    sheet_h = bar_y0 + COLORBAR_PX
    bar = (MARGIN_PX + pw // 8, bar_y0, MARGIN_PX + 2 * pw + GAP_PX - pw // 8, bar_y0 + 14)
    return (sheet_w, sheet_h), boxes, bar


def _instance_colours(ids: list[int]) -> dict[int, tuple]:
    """A distinct colour per instance id (tab20, by the id's rank), RGB in [0, 1]."""
    from matplotlib import colormaps

    palette = colormaps["tab20"]
    return {i: palette(k % 20)[:3] for k, i in enumerate(sorted(ids))}


def draw_sheet(title: str, rows: list[SheetFrame], path: str | Path) -> list[Panel]:
    """Draw the contact sheet of ``rows`` into the PNG ``path`` (atomically); return where its panels are.

    Every row must have the first row's image size.
    """
    from matplotlib import colormaps
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.colors import Normalize
    from matplotlib.figure import Figure
    from matplotlib.patches import Rectangle

    height, width = rows[0].depth.shape
    for r in rows:
        if r.depth.shape != (height, width):
            raise InputError(f"frame {r.frame}: {r.depth.shape[1]}x{r.depth.shape[0]} px, the sheet's frames are "
                             f"{width}x{height}")  # fmt: skip
    (sheet_w, sheet_h), boxes, bar = layout(len(rows), width, height)
    fig = Figure(figsize=(sheet_w / DPI, sheet_h / DPI), dpi=DPI, facecolor="white")
    FigureCanvasAgg(fig)

    def axes_at(box):
        x0, y0, x1, y1 = box  # pixels, y down -> figure fractions, y up
        ax = fig.add_axes((x0 / sheet_w, 1.0 - y1 / sheet_h, (x1 - x0) / sheet_w, (y1 - y0) / sheet_h))
        ax.set_axis_off()
        return ax

    def show(ax, image, **kwargs):
        ax.imshow(image, interpolation="nearest", aspect="auto", extent=(0, width, height, 0), **kwargs)
        ax.set_xlim(0, width)
        ax.set_ylim(height, 0)

    def missing(ax, what):
        ax.add_patch(Rectangle((0, 0), 1, 1, transform=ax.transAxes, facecolor="0.85", edgecolor="none"))
        ax.text(0.5, 0.5, what, transform=ax.transAxes, ha="center", va="center", fontsize=11, color="0.3")

    fig.text(0.5, 1.0 - (TITLE_PX / 2) / sheet_h, title, ha="center", va="center", fontsize=14, weight="bold")
    lo, hi = depth_range(rows)
    norm = Normalize(lo, hi)
    depth_cmap = colormaps["turbo"].with_extremes(bad="black")
    panels = []
    for row, row_boxes in zip(rows, boxes):
        depth_ax, ir_ax, inst_ax = (axes_at(b) for b in row_boxes)
        valid = row.depth > 0
        show(depth_ax, np.ma.masked_array(row.depth, mask=~valid), cmap=depth_cmap, norm=norm)
        labels = [f"frame {row.frame}: depth, {100 * valid.mean():.0f} % valid"]

        if row.ir is None:
            missing(ir_ax, "no IR image")
            labels.append("IR")
        else:
            show(ir_ax, row.ir, cmap="gray", vmin=0, vmax=255)
            labels.append(f"IR, white = {row.ir_white_counts:.0f} counts" if row.ir_white_counts else "IR")

        if row.instances is None and not row.boxes:
            missing(inst_ax, "no instance mask")
            labels.append("instances")
        else:
            ids = [b[0] for b in row.boxes] if row.instances is None else np.unique(row.instances).tolist()
            colours = _instance_colours([i for i in ids if i > 0])
            if row.instances is None:  # boxes from poses only: drawn over the depth in grey for context
                show(inst_ax, np.ma.masked_array(row.depth, mask=~valid), cmap=colormaps["gray"].with_extremes(
                    bad="black"), norm=norm)  # fmt: skip
                labels.append(f"{len(row.boxes)} projected mesh box{'es' if len(row.boxes) != 1 else ''} (no mask)")
            else:
                rgb = np.zeros((height, width, 3))
                for i, c in colours.items():
                    rgb[row.instances == i] = c
                show(inst_ax, rgb)
                labels.append(f"{len(colours)} instance{'s' if len(colours) != 1 else ''}, boxes, classes")
            for obj_id, name, x, y, w, h in row.boxes:
                colour = colours.get(obj_id, (1.0, 1.0, 1.0))
                inst_ax.add_patch(Rectangle((x, y), w, h, fill=False, edgecolor=colour, linewidth=1.5))
                inst_ax.text(x + 1, y + 1, name, color="black", fontsize=8, va="top", ha="left", clip_on=True,
                             bbox={"facecolor": colour, "edgecolor": "none", "pad": 1.0})  # fmt: skip

        for kind, box, label in zip(PANEL_KINDS, row_boxes, labels):
            x0, y0, x1, _ = box
            fig.text(x0 / sheet_w, 1.0 - (y0 - 5) / sheet_h, label, ha="left", va="bottom", fontsize=10)
            panels.append(Panel(kind, row.frame, *box))

    bar_ax = fig.add_axes((bar[0] / sheet_w, 1.0 - bar[3] / sheet_h, (bar[2] - bar[0]) / sheet_w,
                           (bar[3] - bar[1]) / sheet_h))  # fmt: skip
    from matplotlib.cm import ScalarMappable

    colorbar = fig.colorbar(ScalarMappable(norm=norm, cmap=depth_cmap), cax=bar_ax, orientation="horizontal")
    colorbar.set_label("depth (m), one scale for every row; black = no depth", fontsize=10)
    fig.text(0.5, 6 / sheet_h, "IR auto-exposed per frame (99.9th percentile white, square-root encoded); "
             "instances: the mask, boxes and classes of the labels", ha="center", va="bottom", fontsize=9,
             color="0.3")  # fmt: skip
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=DPI, format="png", metadata={"Software": None})
    return panels


def default_sheet_path(folder: str | Path) -> Path:
    """Where the contact sheet of ``folder`` goes when no path is given: ``folder/preview.png`` for a folder that
    ``ddsgen render`` wrote (its run.json, under the scans folder in the BOP layout), else ``preview_NAME.png`` in
    the current folder: a dataset that ddsgen did not make (downloaded, real scans) is never written into."""
    folder = Path(folder)
    if (folder / RUN_FILE).is_file() or (scans_folder(folder) / RUN_FILE).is_file():
        return folder / "preview.png"
    return Path(f"preview_{folder.resolve().name or 'root'}.png")


def write_preview(folder: str | Path, out: str | Path | None = None,
                  frames: int = DEFAULT_FRAMES) -> tuple[Path, list[Panel]]:
    """Write the contact sheet of the scan folder ``folder`` to ``out`` (default :func:`default_sheet_path`).

    Returns (path written, panels). Raises :class:`InputError` on bad input, before writing anything.
    """
    out = Path(out) if out is not None else default_sheet_path(folder)
    if out.suffix.lower() != ".png":
        raise InputError(f"--out: {out}: the contact sheet is a PNG, name it *.png")
    if out.is_dir():
        raise InputError(f"--out: {out}: is a folder, expected a *.png file")
    title, rows = load_rows(folder, frames)
    try:
        panels = draw_sheet(title, rows, out)
    except OSError as error:
        raise InputError(f"--out: {out}: cannot write ({error.strerror or error})") from None
    return out, panels
