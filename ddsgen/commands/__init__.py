"""One module per CLI command; each defines a click command named like the module.

What several commands share (option helpers) lives here, so that no command module imports another.
"""

import click


def split_names(values) -> list[str]:
    """Names from a repeatable, comma-separated option: ("a,b", "c") -> ["a", "b", "c"]."""
    return [name.strip() for value in values for name in value.split(",") if name.strip()]


def common_options(f):
    """The options of the real-scan commands (compare, fit): support plane, crop, plausibility, region, seed."""
    f = click.option("--no-plane", is_flag=True, help="Do not add a RANSAC support plane fitted to the real depth.")(f)
    f = click.option("--crop", is_flag=True, help="Simulate only a box around the objects (faster; exact: a "
                     "sub-window of a pinhole image is a pinhole image).")(f)  # fmt: skip
    f = click.option("--plausible-px", type=float, default=2.0, show_default=True,
                     help="Compare only where |real - clean| disparity is below this (px), or real is invalid.")(f)
    f = click.option("--region", type=click.Choice(["all", "objects"]), default="all", show_default=True,
                     help="Pixels that count: every modelled surface, or only the objects'.")(f)
    f = click.option("--seed", type=int, default=0, show_default=True, help="Noise seed of the simulation.")(f)
    f = click.option("--quiet", is_flag=True, help="No progress bars.")(f)
    return f


def echo_stderr(message: str) -> None:
    click.echo(message, err=True)
