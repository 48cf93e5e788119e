"""The device's output window: the columns and rows at the image border where it outputs no depth.

A raw Kinect V1 outputs no depth in its leftmost 8 columns (its matcher's window); a PrimeSense
device that registers depth to its RGB camera (IC-BIN, many BOP datasets) leaves bands at the
right, top and bottom where the RGB view is not covered by the IR camera (measured on the nine
IC-BIN frames: right 33-39 columns, top 11 rows, bottom 10 rows, left none). The window is a
property of the device's output, not of the scene: an image column empty in every frame of a
folder is the window, whatever the scenes show (:func:`measure_output_window`).

Widths are in pixels of the preset's full image. A crop (``compare --crop``) sees the part of the
band that falls inside it: its offset in the full image is the shift of its principal point.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ddsgen.sensor.registration import ir_frame_validity, is_registered

#: Preset keys of the window, in the order of :class:`OutputWindow`'s fields.
WINDOW_KEYS = ("output_left_border_px", "output_right_border_px", "output_top_border_px", "output_bottom_border_px")


@dataclass(frozen=True)
class OutputWindow:
    """Border bands without depth (px of the full image): left, right (columns), top, bottom (rows)."""

    left: int = 0
    right: int = 0
    top: int = 0
    bottom: int = 0

    @classmethod
    def of(cls, preset) -> "OutputWindow":
        """The window a preset declares (keys it lacks count as 0)."""
        return cls(*(int(getattr(preset, key, 0) or 0) for key in WINDOW_KEYS))

    def as_keys(self) -> dict[str, int]:
        """{preset key: width} for ``SensorPreset.replace``."""
        return dict(zip(WINDOW_KEYS, (self.left, self.right, self.top, self.bottom)))

    def rescaled(self, width: int, height: int, to_width: int, to_height: int) -> "OutputWindow":
        """The same bands in the pixels of an image of ``to_width`` x ``to_height`` (this one's: ``width`` x
        ``height``), rounded to whole pixels."""
        sx, sy = to_width / width, to_height / height
        return OutputWindow(*(int(round(px * s)) for px, s in
                              ((self.left, sx), (self.right, sx), (self.top, sy), (self.bottom, sy))))  # fmt: skip

    def largest_difference(self, other: "OutputWindow") -> int:
        """The largest difference of one side's band to ``other``'s (px)."""
        return max(abs(a - b) for a, b in zip(self.as_keys().values(), other.as_keys().values()))

    def describe(self) -> str:
        """``left 8, right 0, top 0, bottom 0 px``."""
        return f"left {self.left}, right {self.right}, top {self.top}, bottom {self.bottom} px"

    @property
    def is_full(self) -> bool:
        """True when the device outputs depth up to every border."""
        return not (self.left or self.right or self.top or self.bottom)

    def inside(self, height: int, width: int, full_height: int, full_width: int, x0: int = 0,
               y0: int = 0) -> np.ndarray:  # fmt: skip
        """(height, width) bool: pixels of an image (the full one, or a crop whose pixel (0, 0) is the
        full image's (x0, y0)) where the device outputs depth."""
        columns = np.arange(width) + x0
        rows = np.arange(height) + y0
        col_ok = (columns >= self.left) & (columns < full_width - self.right)
        row_ok = (rows >= self.top) & (rows < full_height - self.bottom)
        return row_ok[:, None] & col_ok[None, :]


#: In a registered device's IR frame, a column (row) valid at most this fraction as often as the median column
#: (row) is empty too: the band shows a few pixels that depth edges map there (a nearer surface's depth on a
#: farther pixel). Measured on 6 table-scene frames at 320x240: 2-3.5 % of a band column against 88 % inside,
#: which read the right band 4 px narrow under the 1 % rule alone; the ten real frames read the same either way.
RELATIVE_EMPTY_SHARE = 0.05


def measure_output_window(valid_frames, max_valid_share: float = 0.01, relative_share: float = 0.0) -> OutputWindow:
    """The window of the device that wrote these frames: at each side, the run of outermost columns
    (rows) whose pixels are valid in at most ``max_valid_share`` of all frames together (or in at most
    ``relative_share`` times the median column's (row's) share).

    Scene content cannot empty a whole column of every frame; the device's window does. The band
    is the part common to all frames (a registered device's right band also moves with depth by a
    few px: the always-empty part is taken).

    Args:
        valid_frames: sequence of (H, W) bool maps (depth > 0) of one device, all the same size.
    """
    frames = [np.asarray(v, bool) for v in valid_frames]
    if not frames:
        raise ValueError("measure_output_window needs at least one frame")
    share = np.mean(frames, axis=0)
    columns, rows = share.mean(axis=0), share.mean(axis=1)

    def run(profile: np.ndarray) -> int:
        empty = profile <= max(max_valid_share, relative_share * float(np.median(profile)))
        return int(len(profile) if empty.all() else np.argmin(empty))

    return OutputWindow(left=run(columns), right=run(columns[::-1]), top=run(rows), bottom=run(rows[::-1]))


def measure_device_window(depth_frames, preset, max_valid_share: float = 0.01) -> OutputWindow:
    """The preset's window keys measured on real depth frames (H, W, m, 0 = invalid) in the preset's camera.

    Unregistered, the window is the frames' own (:func:`measure_output_window`). For a device registered to an
    RGB camera (:mod:`ddsgen.sensor.registration`) the keys are the IR frame's bands, which the registration
    moves by f b_r / Z - s: each frame's valid pixels are mapped back into the IR frame
    (:func:`~ddsgen.sensor.registration.ir_frame_validity`) and the bands are measured there. Right, top and
    bottom as unregistered, except that a few stray pixels (:data:`RELATIVE_EMPTY_SHARE`) do not end a band.
    The left band is the most common first IR column of a row: far rows show the band's edge, near rows (whose
    output edge maps further right) and rows with a hole at the edge start later, and a shift-only registration
    is a few pixels off on some rows of real frames (LineMOD cat: rows at 2 m start 3-4 px left of the rest),
    which the 1 % rule would take as the band. The dense registration's splat shows a
    band's last column (left) and row (top) with its neighbour's depth: those sides are one pixel wider than
    the maps show.
    """
    depths = [np.asarray(d) for d in depth_frames]
    if not is_registered(preset):
        return measure_output_window([d > 0 for d in depths], max_valid_share)
    maps = [ir_frame_validity(d, preset) for d in depths]
    window = measure_output_window(maps, max_valid_share, RELATIVE_EMPTY_SHARE)
    firsts = np.concatenate([np.argmax(m[m.any(axis=1)], axis=1) for m in maps])
    left = int(np.bincount(firsts).argmax()) if len(firsts) else window.left
    splat = int(bool(preset.registration_dense))
    return OutputWindow(left=left + splat, right=window.right, top=window.top + splat * (window.top > 0),
                        bottom=window.bottom)  # fmt: skip
