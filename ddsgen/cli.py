"""The ``ddsgen`` command line: thin parsing and reporting around the library.

Every command: ``--help``; exit 0 on success; bad input -> one line on stderr and
exit 2 (no traceback, nothing half-written); so is a path the system refuses to read or write (OSError).
"""

from __future__ import annotations

import importlib
import importlib.util
import sys

import click

from ddsgen.errors import InputError

# Commands live in ddsgen/commands/<name>.py, each exposing a click command called <name>.
COMMAND_MODULES = ("render", "preview", "pattern", "stereo", "compare", "fit", "diagnose", "refine", "study", "presets")


@click.group(context_settings={"help_option_names": ["-h", "--help"], "max_content_width": 100})
@click.version_option(package_name="ddsgen")
def cli():
    """ddsgen: realistic synthetic depth scans by simulating a structured-light depth sensor.

    Ray-trace a scene, render the projector's IR dot pattern on it, recover disparity with a
    differentiable block matcher, turn it into depth; fit the sensor to real scans.
    """


for _name in COMMAND_MODULES:
    if importlib.util.find_spec(f"ddsgen.commands.{_name}") is not None:
        cli.add_command(getattr(importlib.import_module(f"ddsgen.commands.{_name}"), _name))


def main(argv: list[str] | None = None) -> int:
    """Entry point: run the CLI, turning bad input into one line and exit code 2."""
    try:
        cli.main(args=argv, prog_name="ddsgen", standalone_mode=False)
    except InputError as error:
        click.echo(f"ddsgen: error: {error}", err=True)
        return 2
    except click.exceptions.UsageError as error:
        path = error.ctx.command_path if error.ctx else ""
        where = f"{path}: " if path and path != "ddsgen" else ""
        click.echo(f"ddsgen: error: {where}{error.format_message()}", err=True)
        return 2
    except click.exceptions.Abort:
        click.echo("ddsgen: interrupted", err=True)
        return 130
    except click.exceptions.ClickException as error:
        click.echo(f"ddsgen: error: {error.format_message()}", err=True)
        return error.exit_code
    except KeyboardInterrupt:
        click.echo("ddsgen: interrupted; re-run the same command to resume", err=True)
        return 130
    except OSError as error:  # a path the system refuses (a file where a folder goes, no space, no permission)
        click.echo(f"ddsgen: error: {_os_line(error)}", err=True)
        return 2
    return 0


def _os_line(error: OSError) -> str:
    """'PATH: REASON' of an OSError that no command turned into an InputError of its own."""
    reason = error.strerror or str(error) or type(error).__name__
    name = error.filename if error.filename is not None else ""
    return f"{name}: {reason.lower()}" if name else reason


def entry_point() -> None:
    """Console-script wrapper (``ddsgen``): exits with :func:`main`'s code."""
    sys.exit(main())
