"""Diagnosis: find where simulation and measurement disagree, name the missing effect, add it, show the gap shrink.

The loop (:func:`diagnose`):

0. **Output window** (:mod:`~ddsgen.diagnose.window`): border bands without depth in every real frame are
   measured and used by the model when they differ from the preset's (not an effect: a format).
1. **Base fit.** The base sensor parameters are fitted on the fit frames with the fit
   machinery (:func:`ddsgen.fit.fitting.fit_sensor`); the held-out gap (the ``compare``
   metric, :func:`ddsgen.realscan.gap.gap`, and its noise floor) of that model is the baseline.
2. **Residual analysis** (:mod:`ddsgen.diagnose.residuals`): bias and validity disagreement
   binned by depth, incidence angle, image radius, row, column, distance to depth edges and
   IR signal; per axis the structure beyond noise (bootstrap over frames).
3. **Candidates.** Every library effect not yet in the model is added in turn and its
   parameters are fitted on the fit frames, maximising the credited fall of the gap (below):
   depth effects start from their signature read off the residual
   (:func:`~ddsgen.diagnose.candidates.signature_guess`: a median or a least-squares fit, no
   extra simulation), validity effects from a coarse grid; a local search refines either.
   Then the held-out gap and noise floor it leaves are measured. Besides the library effects, the device
   behaviours the preset has switched off (:mod:`~ddsgen.diagnose.device_candidates`: keeping windows across
   depth edges, filling small holes and narrow gaps, removing specks) are candidates too, searched on a grid
   of their preset key.
4. **Acceptance** (:data:`~ddsgen.diagnose.acceptance.RULE`). Accepted: named, added, the base
   parameters refitted with it, and the loop repeats with the remaining effects -- unless the held-out gap
   is now below its noise floor (averaged over units): the real scans are then as close to the model as
   another unit of it is, and a further effect could only be fitted to this unit's noise (the real cat,
   `--region objects`, added a 0.02 px offset at -0.48 mm beyond the floor before this rule). A validity effect
   must also raise the held-out likelihood of the real hole map
   (:func:`~ddsgen.diagnose.evaluation.validity_log_likelihood`).
4b. **Beyond the library** (:mod:`~ddsgen.diagnose.axis_candidates`). When no named effect is accepted,
   a generic smooth term (disparity bias or dropout, degree-4 Legendre) is fitted along each axis with
   residual structure beyond noise and judged by the same rule; one accepted is reported as an *unnamed
   effect along that axis*, with its shape and the physical effects that produce such a shape. Named
   effects keep precedence: the generic terms are tried only when none of them clears the rule.
   Otherwise the loop stops.
5. **What remains**: axes whose residual structure is still beyond noise (and at least
   :data:`~ddsgen.diagnose.acceptance.UNEXPLAINED_MIN_MM`) are reported as unexplained, strongest first, rather than
   naming a wrong effect. When no axis has any but the gap is still beyond its floor (by more than the floor
   and that minimum), the gap is local: :mod:`~ddsgen.diagnose.local_patches` finds the patches that carry it
   (the scene the model lacks, as on real frames of a partly modelled scene).

**One frame** is enough: it is split spatially (:mod:`~ddsgen.diagnose.split`) into blocks dealt into
pieces, some held out, the others fitted together; the report says so.

Two things make the comparison fair to every candidate:

* **Credit only what the noise floor does not explain.** Two noise draws of one sensor do not
  score 0: the ``compare`` gap has a noise floor (its ``noise_floor``, measured between two
  draws of the model under test), and a model can lower the gap by *hiding* noise -- a
  dropout effect that removes the noisiest pixels lowers gap and floor alike, even on data
  without such dropout -- while a genuinely missing effect lowers the gap and leaves the
  floor. So a candidate is credited, per frame and with the same noise draws for every model,
  with the fall of its gap minus any fall of its floor (:func:`~ddsgen.diagnose.acceptance.frame_falls`), and gets
  nothing for making its own draws disagree more. The floor is the mean over the same several units as the
  reported one (at least four in all, :func:`~ddsgen.realscan.simulate.twin_draws`): a model that changes the depth
  changes its draws, and against one unit the floor's own scatter was charged to it (at a 10 m range a disparity
  offset's floor fell 0.13 mm by chance and its credited fall tied with a depth scale's, 43.0 % each).
* **Gaps are reported beyond the noise floor.** ``diagnosis.json``'s gaps are ``compare``'s
  ``excess``: held-out gap minus noise floor (mean over held-out frames), what a better
  model could still remove -- the true sensor scores about 0, so "the gap halves" means half
  of the explainable disagreement is gone. (At 640 x 480 the floor is ~1.5 mm, and a missing
  4-px edge band adds ~0.5 mm to it; in raw gaps no validity effect could ever halve the gap.)
  The raw gaps and floors are printed and in ``report.html``.
* **The support plane is re-estimated under each model** (:func:`~ddsgen.diagnose.plane.replane`). It is fitted to
  the real depth, so it already contains any bias that keeps planes planar (a disparity
  offset, a depth scale error); a model with that effect would apply it twice.

Speed: effects that act after block matching (disparity, depth and validity stages) do not
change the matcher's input, so the diagnosis' :class:`~ddsgen.diagnose.stage_cache.StageCache` (held by every
sensor it makes) serves the matcher's result from a cache keyed by the IR image; validity effects do not move the
plane either, so their whole search reuses the sensor's front end (IR image, matching, depth) and uses every fit
frame, and they are judged on the
held-out planes re-estimated under the current model (:data:`HELD_REPLANE_STEPS`); depth effects
are searched on at most :attr:`DiagnoseConfig.grid_frames` fit frames. **Screening** (:data:`SCREEN_FRACTION`):
each candidate is first searched on one fit frame and judged on the held-out frames at those values; only a
candidate whose credited fall there reaches 0.6 of the acceptance threshold is searched on every search
frame and judged again (the others cannot be accepted, so the answer is the full search's).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch

from ddsgen.diagnose.acceptance import (
    UNEXPLAINED_MIN_MM,
    bootstrap_fall,
    relative_fall,
    unexplained_axes,
)
from ddsgen.diagnose.axis_candidates import (
    DISPARITY_TERM,
    FailedFit,
    axes_to_try,
    fit_axis_candidate,
    label,
    split_label,
)
from ddsgen.diagnose.candidates import changes_depth, copy_of, fit_any, spec
from ddsgen.diagnose.config import DiagnoseConfig
from ddsgen.diagnose.device_candidates import device_candidates, is_device
from ddsgen.diagnose.evaluation import Evaluation, evaluate
from ddsgen.diagnose.local_patches import local_reading
from ddsgen.diagnose.maps import MAP_FRAMES, residual_maps
from ddsgen.diagnose.stage_cache import StageCache
from ddsgen.diagnose.plane import replaned
from ddsgen.diagnose.residuals import analyse, pixel_residuals
from ddsgen.diagnose.results import Candidate, Diagnosis, Step
from ddsgen.diagnose.sentences import format_values, step_sentence, structure_summary
from ddsgen.diagnose.split import split_note, split_single_frame
from ddsgen.diagnose.window import with_measured_quantum, with_measured_window
from ddsgen.fit.fitting import fit_sensor, split_frames
from ddsgen.realscan.simulate import simulate, twin_draws
from ddsgen.sensor.depth_sensor import DepthSensor
from ddsgen.sensor.effects import REGISTRY, library_names

#: Screening rule (speed). Each candidate's search runs first on the first ``screen_frames`` fit frames of
#: its search set (a quarter to a fifth of the work) and is judged on the held-out frames at the values found there.
#: When its credited held-out fall is below SCREEN_FRACTION times the acceptance threshold (0.6 x 5 % = 3 %), the
#: full search is skipped and that judgement stands (its log line says "screened"); such a candidate cannot be
#: accepted, so screening never accepts an effect fitted on one frame. Otherwise the screening result is discarded
#: and the candidate is searched on every search frame and judged again, exactly as without screening. The margin,
#: measured on 18 screen / full-search pairs (bench and test runs): those that explain nothing screened at
#: +1.3 .. +3.5 % (their full searches -2.0 .. +2.1 %); those that explain screened at +22.5 .. +68.8 % (full +25.5 ..
#: +80 %), 0.63 to 1.06 of their full fall, so an effect at the acceptance threshold screens at about 3.2 % or more
#: and is searched in full; a lower margin let noise-level screens (+1.8 %, +2.4 %) cost full searches of 12-15 s.
#: The best fall on the search frames themselves is no screen (a maximum over many noisy trials on one frame: +0.9 %
#: .. +2 % for candidates at -2 % .. -7 % on held-out frames, measured).
SCREEN_FRACTION = 0.6

#: Gauss-Newton steps that re-estimate the held-out frames' support planes under a model, from the planes fitted
#: to the real depth: the current model's (baseline, and after each accepted effect) and each depth candidate's.
#: A validity candidate leaves every depth as it was, so it is judged on the current model's planes: the
#: comparison then credits only the pixels it removes, and the current model's cached front ends serve it. (Its own
#: re-estimate moved the planes by the fit's scatter: it changed credited falls by up to 2 % of the gap.)
HELD_REPLANE_STEPS = 2


def passes(candidate: Candidate, config: DiagnoseConfig) -> bool:
    """The acceptance rule (:data:`~ddsgen.diagnose.acceptance.RULE`); a validity effect must also make the
    real valid/invalid map more likely (:func:`~ddsgen.diagnose.evaluation.validity_log_likelihood`)."""
    ok = candidate.gain >= config.min_relative_gain and candidate.gain_low > 0.0
    return ok and (not is_validity(candidate.effect) or candidate.validity_ll_gain >= 0.0)


def is_validity(label: str) -> bool:
    """Whether the candidate ``label`` (a named effect or ``TERM:AXIS``) only removes pixels."""
    return spec(split_label(label)[0]).stage == "validity"


def held_frames_for(name: str, cand_sensor, held: list, held_now: list, seed: int) -> list:
    """The held-out frames a candidate is judged on (see :data:`HELD_REPLANE_STEPS`): ``held_now`` (the current
    model's planes) for a validity candidate, else ``held`` re-planed under the candidate ``cand_sensor``."""
    return held_now if is_validity(name) else replaned(cand_sensor, held, seed, HELD_REPLANE_STEPS)


def analysis_of(sensor, frames, seed: int, edges: dict | None = None, stride: int = 1) -> dict:
    """Residual analysis (stats and structure per axis) of ``sensor`` on ``frames`` (re-planed under it)."""
    frames = replaned(sensor, frames, seed, 1)
    with torch.no_grad():
        sims = [simulate(sensor, f, seed) for f in frames]
    res = pixel_residuals(frames, sims, stride=stride)
    return analyse(res, seed=seed, edges=edges)


#: The refit's SNR search stays within this factor of the value fitted before (the base fit searched the whole
#: bounds, 0.25-4x): 5 coarse points instead of 9, the same golden-section steps after them (12 simulations of
#: each fit frame, not 16).
REFIT_SNR_SPAN = 2.0


def refit(sensor, frames, config: DiagnoseConfig, progress: bool) -> None:
    """Refit the base parameters (and, by Adam, the parameters of accepted effects that change depth) in place.

    Dropout thresholds are left where their search put them: the fit loss, unlike the credited
    fall, rewards dropping noisy pixels; so are the shapes of generic axis terms (read off the residual).
    """
    names = list(config.base_params) + [f"effect:{e.name}" for e in sensor.effects
                                        if changes_depth(e.name) and not e.generic]  # fmt: skip
    fit_sensor(sensor, frames, names, steps=config.refit_steps, lr=config.lr, progress=progress, seed=config.seed,
               batch_frames=config.batch_frames, snr_span=REFIT_SNR_SPAN, tile_px=config.tile_px)  # fmt: skip


# ------------------------------------------------------------------------------------------ the loop


#: Named effects tried only when asked for (--candidates): a 3x5 disparity-distortion field is flexible
#: enough to absorb part of an offset, a scale or a lens distortion, so by default the simpler effects
#: are tried alone (named effects are not ranked by simplicity).
OPT_IN_CANDIDATES = ("disparity_distortion",)


def default_candidates() -> list[str]:
    """The library effects tried by default: the named ones (not the generic axis terms), minus the opt-in ones."""
    return [name for name in library_names() if name not in OPT_IN_CANDIDATES]


def diagnose(preset, frames, config: DiagnoseConfig | None = None, echo: Callable[[str], None] = print,
             progress: bool = False, analysis_stride: int = 1,
             stage_cache: StageCache | None = None) -> Diagnosis:  # fmt: skip
    """Run the diagnosis loop (see the module docstring) on prepared frames.

    Args:
        preset: the starting sensor preset (with the scans' camera).
        frames: :func:`ddsgen.realscan.simulate.prepare_frames` output (split into fit / held-out here).
        config: settings.
        echo: receives one line per stage (progress output).
        progress: tqdm bars of the fits.
        analysis_stride: pixel subsampling of the residual analysis (1 = every pixel).
        stage_cache: the cache every sensor of the diagnosis holds (default: a new one); it serves while the
            candidates are searched and judged, and counts the stages computed throughout.
    """
    config = config or DiagnoseConfig()
    names = list(config.candidates) if config.candidates else default_candidates() + device_candidates(preset)
    unknown = [n for n in names if n not in REGISTRY and not is_device(n)]
    if unknown:
        raise ValueError(f"unknown candidate effect(s) {unknown}")
    notes = []
    preset, window, window_note = with_measured_window(preset, frames)
    if window_note:
        notes.append(window_note)
        echo("      " + window_note)
    if len(frames) == 1:  # one scan: pieces of it are the units of the fit / held-out split
        fit_frames, held = split_single_frame(frames[0], config.holdout, config.seed)
        notes.append(split_note(frames[0], fit_frames, held))
        echo("      " + notes[-1])
    else:
        fit_frames, held = split_frames(frames, config.holdout, config.seed)
    preset, quantum_note = with_measured_quantum(preset, fit_frames, held)
    if quantum_note:
        notes.append(quantum_note)
        echo("      " + quantum_note)
    held_seed = config.seed + 1  # held-out gaps use other noise draws than the fit
    rng = np.random.default_rng([config.seed, 77])

    echo(f"[1/5] base fit of {', '.join(config.base_params)} on {len(fit_frames)} fit frame(s) "
         f"({len(held)} held out)")  # fmt: skip
    cache = StageCache() if stage_cache is None else stage_cache
    sensor = DepthSensor(preset, stage_cache=cache)
    fit_sensor(sensor, fit_frames, list(config.base_params), steps=config.base_steps, lr=config.lr, progress=progress,
               seed=config.seed, batch_frames=config.batch_frames, tile_px=config.tile_px)  # fmt: skip
    # Gaps beyond the floor average the floor over several units, as compare does (a split frame counts as one
    # frame); the candidates are judged against the same units (acceptance.frame_falls).
    floor_draws = twin_draws(1 if len(frames) == 1 else len(held))
    held_now = replaned(sensor, held, held_seed, HELD_REPLANE_STEPS)  # the held-out planes under the current model
    current = evaluate(sensor, held_now, held_seed, floor_draws=floor_draws)
    baseline, base_sensor = current, sensor  # accepted effects make new sensors: base_sensor stays as fitted
    echo(f"      held-out gap {current.gap:.2f} mm, noise floor {current.floor:.2f} mm: "
         f"{current.excess:.2f} mm beyond it")  # fmt: skip

    echo("[2/5] residual analysis (depth, incidence, radius, row, column, edge distance, IR signal) "
         "on the held-out and search frames")
    analysis_frames = held + fit_frames[: config.grid_frames or None]
    analysis = analysis_of(sensor, analysis_frames, held_seed, stride=analysis_stride)
    edges = {axis: stats.edges for axis, (stats, _) in analysis.items()}
    analysis_baseline = analysis
    echo(f"      strongest structure: {structure_summary(analysis)}")

    steps: list[Step] = []
    rounds: list[list[Candidate]] = []
    in_model = {e.name for e in sensor.effects}
    with cache.serving():
        while len(steps) < config.max_steps:
            todo = [n for n in names if n not in in_model]
            if not todo and not config.axis_terms:
                break
            echo(f"[3/5] round {len(rounds) + 1}: fitting {len(todo)} candidate effect(s) on the fit frames")
            # Depth-changing effects are searched on grid_frames (each trial re-planes and re-matches);
            # validity effects on every fit frame (their trials reuse the matcher's results: cheap).
            all_fit = replaned(sensor, fit_frames, config.seed)
            all_base = evaluate(sensor, all_fit, config.seed)
            with torch.no_grad():
                all_sims = [simulate(sensor, f, config.seed) for f in all_fit]
            n_grid = len(all_fit[: config.grid_frames or None])  # grid frames: the first n_grid fit frames
            grid_frames = all_fit[:n_grid]
            search_sets = {
                True: (grid_frames, Evaluation(all_base.frame_gaps[:n_grid], all_base.frame_floors[:n_grid]),
                       all_sims[:n_grid]),
                False: (all_fit, all_base, all_sims),
            }  # fmt: skip
            results = []

            def judge(name, fitted, screened: str = ""):
                cand_sensor, values, fit_score = fitted
                judged_on = held_frames_for(name, cand_sensor, held, held_now, held_seed)
                held_eval = evaluate(cand_sensor, judged_on, held_seed, floor_draws=floor_draws)
                c = Candidate(name, values, fit_score, held_eval, sensor=cand_sensor, screened=bool(screened))
                c.gain = relative_fall(current, held_eval)
                c.gain_low = bootstrap_fall(current, held_eval, rng)
                c.validity_ll_gain = held_eval.validity_ll - current.validity_ll
                results.append(c)
                echo(f"      {name:20s} held-out gap {held_eval.gap:6.2f} mm (floor {held_eval.floor:5.2f}, beyond it "
                     f"{held_eval.excess:5.2f})  "
                     f"credited fall {100 * c.gain:+6.1f} % (bootstrap 5 %: {100 * c.gain_low:+6.1f} %)  "
                     f"validity log-lik. {1000 * c.validity_ll_gain:+.1f} mnat/px  {format_values(values)}"
                     + (f"  ({screened})" if screened else ""))  # fmt: skip
                return c

            for name in todo:
                search_frames, search_base, search_sims = search_sets[changes_depth(name)]
                n = config.screen_frames
                if n and len(search_frames) > n:  # screening (see SCREEN_FRACTION): one frame's search first
                    screen_base = Evaluation(search_base.frame_gaps[:n], search_base.frame_floors[:n])
                    fitted = fit_any(sensor, name, search_frames[:n], config, screen_base, search_sims[:n],
                                     screening=True, guess_from=(all_fit, all_sims))  # fmt: skip
                    c = judge(name, fitted, f"screened: searched on {n} fit frame(s)")
                    if c.gain < SCREEN_FRACTION * config.min_relative_gain:
                        continue
                    results.remove(c)  # promising: searched on every search frame and judged again
                judge(name, fit_any(sensor, name, search_frames, config, search_base, search_sims,
                                    guess_from=(all_fit, all_sims)))  # fmt: skip
            best = max(results, key=lambda c: c.gain) if results else None
            if config.axis_terms and not (best is not None and passes(best, config)):
                # No named effect explains it: a generic smooth term along an axis with structure beyond noise.
                tried = []
                for term, axes in axes_to_try(analysis).items():
                    if any(e.name == term for e in sensor.effects):  # a preset holds one term of each kind
                        continue
                    for axis in axes:
                        search_frames, search_base, search_sims = search_sets[term == DISPARITY_TERM]
                        fitted = fit_axis_candidate(sensor, term, axis, search_frames, config, search_base,
                                                    search_sims)  # fmt: skip
                        if isinstance(fitted, FailedFit):
                            echo(f"      {label(term, axis)} failed fit: {fitted.reason}; not tried on the held-out "
                                 f"frames")  # fmt: skip
                        elif fitted is not None:
                            tried.append(judge(label(term, axis), fitted))
                if tried:
                    echo("      (generic axis terms: tried because no named effect clears the rule)")
                    best = max(tried, key=lambda c: c.gain)
            rounds.append(results)
            if best is None or not passes(best, config):
                if best is not None:
                    echo(f"[4/5] no candidate clears the rule (best: {best.effect}, {100 * best.gain:.1f} %, "
                         f"bootstrap 5 % {100 * best.gain_low:.1f} %): stop")  # fmt: skip
                break
            echo(f"[4/5] accepted {best.effect}; refitting the base parameters with it")
            new = best.sensor
            judged = copy_of(new)  # the candidate as judged (with any SNR its search moved): the refit is in place
            fit_before = evaluate(new, grid_frames, config.seed, replane_steps=1)
            refit(new, replaned(new, fit_frames, config.seed), config, progress)
            if relative_fall(fit_before, evaluate(new, grid_frames, config.seed, replane_steps=1)) < 0.0:
                new = judged  # the refit did not help: undo it
            held_now = replaned(new, held, held_seed, HELD_REPLANE_STEPS)
            after = evaluate(new, held_now, held_seed, floor_draws=floor_draws)
            name, options = split_label(best.effect)
            params = dict(best.params) if is_device(name) else new.effects[-1].values()
            after_analysis = analysis_of(new, analysis_frames, held_seed, edges=edges, stride=analysis_stride)
            axis = options.get("axis", spec(name).axis)
            steps.append(Step(best.effect, params, current, after, axis,
                              step_sentence(best.effect, params, current, after), analysis, after_analysis))  # fmt: skip
            echo(f"      {best.effect}: held-out gap beyond the noise floor {current.excess:.2f} -> {after.excess:.2f} mm "
                 f"(compare gap {current.gap:.2f} -> {after.gap:.2f} mm; {format_values(params)})")  # fmt: skip
            sensor, current, analysis = new, after, after_analysis
            in_model.add(best.effect)
            if current.excess <= 0.0:
                notes.append(f"Stopped after {best.effect}: the held-out gap is below its noise floor now "
                             f"({current.gap:.2f} mm against {current.floor:.2f} mm); nothing is left beyond the "
                             f"floor to explain.")  # fmt: skip
                echo("[4/5] " + notes[-1])
                break

    unexplained = unexplained_axes(analysis)
    if unexplained:
        echo("[5/5] unexplained structure: " + ", ".join(f"{u['axis']} {u['strength']:.1f} mm" for u in unexplained))
    else:
        echo("[5/5] no residual structure beyond noise remains along any axis")
    local = None
    if not unexplained and current.excess >= max(UNEXPLAINED_MIN_MM, current.floor):
        # A gap well beyond the floor that no axis explains: say where it is (local patches: scene, not sensor).
        local = local_reading(sensor, frames, held_now, held_seed, current, floor_draws, HELD_REPLANE_STEPS)
        echo("      " + local.sentence())
    # A split frame is mapped whole (fit and held-out blocks): its pieces alone would show a checkerboard.
    map_frames = frames[:1] if len(frames) == 1 else held[:MAP_FRAMES]
    maps_baseline = residual_maps(base_sensor, map_frames, held_seed)
    maps_final = residual_maps(sensor, map_frames, held_seed) if steps else maps_baseline
    return Diagnosis(baseline, steps, current, unexplained, sensor, fit_frames, held, analysis_baseline, analysis,
                     rounds, maps_baseline, maps_final, notes, window, local)  # fmt: skip

