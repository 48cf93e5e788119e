"""The preset's keys, each declared once: the one table every preset key's type, range and use is read from.

A :class:`Parameter` is one key of a sensor preset: its type, unit, a one-line doc (the preset's error messages quote
it), the physical range a preset may give it, its default, and the sensor stage that reads it (:data:`STAGES`). It
may carry three optional sub-records, one per command that moves it:

* ``fit`` (:class:`FitRule`): ``ddsgen fit`` moves it -- the ``--params`` name, the DepthSensor tensor that holds it
  (or none: a 1-D search over its bounds), its bounds, prior width, revert group and finite-difference step;
* ``unpaired`` (:class:`UnpairedSearch`): ``ddsgen fit --unpaired`` searches it -- bounds, scale, grid, the distance
  terms its search minimises;
* ``diagnose`` (:class:`Behaviour`): ``ddsgen diagnose`` offers it as a device-behaviour candidate when a preset has
  it off -- the value that means off, the values tried, what it explains.

Every table those commands use is derived from :data:`PARAMETERS`: the preset schema (``ddsgen.preset.FIELDS``), the
fit's ``SENSOR_PARAMS``, the unpaired fit's ``UNPAIRED_PARAMETERS``, the diagnosis' ``BEHAVIOURS`` and its front-end
cache's key lists. Adding a key to the preset, or letting a command move one, is editing its entry here; no range of a
preset key is written anywhere else (``tests/test_parameters.py`` checks). This module imports nothing of ddsgen.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

#: Marks a key with no default (a preset must give it).
REQUIRED = object()

#: The sensor's stages, in the order a frame passes them; every key belongs to one. "name", "effects" (optional
#: physics, each effect with its own parameters) and "postprocess" (the CNN's weights) are keys of their own.
STAGES = ("name", "camera", "pattern", "ir_lens", "ir", "matcher", "row_smoothing", "validity", "cleanup", "output_window",
          "registration", "effects", "postprocess")  # fmt: skip


@dataclasses.dataclass(frozen=True)
class FitRule:
    """How ``ddsgen fit`` may move a key (the fit's table, ``ddsgen.fit.parameters.SENSOR_PARAMS``, holds these).

    * ``name`` -- the key's name in ``--params``; ``order`` -- its place in that table (the order the help lists the
      names and the device keys are searched in);
    * ``attr`` -- the :class:`~ddsgen.sensor.depth_sensor.DepthSensor` tensor that stores it (``None``: a device key of
      the preset, fitted by a 1-D search over its bounds, :mod:`ddsgen.fit.device_keys`, docs/validation.md);
      ``log`` -- whether that tensor is the logarithm of the physical value; ``tensor_is_ratio`` -- the tensor holds
      the value's ratio to the preset's (the focal scale f / f_preset), not the value;
    * ``bound`` -- where the fitted value must stay: ``("factor", lo, hi)`` = within [lo, hi] x the start (input
      preset's) value, ``("range", lo, hi)`` = within [lo, hi] in the key's units; enforced by projecting the stored
      value back after every Adam step (and bounding the 1-D searches);
    * ``width`` -- the prior's standard deviation in stored units (log units for ``log``): the regulariser
      ``prior_mm * sum ((stored - start) / width)^2`` (mm, like the loss) pulls a parameter the data constrain only
      weakly back to the input preset instead of letting one view's noise drive it to a bound;
    * ``group`` -- parameters that are kept or reverted together (eta_c and the read-noise std only act through their
      ratio, so they are one group);
    * ``step`` -- the finite-difference step (stored units) of the uncertainty estimate (:mod:`ddsgen.fit.uncertainty`);
    * ``key`` -- the preset key (filled in from the :class:`Parameter` the rule belongs to).
    """

    name: str
    order: int
    attr: str | None
    log: bool
    bound: tuple[str, float, float]
    width: float
    group: str
    step: float = 0.05
    tensor_is_ratio: bool = False
    key: str = ""

    def stored_bounds(self, start_stored: float) -> tuple[float, float]:
        """(low, high) of the stored value given the stored start value."""
        kind, lo, hi = self.bound
        if kind == "factor":
            if self.log:
                return start_stored + math.log(lo), start_stored + math.log(hi)
            a, b = start_stored * lo, start_stored * hi
            return min(a, b), max(a, b)
        if kind == "range":
            if self.log:
                return math.log(max(lo, 1e-9)), math.log(hi)
            return lo, hi
        raise ValueError(f"unknown bound kind {kind!r}")

    def describe(self) -> str:
        kind, lo, hi = self.bound
        where = f"x{lo:g}..x{hi:g} of the input" if kind == "factor" else f"{lo:g}..{hi:g}"
        prior = f"{self.width:g} in log" if self.log else f"{self.width:g}"
        return f"{self.key}: {where}; prior width {prior}; group {self.group}"


@dataclasses.dataclass(frozen=True)
class UnpairedSearch:
    """How ``ddsgen fit --unpaired`` searches a key (``ddsgen.fit.unpaired.parameters.UnpairedParameter``).

    ``order`` -- its place in the search (the lattice first: it shapes the noise histogram; the clean-up before the
    fall-off: filled holes change the validity by radius); [``low``, ``high``] --
    the search bounds; ``log`` -- searched in log or linear scale; ``grid`` -- points of the first coarse search;
    ``choices`` -- an integer key searched over these values only (sizes spanning decades, where every integer would
    be a wasted render); ``terms`` -- the distance terms whose weighted sum its search minimises ("total" = all).
    An integer key (``kind`` int) is searched over integers.
    """

    order: int
    low: float
    high: float
    log: bool = True
    grid: int = 7
    choices: tuple = ()
    terms: tuple = ("total",)


@dataclasses.dataclass(frozen=True)
class Behaviour:
    """A device behaviour ``ddsgen diagnose`` offers when a preset has the key at ``off``: the key set to each value
    of ``grid``, judged like a library effect (``ddsgen.diagnose.device_candidates.BEHAVIOURS``).

    ``name`` -- the candidate's name; ``order`` -- its place among the device candidates; ``acts_on`` --
    "disparity": it changes the matches (re-matched, the support plane re-estimated), "validity": it acts after them;
    ``axis`` -- the axis its signature is read along; ``description`` and ``signature`` -- what the device does, and
    what a simulation without it shows against the real frames.
    """

    name: str
    order: int
    off: float
    grid: tuple
    acts_on: str
    axis: str
    description: str
    signature: str


@dataclasses.dataclass(frozen=True)
class Parameter:
    """One preset key (see the module docstring). ``low`` / ``high``: the physical range a preset may give it (``None``:
    unbounded; ``low_open``: the value must be > ``low``, not >=); ``default``: :data:`REQUIRED` when a preset must
    give it."""

    name: str
    kind: type
    unit: str
    stage: str
    doc: str
    low: float | None = None
    high: float | None = None
    low_open: bool = False
    default: Any = REQUIRED
    fit: FitRule | None = None
    unpaired: UnpairedSearch | None = None
    diagnose: Behaviour | None = None

    def __post_init__(self):
        if self.stage not in STAGES:
            raise ValueError(f"{self.name}: unknown stage {self.stage!r} (known: {', '.join(STAGES)})")
        if self.fit is not None:  # the rule names its key, as the fit's tables and reports use it
            object.__setattr__(self, "fit", dataclasses.replace(self.fit, key=self.name))


#: Every preset key by name, in the order of keys in a written preset.
PARAMETERS: dict[str, Parameter] = {p.name: p for p in (
    Parameter("name", str, "", "name",
        "preset name",
    ),
    Parameter("width_px", int, "px", "camera",
        "image width (px)",
        low=8, high=16384,
    ),
    Parameter("height_px", int, "px", "camera",
        "image height (px)",
        low=8, high=16384,
    ),
    Parameter("focal_px", float, "px", "camera",
        "camera intrinsics fx: horizontal focal length f of IR camera and projector (px); disparity = f x baseline"
        " / depth",
        low=0, high=1e5, low_open=True,
        fit=FitRule("focal", order=4, attr="log_focal_scale", log=True, bound=("factor", 0.97, 1.03),
                    width=0.01, group="geometry", step=0.003, tensor_is_ratio=True),
    ),
    Parameter("focal_y_px", float, "px", "camera",
        "camera intrinsics fy: vertical focal length (px); default = focal_px",
        low=0, high=1e5, low_open=True, default=None,
    ),
    Parameter("cx_px", float, "px", "camera",
        "camera intrinsics cx: principal point column (px, 0 = centre of the first pixel); default = (width-1)/2",
        default=None,
    ),
    Parameter("cy_px", float, "px", "camera",
        "camera intrinsics cy: principal point row (px, 0 = centre of the first pixel); default = (height-1)/2",
        default=None,
    ),
    Parameter("baseline_m", float, "m", "camera",
        "projector-camera baseline b along +x (m)",
        low=0, high=2.0, low_open=True,
        fit=FitRule("baseline", order=3, attr="log_baseline", log=True, bound=("factor", 0.95, 1.05),
                    width=0.02, group="geometry", step=0.005),
    ),
    Parameter("z_min_m", float, "m", "camera",
        "nearest measurable depth (m)",
        low=0, high=1000.0, low_open=True,
    ),
    Parameter("z_max_m", float, "m", "camera",
        "farthest measurable depth (m)",
        low=0, high=1000.0, low_open=True,
    ),
    Parameter("block_size_px", int, "px", "matcher",
        "block-matching window w (px, odd)",
        low=3, high=255,
    ),
    Parameter("emitted_intensity", float, "counts mm^2", "ir",
        ("emitted intensity eta_c (IR counts * mm^2 per unit dot intensity; a lit dot is 393 units, so 1.5e6 gives "
         "Landau et al.'s 5.9e8 counts*mm^2)"),
        low=0, high=1e20, low_open=True,
        fit=FitRule("emitted_intensity", order=0, attr="log_emitted_intensity", log=True, bound=("factor", 0.25, 4.0),
                    width=0.7, group="snr", step=0.25),
        unpaired=UnpairedSearch(order=1, low=2e5, high=5e7, grid=8),
    ),
    Parameter("shadow_bias_m", float, "m", "camera",
        "shadow-ray bias xi (m)",
        low=0, high=1.0,
    ),
    Parameter("softargmax_beta", float, "1/ZNCC", "matcher",
        "soft-argmax temperature beta (1/ZNCC)",
        low=0, high=1e4, low_open=True,
        fit=FitRule("beta", order=2, attr="log_beta", log=True, bound=("range", 5.0, 40.0),
                    width=1.0, group="matching", step=0.15),
        unpaired=UnpairedSearch(order=2, low=4.0, high=60.0),
    ),
    Parameter("subpixel_level", int, "", "matcher",
        "sub-pixel refinement level n_sub (steps of 2^-n_sub px)",
        low=0, high=6,
        unpaired=UnpairedSearch(order=0, low=1, high=4, log=False),
    ),
    Parameter("speckle_shape", float, "", "ir",
        "multiplicative speckle ~ Gamma(shape, scale): shape",
        low=0, high=1e4, low_open=True, default=4.54,
        fit=FitRule("speckle_shape", order=11, attr=None, log=True, bound=("factor", 0.25, 4.0),
                    width=0.7, group="speckle", step=0.2),
    ),
    Parameter("speckle_scale", float, "", "ir",
        "multiplicative speckle ~ Gamma(shape, scale): scale",
        low=0, high=1000.0, low_open=True, default=0.196,
        fit=FitRule("speckle_scale", order=5, attr="log_speckle_scale", log=True, bound=("factor", 0.25, 4.0),
                    width=0.7, group="pattern", step=0.2),
    ),
    Parameter("speckle_grain_px", float, "px", "ir",
        "speckle grain: correlation sigma of the speckle field (camera px); 0 = independent per pixel",
        low=0, high=50, default=0.0,
        fit=FitRule("speckle_grain", order=10, attr=None, log=False, bound=("range", 0.0, 3.0),
                    width=0.5, group="speckle", step=0.25),
    ),
    Parameter("speckle_fixed_to_scene", bool, "", "ir",
        "speckle seeded by the scene's geometry (the same static scene shows the same speckle) instead of per frame",
        default=False,
    ),
    Parameter("read_noise_mean_counts", float, "counts", "ir",
        "additive detector noise mean (IR counts)",
        low=-1e4, high=1e4, default=-0.126,
        fit=FitRule("read_noise_mean", order=7, attr="read_noise_mean", log=False, bound=("range", -64.0, 64.0),
                    width=16.0, group="ir_offset", step=1.0),
    ),
    Parameter("read_noise_std_counts", float, "counts", "ir",
        "additive detector noise std (IR counts)",
        low=0, high=1e4, default=10.4,
        fit=FitRule("read_noise_std", order=1, attr="log_read_noise_std", log=True, bound=("factor", 0.25, 4.0),
                    width=0.7, group="snr", step=0.25),
    ),
    Parameter("electrons_per_count", float, "e-/count", "ir",
        ("IR camera gain (photo-electrons per count): > 0 adds photon shot noise, variance = light / gain (counts^2); "
         "0 = read noise only"),
        low=0, high=1e6, default=0.0,
        fit=FitRule("shot_noise_gain", order=12, attr=None, log=True, bound=("factor", 0.25, 4.0),
                    width=0.7, group="snr", step=0.25),
    ),
    Parameter("ambient_counts", float, "counts", "ir",
        "ambient IR level added everywhere (IR counts)",
        low=0, high=1e6, default=0.0,
        fit=FitRule("ambient", order=6, attr="log_ambient", log=True, bound=("range", 1e-6, 255.0),
                    width=3.0, group="ambient", step=0.1),
    ),
    Parameter("projector_falloff_exponent", float, "", "ir",
        "projector beam profile: signal x cos^m(angle off the projector's axis); 0 = flat",
        low=0, high=32, default=0.0,
        fit=FitRule("projector_falloff", order=8, attr=None, log=False, bound=("range", 0.0, 8.0),
                    width=2.0, group="falloff", step=0.5),
        # --unpaired: the beam's fall-off darkens the corners -> searched on validity by radius alone (it also changes
        # the hole rates, but those are scene-dominated: measured, they swung by 0.6 between fall-off values 4 apart
        # while the radius term pointed at the hidden value).
        unpaired=UnpairedSearch(order=7, low=0.0, high=16.0, log=False, grid=5, terms=("radius",)),
        diagnose=Behaviour(
            "beam_falloff", order=4, off=0.0, grid=(2.0, 4.0, 6.0, 8.0), acts_on="disparity", axis="radius",
            description=("The projector's beam is brightest on its axis and fades towards the image corners "
                         "(cos^m off its axis), so the corners' dots are weaker and lose depth first."),
            signature="valid depth in the simulation's corners where the real frame has holes, more on far surfaces",
        ),
    ),
    Parameter("vignetting_exponent", float, "", "ir",
        "IR lens vignetting: signal x cos^n(angle off the camera's axis); 4 = the cos^4 law, 0 = none",
        low=0, high=32, default=0.0,
        fit=FitRule("vignetting", order=9, attr=None, log=False, bound=("range", 0.0, 8.0),
                    width=1.0, group="falloff", step=0.5),
        diagnose=Behaviour(
            "lens_vignetting", order=5, off=0.0, grid=(2.0, 4.0, 6.0, 8.0), acts_on="disparity", axis="radius",
            description=("The IR camera's lens passes less light towards the image corners (cos^n off its axis), so "
                         "the corners' dots are weaker and lose depth first."),
            signature="valid depth in the simulation's corners where the real frame has holes, more on far surfaces",
        ),
    ),
    Parameter("ir_bits", int, "bits", "ir",
        "IR sensor bit depth (clip and quantise to 2^bits - 1)",
        low=4, high=16, default=10,
    ),
    Parameter("min_confidence", float, "ZNCC", "matcher",
        "matcher confidence (best minus second-best ZNCC) below which depth is invalid",
        low=0, high=1, default=0.15,
        unpaired=UnpairedSearch(order=4, low=0.05, high=0.35, log=False),
    ),
    Parameter("shadow_always_invalid", bool, "", "validity",
        ("pixels the projector cannot light are invalid whatever the matcher finds (true: the paper's shadow map); "
         "false: only matching decides, so windows at a shadow's edges keep the surface they see"),
        default=True,
    ),
    Parameter("no_hit_always_invalid", bool, "", "validity",
        ("pixels whose ray meets no surface are invalid whatever the matcher finds (true: the ray cast's mask); false:"
         " only matching decides, so a window at an object's edge over empty space keeps the object's depth"),
        default=True,
    ),
    Parameter("row_smoothing_weight", float, "", "row_smoothing",
        ("the device averages each valid disparity with its left and right neighbours on the same surface (within 1 "
         "px), weights [w, 1 - 2w, w], before its 2^-n px quantum: real depth's noise is grained along the rows "
         "(ddsgen/sensor/row_smoothing.py); 0 = off"),
        low=0, high=0.5, default=0.0,
        # --unpaired: the row smoothing raises the flat-surface noise's correlation with the next pixel in the row (and
        # lowers the column's a little), which beta and the SNR hardly move -> searched on the grain alone. Up to 0.3:
        # beyond ~0.3 the side taps outweigh the centre, and the correlation falls again (no longer a one-valued
        # function of w).
        unpaired=UnpairedSearch(order=3, low=0.0, high=0.3, log=False, terms=("grain",)),
    ),
    Parameter("confirmed_match_zncc", float, "ZNCC", "matcher",
        ("a match that fails min_confidence (a close second peak) is still valid when its best ZNCC exceeds this and a"
         " unique match within its window has its disparity (+-1 px): a window across a depth edge sees two surfaces; "
         "1 = off (uniqueness only)"),
        low=0, high=1, default=1.0,
        fit=FitRule("confirmed_match", order=17, attr=None, log=False, bound=("range", 0.2, 1.0),
                    width=0.5, group="edges", step=0.05),
        diagnose=Behaviour(
            "edge_keeping_matches", order=0, off=1.0, grid=(0.3, 0.35, 0.4, 0.5, 0.6), acts_on="disparity",
            axis="edge_distance",
            description=("The device keeps a match whose window straddles a depth edge (two correlation peaks, so it "
                         "fails the uniqueness test) when a unique match within its window agrees with it, so objects"
                         " keep their edges, fattened by a pixel or two, instead of a ring of holes."),
            signature="depth missing in the simulation, present in the real frame, along depth edges",
        ),
    ),
    Parameter("cleanup_speckle_px", int, "px", "cleanup",
        "device clean-up: valid regions smaller than this are removed (px; 0 = off)",
        low=0, high=1_000_000, default=0,
        fit=FitRule("cleanup_speckle", order=13, attr=None, log=False, bound=("range", 0.0, 400.0),
                    width=100.0, group="cleanup", step=25.0),
        # --unpaired: the clean-up removes valid specks below this size (and holes below cleanup_hole_px) -> searched
        # on the hole-size histogram; a preset without it has it at 0 (off), so the fit can switch it on.
        unpaired=UnpairedSearch(order=6, low=0, high=400, log=False, choices=(0, 25, 50, 100, 200, 400),
                                terms=("holes",)),
        diagnose=Behaviour(
            "speckle_removal", order=3, off=0, grid=(25, 50, 100, 200, 400), acts_on="validity", axis="signal",
            description=("The device removes small isolated regions of valid depth (stray matches in shadows and on "
                         "dark surfaces)."),
            signature="isolated specks of depth in the simulation where the real frame has none",
        ),
    ),
    Parameter("cleanup_max_diff_px", float, "px", "cleanup",
        "device clean-up: neighbours differing by more disparity than this are separate regions (px)",
        low=0, high=1000, low_open=True, default=1.0,
        fit=FitRule("cleanup_max_diff", order=15, attr=None, log=False, bound=("range", 0.25, 4.0),
                    width=1.0, group="cleanup", step=0.25),
    ),
    Parameter("cleanup_hole_px", int, "px", "cleanup",
        "device clean-up: invalid holes smaller than this take their nearest valid pixel's disparity (px; 0 = off)",
        low=0, high=1_000_000, default=0,
        fit=FitRule("cleanup_hole", order=14, attr=None, log=False, bound=("range", 0.0, 32.0),
                    width=8.0, group="cleanup", step=2.0),
        # --unpaired: as cleanup_speckle_px, searched on the hole-size histogram.
        unpaired=UnpairedSearch(order=5, low=0, high=32, log=False, choices=(0, 2, 4, 8, 16, 32), terms=("holes",)),
        diagnose=Behaviour(
            "hole_fill", order=1, off=0, grid=(2, 4, 8, 16, 32), acts_on="validity", axis="signal",
            description=("The device fills invalid holes of a few pixels inside one surface from their nearest valid "
                         "neighbour, so surfaces carry no pepper of single missing pixels."),
            signature="small holes on surfaces in the simulation that the real frame does not have",
        ),
    ),
    Parameter("cleanup_fill_width_px", int, "px", "cleanup",
        ("device clean-up: an invalid pixel whose (2w+1) x (2w+1) window sees a gap at most this wide (w) on average, "
         "to the nearest pixel, takes its nearest valid pixel's disparity along its row or column, at depth edges too "
         "(px; 0 = off): a matching window centred in so narrow a shadow or crack is mostly lit and matches"),
        low=0, high=1000, default=0,
        fit=FitRule("cleanup_fill_width", order=16, attr=None, log=False, bound=("range", 0.0, 8.0),
                    width=4.0, group="cleanup", step=1.0),
        diagnose=Behaviour(
            "narrow_gap_fill", order=2, off=0, grid=(1, 2, 3, 4, 6), acts_on="validity", axis="edge_distance",
            description=("A pixel in a gap so narrow that a matching window centred on it is mostly lit takes its "
                         "nearest valid neighbour's depth: thin projector shadows and cracks keep depth on the "
                         "device."),
            signature="thin bands of missing depth along edges in the simulation, valid in the real frame",
        ),
    ),
    Parameter("output_left_border_px", int, "px", "output_window",
        "the device outputs no depth in this many leftmost columns (px; 0 = none)",
        low=0, high=16384, default=0,
    ),
    Parameter("output_right_border_px", int, "px", "output_window",
        ("the device outputs no depth in this many rightmost columns (px; 0 = none; depth registered to an RGB camera "
         "leaves such a band)"),
        low=0, high=16384, default=0,
    ),
    Parameter("ir_margin_right_px", int, "px", "ir",
        ("the IR camera sees this many columns beyond the depth image's right edge, so matching windows there are "
         "whole (px; 0 = the IR image is the depth image's grid). Takes effect where the caller ray-casts the margin "
         "(render, compare, fit, diagnose, study)"),
        low=0, high=64, default=0,
    ),
    Parameter("registration_ir_offset_m", float, "m", "registration",
        ("depth registered to an RGB camera: the IR camera sits this far left (-x) of the output (RGB) camera, so near"
         " points shift by f b / z px and RGB-view pixels the IR camera does not see get no depth (m; 0 = depth in the"
         " IR camera's own image). Takes effect where the caller casts the IR view (render, compare, fit, diagnose, "
         "study)"),
        low=0, high=1, default=0.0,
    ),
    Parameter("registration_shift_px", float, "px", "registration",
        ("depth registered to an RGB camera: the IR camera's principal point is this many px left of the output "
         "camera's (px; with the IR frame's blind left columns it sets the registered left band, output_left_border_px"
         " + this - f b / z)"),
        low=-1000, high=1000, default=0.0,
    ),
    Parameter("registration_dense", bool, "", "registration",
        ("depth registered to an RGB camera: the device writes each depth to a 2x2 block (OpenNI's dense "
         "registration), so pixels without depth of their own take a lower or right neighbour's: 1-px holes and cracks"
         " close"),
        default=False,
    ),
    Parameter("registration_forward_gap_px", int, "px", "registration",
        ("depth registered to an RGB camera: 0 = map each output pixel back to the IR pixel that sees its ray-cast "
         "surface point; N >= 1 = map each valid IR depth forward by its measured depth, as the device does (z-buffer:"
         " the nearest wins), and close a run of at most N empty pixels between two written pixels whose IR sources "
         "are neighbours (a rasteriser's gap fill): the band right of a near surface stays open when wider than N, and"
         " the near surface the matcher carried past its edge lands next to it"),
        low=0, high=64, default=0,
    ),
    Parameter("registration_forward_fill_rows", int, "px", "registration",
        ("with registration_forward_gap_px: close a run of at most N empty pixels in a column, between two written "
         "pixels, where the IR camera saw a valid surface (its depth was carried elsewhere) or saw nothing; the nearer"
         " source wins. A forward map by rows leaves a dashed line along a near-horizontal depth edge where "
         "consecutive rows' bands overlap; real frames show no such dashes (their isolated dropouts are as often "
         "horizontal as vertical)"),
        low=0, high=16, default=0,
    ),
    Parameter("output_top_border_px", int, "px", "output_window",
        "the device outputs no depth in this many top rows (px; 0 = none)",
        low=0, high=16384, default=0,
    ),
    Parameter("output_bottom_border_px", int, "px", "output_window",
        "the device outputs no depth in this many bottom rows (px; 0 = none)",
        low=0, high=16384, default=0,
    ),
    Parameter("band_rows", int, "rows", "matcher",
        "rows per matching band (bounds matcher memory)",
        low=1, high=16384, default=64,
    ),
    Parameter("pattern", str, "", "pattern",
        "dot pattern: a file in pattern_assets/ or a path (relative to the preset)",
        default="kinect_like_640.png",
    ),
    Parameter("pattern_psf_px", float, "px", "pattern",
        "Gaussian point-spread sigma of a projected dot (px)",
        low=0, high=10, low_open=True, default=0.5,
    ),
    Parameter("pattern_dot_jitter_px", float, "px", "pattern",
        ("projected dots sit this far (uniform, +-half, projector px) off the pattern's pixel lattice; 0 = on the "
         "lattice"),
        low=0, high=2, default=0.0,
    ),
    Parameter("ir_lens_k1", float, "", "ir_lens",
        ("radial distortion of the IR lens: a pixel at normalised distorted position x_d looks along the ray "
         "x_d (1 + k1 r_d^2) (k1 > 0: barrel); dots the reference plane shows move off the matcher's rows on other "
         "surfaces, most in the corners (ddsgen/sensor/ir_lens.py); 0 = a pinhole lens"),
        low=-0.5, high=0.5, default=0.0,
    ),
    Parameter("reference_distance_m", float, "m", "ir_lens",
        ("distance of the plane the device recorded its reference image on, through its own lens (m); with "
         "ir_lens_k1 != 0 surfaces far from it lose depth in the image corners"),
        low=0.2, high=20, default=1.0,
    ),
    Parameter("effects", list, "", "effects",
        "extra physical effects: list of {name: EFFECT, PARAM: value}",
        default=(),
    ),
    Parameter("postprocess", str, "", "postprocess",
        "optional post-processing CNN weights file (relative to the preset)",
        default=None,
    ),
)}  # fmt: skip


def fit_rules() -> dict[str, FitRule]:
    """The keys ``fit`` may move: ``--params`` name -> rule, in the fit's order."""
    rules = sorted((p.fit for p in PARAMETERS.values() if p.fit is not None), key=lambda rule: rule.order)
    return {rule.name: rule for rule in rules}


def unpaired_searches() -> list[tuple[Parameter, UnpairedSearch]]:
    """The keys ``fit --unpaired`` searches, in search order."""
    found = [(p, p.unpaired) for p in PARAMETERS.values() if p.unpaired is not None]
    return sorted(found, key=lambda pair: pair[1].order)


def behaviours() -> list[tuple[Parameter, Behaviour]]:
    """The keys ``diagnose`` offers as device behaviours, in candidate order."""
    found = [(p, p.diagnose) for p in PARAMETERS.values() if p.diagnose is not None]
    return sorted(found, key=lambda pair: pair[1].order)


def stage_keys(stage: str) -> list[str]:
    """The keys of one stage (:data:`STAGES`), in schema order."""
    if stage not in STAGES:
        raise ValueError(f"unknown stage {stage!r} (known: {', '.join(STAGES)})")
    return [p.name for p in PARAMETERS.values() if p.stage == stage]
