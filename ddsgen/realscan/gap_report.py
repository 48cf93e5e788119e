"""The result of a comparison (:func:`ddsgen.realscan.gap.gap`): the gap, its noise floor and parts, and the words
that define them. The figures (:mod:`ddsgen.realscan.plots`) and the report writer read it."""

from __future__ import annotations

import dataclasses
import math

from ddsgen.realscan.region import RULE


def round_or_none(x, nd=4):
    """``x`` rounded to ``nd`` decimals, None when not finite (JSON has no NaN)."""
    x = float(x)
    return round(x, nd) if math.isfinite(x) else None


@dataclasses.dataclass
class GapReport:
    """Result of :func:`ddsgen.realscan.gap.gap`.

    gap: headline (mm); noise_floor: gap between the simulation and other units' (mm, NaN if not computed),
    averaged over ``len(noise_floor_draws)`` units per frame; noise_floor_draws: the floor against each of them
    (mean over frames, mm), whose spread is the floor's own scatter;
    frames: per-frame dicts (name, gap, noise_floor when computed, depth_mm, gradient_mm, validity_mm, bias_mm,
    spread_mm, confusion, pixels); parts: aggregated bins and confusion; maps: per-frame (name, sim depth,
    real depth, region) numpy arrays when requested (for residual plots); realism: the hole and
    quantisation statistics of real and sim (:mod:`ddsgen.realscan.realism`), when computed.
    """

    gap: float
    noise_floor: float
    frames: list[dict]
    parts: dict
    region: str = "all"
    maps: list[dict] = dataclasses.field(default_factory=list)
    realism: dict | None = None
    noise_floor_draws: list[float] = dataclasses.field(default_factory=list)
    local: dict | None = None  # the local patches (ddsgen.realscan.local_patches.patch_summary), with the floor
    objects: dict | None = None  # region "all": gap, noise_floor, excess (mm) of the annotated objects' pixels alone

    @property
    def excess(self) -> float:
        return self.gap - self.noise_floor if math.isfinite(self.noise_floor) else float("nan")

    def to_dict(self) -> dict:
        return {"gap": round_or_none(self.gap), "noise_floor": round_or_none(self.noise_floor), "excess": round_or_none(self.excess),
                "noise_floor_draws": [round_or_none(v) for v in self.noise_floor_draws], "units": "mm", "region": self.region, "definition": DEFINITION, "region_rule": region_rule(self.region),
                "frames": self.frames,
                "parts": self.parts, **({"realism": self.realism} if self.realism else {}),
                **({"local_patches": self.local} if self.local else {}),
                **({"objects_only": self.objects} if self.objects else {})}  # fmt: skip


DEFINITION = (
    "gap = mean over frames of D + G + V (mm) on the modelled, plausible region: D = mean Huber(5 mm) of the local "
    "mean of sim - real (both valid, clipped to +-50 mm) over a window of 1.5 deg of view (15 px at 640 x 480, "
    "at least 5 px); G = Huber of the difference of mean |Sobel(depth - clean)| of sim and real per 0.25 m depth "
    "bin; D only where one disparity quantum is a depth step of at most 50 mm (Kinect V1 at 1/8 px: nearer than "
    "4.14 m); V = 100 mm x mean squared difference of the local valid rates (same window). "
    "noise_floor = the same between the simulation and another unit of the same sensor model (its own noise draw, "
    "laser speckle and dot positions, as the real unit has its own); excess = gap - noise_floor."
)


#: Said wherever a gap beyond the noise floor comes out negative.
BELOW_FLOOR = ("below the floor: the real scans are as close to the simulation as another simulated unit is "
               "(the floor scatters from unit to unit, by tens of percent on one frame or a small region)")


def region_rule(region: str) -> str:
    """The compare region's rule in words (comparison.json and the report state it)."""
    return RULE + ("; --region objects: only the posed objects' pixels of it" if region == "objects" else "")
