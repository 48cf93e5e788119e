"""The ``ddsgen`` command line: thin parsing and reporting around the library.

Every command: ``--help``; exit 0 on success; bad input -> one line on stderr and
exit 2 (no traceback, nothing half-written); so is a path the system refuses to read or write (OSError).
Ctrl-C (SIGINT) and SIGTERM unwind the same way (worker processes ended, finished frames kept): exit 130 / 143.
"""

from __future__ import annotations

import contextlib
import importlib
import importlib.util
import signal
import sys
import threading

import click

from ddsgen.errors import InputError

# Commands live in ddsgen/commands/<name>.py, each exposing a click command called <name>.
COMMAND_MODULES = ("render", "preview", "pattern", "stereo", "compare", "fit", "diagnose", "refine", "study", "presets")


class Terminated(KeyboardInterrupt):
    """SIGTERM as an exception. A KeyboardInterrupt, so that it unwinds exactly as Ctrl-C does: every
    ``except KeyboardInterrupt`` / ``except BaseException`` clean-up runs (the runner ends its worker processes,
    atomic writes drop their temporary files), where SIGTERM's default action ended the process on the spot and
    left the pool's workers and multiprocessing's resource tracker running, re-parented to PID 1."""


#: Exit code after SIGTERM: 128 + 15, as a shell reports a process that SIGTERM ended.
EXIT_TERMINATED = 128 + signal.SIGTERM
#: Exit code after Ctrl-C (SIGINT): 128 + 2.
EXIT_INTERRUPTED = 128 + signal.SIGINT

#: Commands that keep their finished work when interrupted and continue it when run again.
RESUMABLE_COMMANDS = frozenset({"render"})


class _Stopped(BaseException):
    """A Ctrl-C or SIGTERM inside a command, carried past click's ``main`` (which would print an empty line to
    stderr and turn it into ``Abort``), with the name of the command it stopped."""

    def __init__(self, signal_exception: KeyboardInterrupt, command: str | None):
        super().__init__(command)
        self.terminated = isinstance(signal_exception, Terminated)
        self.command = command


class _DdsgenGroup(click.Group):
    def make_context(self, *args, **kwargs) -> click.Context:
        try:
            return super().make_context(*args, **kwargs)
        except KeyboardInterrupt as stop:  # while the command line is parsed
            raise _Stopped(stop, None) from None

    def invoke(self, ctx: click.Context):
        try:
            return super().invoke(ctx)
        except KeyboardInterrupt as stop:
            raise _Stopped(stop, ctx.invoked_subcommand) from None


@click.group(cls=_DdsgenGroup, context_settings={"help_option_names": ["-h", "--help"], "max_content_width": 100})
@click.version_option(package_name="ddsgen")
def cli():
    """ddsgen: realistic synthetic depth scans by simulating a structured-light depth sensor.

    Ray-trace a scene, render the projector's IR dot pattern on it, recover disparity with a
    differentiable block matcher, turn it into depth; fit the sensor to real scans.
    """


for _name in COMMAND_MODULES:
    if importlib.util.find_spec(f"ddsgen.commands.{_name}") is not None:
        cli.add_command(getattr(importlib.import_module(f"ddsgen.commands.{_name}"), _name))


@contextlib.contextmanager
def _sigterm_raises():
    """While the block runs, SIGTERM raises :class:`Terminated` in the main thread (once: a second SIGTERM
    during the clean-up does not cut the clean-up short; SIGKILL still ends everything). The previous handler is
    restored afterwards. Left alone where the embedding program installed its own handler, and off the main
    thread (only the main thread can set handlers)."""
    if threading.current_thread() is not threading.main_thread() or signal.getsignal(signal.SIGTERM) != signal.SIG_DFL:
        yield
        return
    received: list[int] = []

    def handler(number, frame):
        if not received:
            received.append(number)
            raise Terminated()

    previous = signal.signal(signal.SIGTERM, handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def main(argv: list[str] | None = None) -> int:
    """Entry point: run the CLI, turning bad input into one line and exit code 2."""
    try:
        with _sigterm_raises():
            return _run(argv)
    except Terminated:  # the signal came between _run's own handlers and the end of the block
        return _stopped_line(True, None)


def _run(argv: list[str] | None) -> int:
    """:func:`main` inside the SIGTERM handler: each kind of failure -> its one line and exit code."""
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
    except _Stopped as stop:
        return _stopped_line(stop.terminated, stop.command)
    except click.exceptions.Abort as error:  # click's own, for a Ctrl-C between parsing and the command
        return _stopped_line(isinstance(error.__cause__, Terminated), None)
    except click.exceptions.ClickException as error:
        click.echo(f"ddsgen: error: {error.format_message()}", err=True)
        return error.exit_code
    except KeyboardInterrupt as stop:  # before or after click's main
        return _stopped_line(isinstance(stop, Terminated), None)
    except OSError as error:  # a path the system refuses (a file where a folder goes, no space, no permission)
        click.echo(f"ddsgen: error: {_os_line(error)}", err=True)
        return 2
    return 0


def _stopped_line(terminated: bool, command: str | None) -> int:
    """Print the one line of a run stopped by SIGTERM or Ctrl-C; return its exit code (143 / 130)."""
    what = "terminated" if terminated else "interrupted"
    hint = "; finished frames are kept, re-run the same command to resume" if command in RESUMABLE_COMMANDS else ""
    click.echo(f"ddsgen: {what}{hint}", err=True)
    return EXIT_TERMINATED if terminated else EXIT_INTERRUPTED


def _os_line(error: OSError) -> str:
    """'PATH: REASON' of an OSError that no command turned into an InputError of its own."""
    reason = error.strerror or str(error) or type(error).__name__
    name = error.filename if error.filename is not None else ""
    return f"{name}: {reason.lower()}" if name else reason


def entry_point() -> None:
    """Console-script wrapper (``ddsgen``): exits with :func:`main`'s code."""
    sys.exit(main())
