"""Keep only what helped: revert parameter groups whose change does not lower the held-out gap.

A fit lowers the loss on its own frames by construction; whether a change *transfers* shows on
held-out frames. :func:`revert_unhelpful` measures the held-out gap of the fitted sensor and of
the input sensor, then, group by group (eta_c / sigma, beta, baseline / focal, each effect, the
CNN: the ``group`` of :data:`ddsgen.fit.parameters.SENSOR_PARAMS`), puts the group's input values
back and keeps them so when the held-out gap is not higher without the group's change; the groups
still kept are judged again beside those reverted after them, until a pass reverts nothing
(backward elimination). When what remains does not beat the input as a whole, every group goes
back to the input's values. What
remains is reported per group, and the output says plainly when the fit did not beat the input.

The held-out frames choose what is kept, so the final held-out gap is no longer an unbiased
test (it can only be <= min(input, fitted) up to noise); with more scenes, keep a second
held-out set for the final word.
"""

from __future__ import annotations

import torch

from ddsgen.realscan.gap import gap
from ddsgen.fit.device_keys import apply_mirrors

#: A group's ``note`` in :func:`revert_unhelpful`'s report: the fit left it at the input's values.
UNCHANGED = "unchanged"
#: A group's ``note``: kept in the pass, then reverted with the rest because the kept groups did not beat the input.
NOT_BETTER_AS_A_WHOLE = "not better as a whole"


def param_group(name: str, table: dict) -> str:
    """The revert group of a fitted parameter name (see the module docstring)."""
    if name in table:
        return table[name].group
    if name.startswith("effect:"):
        return name.split(".", 1)[0]
    return name


def snapshot(resolved: dict[str, list[torch.Tensor]]) -> dict[str, list[torch.Tensor]]:
    """Copies of the current values of resolved parameters (``parameters.resolve_params``)."""
    return {name: [t.detach().clone() for t in tensors] for name, tensors in resolved.items()}


def _assign(sensor, resolved, values, names) -> None:
    with torch.no_grad():
        for name in names:
            for tensor, value in zip(resolved[name], values[name]):
                tensor.copy_(value)
    apply_mirrors(sensor)  # device keys live in the preset (ddsgen.fit.device_keys)


def revert_unhelpful(sensor, resolved: dict, start: dict, held: list, table: dict, *, region: str = "all",
                     seed: int = 1) -> dict:  # fmt: skip
    """Revert the groups that do not lower the held-out gap (in place on ``sensor``).

    Args:
        resolved: name -> tensors (``parameters.resolve_params`` of the fitted names).
        start: :func:`snapshot` of the same names taken before the fit.
        held: held-out FrameData, or a callable sensor -> FrameData preparing them for the sensor as it is
            (support planes where its disparity errors put them, :mod:`ddsgen.realscan.plane_depth`);
            region/seed: as ``compare.gap``.

    Returns:
        {"gap_input", "gap_fitted", "gap_kept" (mm), "better" (bool: the kept preset beats the input),
        "groups": {group: {"params", "kept" (bool), "gap_without_change"}}}.
    """
    fitted = snapshot(resolved)

    def held_gap() -> float:
        frames = held(sensor) if callable(held) else held
        return gap(sensor, frames, region=region, seed=seed, noise_floor=False).gap

    gap_fitted = held_gap()
    _assign(sensor, resolved, start, list(resolved))
    gap_input = held_gap()
    _assign(sensor, resolved, fitted, list(resolved))
    groups: dict[str, list[str]] = {}
    for name in resolved:
        groups.setdefault(param_group(name, table), []).append(name)
    current = gap_fitted
    report = {}
    for group, names in groups.items():
        changed = any(not torch.equal(a, b) for n in names for a, b in zip(start[n], fitted[n]))
        report[group] = {"params": names, "kept": changed}
        if not changed:
            report[group].update(gap_without_change=current, note=UNCHANGED)
    # Backward elimination: each kept group is taken out in turn and stays out when the held-out gap is not higher
    # without it; a group kept beside changes reverted after it is judged again, until a pass reverts nothing.
    reverted_in_pass = True
    while reverted_in_pass:
        reverted_in_pass = False
        for group, info in report.items():
            if not info["kept"]:
                continue
            _assign(sensor, resolved, start, info["params"])
            without = held_gap()
            info["gap_without_change"] = without
            if without <= current:  # the change did not help on the held-out frames: keep the input's values
                current = without
                info["kept"] = False
                reverted_in_pass = True
            else:
                _assign(sensor, resolved, fitted, info["params"])
    better = current < gap_input
    if not better:
        # A group is kept when taking it out hurts *beside the groups still fitted at that point*; groups reverted
        # after it can leave the kept set no better than the input (e.g. beta kept, then the baseline it
        # compensated reverted). The output is then the input, as the summary says.
        _assign(sensor, resolved, start, list(resolved))
        for info in report.values():
            if info["kept"]:
                info.update(kept=False, note=NOT_BETTER_AS_A_WHOLE)
        current = gap_input
    return {"gap_input": gap_input, "gap_fitted": gap_fitted, "gap_kept": current, "better": better,
            "groups": report}  # fmt: skip


def output_holds_fit(outcome: dict, group: str) -> bool:
    """Whether the output preset holds ``group``'s fitted values: the group was kept, or the fit left it where it
    was (then fitted and input values are one, and calling it "reverted" would misreport it)."""
    info = outcome["groups"][group]
    return info["kept"] or info.get("note") == UNCHANGED


def revert_summary(outcome: dict) -> list[str]:
    """Plain-language lines about what was kept and reverted."""
    lines = []
    if not outcome["gap_fitted"] < outcome["gap_input"]:
        lines.append(f"the fitted preset is NOT better than the input on the held-out frames "
                     f"({outcome['gap_fitted']:.2f} mm vs {outcome['gap_input']:.2f} mm)")  # fmt: skip
    for group, info in outcome["groups"].items():
        if info.get("note") == UNCHANGED:
            continue
        if info["kept"]:
            lines.append(f"kept {group} ({', '.join(info['params'])}): without it {info['gap_without_change']:.2f} mm")
        elif info.get("note") == NOT_BETTER_AS_A_WHOLE:
            lines.append(f"reverted {group} ({', '.join(info['params'])}) to the input's values with the rest: it "
                         f"helped only beside changes that were reverted after it")  # fmt: skip
        else:
            lines.append(f"reverted {group} ({', '.join(info['params'])}) to the input's values: the change did not "
                         f"lower the held-out gap ({info['gap_without_change']:.2f} mm without it)")  # fmt: skip
    if not outcome["better"]:
        lines.append("nothing the fit changed lowers the held-out gap: the output keeps the input's values")
    return lines
