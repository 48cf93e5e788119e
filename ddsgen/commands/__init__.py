"""One module per CLI command; each defines a click command named like the module.

What several commands share (option helpers) lives here, so that no command module imports another.
"""

import math

import click

#: Every --seed: numpy's SeedSequence takes any integer >= 0 (a negative one is bad input, not a traceback).
SEED = click.IntRange(min=0)


class FiniteFloat(click.FloatRange):
    """A float option within a range that is also finite: click's FloatRange lets NaN through (every comparison
    with NaN is False), and a NaN plausibility or albedo ran on to a misleading error or a meaningless result."""

    def convert(self, value, param, ctx):
        number = super().convert(value, param, ctx)
        if not math.isfinite(number):
            self.fail(f"{number} is not a finite number.", param, ctx)
        return number


#: A finite float > 0 (thresholds, scales).
POSITIVE = FiniteFloat(min=0.0, min_open=True)


def split_names(values) -> list[str]:
    """Names from a repeatable, comma-separated option: ("a,b", "c") -> ["a", "b", "c"]."""
    return [name.strip() for value in values for name in value.split(",") if name.strip()]


def common_options(f):
    """The options of the real-scan commands (compare, fit): support plane, crop, plausibility, region, seed."""
    f = click.option("--no-plane", is_flag=True, help="Do not add a RANSAC support plane fitted to the real depth.")(f)
    f = click.option("--crop", is_flag=True, help="Simulate only a box around the objects (faster; exact: a "
                     "sub-window of a pinhole image is a pinhole image).")(f)  # fmt: skip
    f = click.option("--plausible-px", type=POSITIVE, default=2.0, show_default=True,
                     help="Compare only where |real - clean| disparity is below this (px), or real is invalid.")(f)
    f = click.option("--region", type=click.Choice(["all", "objects"]), default="all", show_default=True,
                     help="Pixels that count: every modelled surface, or only the objects'.")(f)
    f = click.option("--seed", type=SEED, default=0, show_default=True, help="Noise seed of the simulation.")(f)
    f = click.option("--quiet", is_flag=True, help="No progress bars.")(f)
    return f


REPRODUCIBLE_THREADS_HELP = ("Torch threads (default: torch's own, one per core). Results are bit-reproducible for a "
                             "given thread count, not across thread counts (docs/scene_gradients.md): pass the same "
                             "--threads to compare runs on machines with different core counts.")


def threads_option(default: int | None, help: str):
    """``--threads``: torch's intra-op threads while the command runs (None: leave torch's default)."""
    return click.option("--threads", type=click.IntRange(min=1), default=default, show_default=default is not None,
                        help=help)  # fmt: skip


def use_threads(threads: int | None) -> None:
    """Run the current command with ``threads`` torch threads (None: unchanged); the previous count comes back when
    the command ends (commands also run inside other programs and tests)."""
    if threads is None:
        return
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(threads)
    click.get_current_context().call_on_close(lambda: torch.set_num_threads(before))


def echo_stderr(message: str) -> None:
    click.echo(message, err=True)
