"""Atomic file writes: write to a temporary name in the same folder, fsync, then rename.

A reader (or a resumed run) therefore sees either the complete old file, the
complete new file, or nothing -- never a half-written one.
"""

from __future__ import annotations

import contextlib
import os
import re
import shutil
import socket
import tempfile
from pathlib import Path

from ddsgen.errors import InputError

_UMASK = os.umask(0)
os.umask(_UMASK)


@contextlib.contextmanager
def atomic_path(path: str | Path):
    """Yield a temporary path next to ``path``; on success rename it onto ``path``.

    The temporary name keeps the suffix (writers pick the format from it).
    On error the temporary file is removed and ``path`` is untouched.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=f".tmp{path.suffix}", dir=path.parent)
    os.close(fd)
    os.chmod(tmp, 0o666 & ~_UMASK)  # mkstemp makes 0600; outputs get the usual permissions
    try:
        yield Path(tmp)
        with open(tmp, "rb+") as handle:
            os.fsync(handle.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


def atomic_write_bytes(path: str | Path, data: bytes) -> None:
    with atomic_path(path) as tmp:
        Path(tmp).write_bytes(data)


def atomic_write_text(path: str | Path, text: str) -> None:
    atomic_write_bytes(path, text.encode("utf-8"))


def check_can_create_folder(folder: str | Path, what: str) -> None:
    """Raise ``InputError`` naming ``folder`` when it cannot become a writable folder: it, or the first of its
    ancestors that exists, is a file or is not writable. Writes nothing: commands call it before hours of work
    whose results go there (a file where the folder should be was a traceback at the end of a fit)."""
    folder = Path(folder)
    existing = folder
    while not existing.exists() and existing != existing.parent:
        existing = existing.parent
    if not existing.is_dir():
        raise InputError(f"{folder}: cannot write {what} there ({existing} is a file, not a folder)")
    if not os.access(existing, os.W_OK | os.X_OK):
        raise InputError(f"{folder}: cannot write {what} there ({existing} is not writable)")


def overlap(folder: str | Path, other: str | Path) -> str | None:
    """How ``folder`` meets ``other``: ``"is"``, ``"is inside"``, ``"holds"`` (symbolic links followed) or None."""
    folder, other = Path(folder).resolve(), Path(other).resolve()
    if folder == other:
        return "is"
    if other in folder.parents:
        return "is inside"
    return "holds" if folder in other.parents else None


def check_new_folder(folder: str | Path, option: str, inputs: tuple[str | Path, ...] = ()) -> Path:
    """Raise ``InputError`` unless ``folder`` can become a new output folder: absent or an empty folder, writable,
    and neither one of ``inputs`` nor inside one nor holding one. Writes nothing; call before any work. Returns
    ``folder`` as a Path. ``option`` names the option in the message (``--out``)."""
    folder = Path(folder)
    for source in inputs:
        where = overlap(folder, source)
        if where:
            raise InputError(f"{folder}: {option}: {where} the input folder {source}; give a new folder")
    if folder.exists() and (not folder.is_dir() or any(folder.iterdir())):
        what = "folder is not empty" if folder.is_dir() else "exists and is not a folder"
        raise InputError(f"{folder}: {option}: {what}; give a new folder")
    check_can_create_folder(folder, option)
    return folder


@contextlib.contextmanager
def atomic_folder(folder: str | Path, what: str, *, merge: bool = True, last: str | None = None):
    """Yield a new hidden folder next to ``folder`` to build it in; on success put what it holds in place.

    ``folder`` therefore appears only complete: an exception (a Ctrl-C's KeyboardInterrupt included) removes the
    temporary folder and the parent folders made for it, and leaves ``folder`` as it was. When ``folder`` is absent
    or empty the temporary folder is renamed to it. An existing folder (an earlier run's report) is kept with
    ``merge``: each entry built replaces its namesake (a sub-folder as a whole), the others stay, ``last`` (the
    index page) goes in last; without ``merge`` it is an error. Ctrl-C waits for the renames. Errors of the file
    system are one-line ``InputError`` naming ``folder`` and ``what``.
    """
    folder = Path(folder)
    target = folder.resolve()
    made = _make_parents(target.parent, folder, what)
    remove_stale_partials(target)
    try:
        prefix = f".{target.name}.{_HOST}-{os.getpid()}."
        tmp = Path(tempfile.mkdtemp(prefix=prefix, suffix=".partial", dir=target.parent))
    except OSError as error:
        _remove_made(made)
        raise InputError(f"{folder}: cannot write {what} there ({error.strerror or error})") from None
    try:
        os.chmod(tmp, 0o777 & ~_UMASK)  # mkdtemp makes 0700; outputs get the usual permissions
        yield tmp
        with _interrupts_deferred():
            _put_in_place(tmp, target, folder, what, merge, last)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        _remove_made(made)
        raise
    if tmp.exists():  # the replaced entries of a merge
        shutil.rmtree(tmp, ignore_errors=True)


#: A hidden ``.NAME.HOST-PID.XXXX.partial`` folder names the host and process building it, so that a later run
#: can tell the folder of a process that died (SIGKILL, power loss) from one still being built.
_HOST = re.sub(r"[^A-Za-z0-9_-]", "_", socket.gethostname())


def remove_stale_partials(target: Path) -> list[Path]:
    """Delete the hidden folders that a killed process left while building ``target`` (see :func:`atomic_folder`);
    returns them. Only those of this host whose process is gone: a folder being built by a live process, or on
    another host sharing the file system, is left alone."""
    pattern = re.compile(rf"\.{re.escape(target.name)}\.(?P<host>[A-Za-z0-9_-]+)-(?P<pid>\d+)\.[^/]*\.partial")
    removed = []
    with contextlib.suppress(OSError):
        for entry in target.parent.iterdir():
            found = pattern.fullmatch(entry.name)
            if found and found["host"] == _HOST and entry.is_dir() and not _process_alive(int(found["pid"])):
                shutil.rmtree(entry, ignore_errors=True)
                removed.append(entry)
    return removed


def _process_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process
        return True
    return True


def _make_parents(parent: Path, folder: Path, what: str) -> list[Path]:
    """Create ``parent`` and its missing ancestors; returns those created, outermost first."""
    missing = [p for p in (parent, *parent.parents) if not p.exists()][::-1]
    try:
        for path in missing:
            path.mkdir()
    except OSError as error:
        _remove_made(missing)
        raise InputError(f"{folder}: cannot write {what} there ({error.strerror or error})") from None
    return missing


def _remove_made(made: list[Path]) -> None:
    for path in reversed(made):
        with contextlib.suppress(OSError):
            path.rmdir()


def _put_in_place(tmp: Path, target: Path, folder: Path, what: str, merge: bool, last: str | None) -> None:
    try:
        if target.is_dir() and not any(target.iterdir()):
            target.rmdir()
        if not target.exists():
            tmp.rename(target)
            return
        if not merge or not target.is_dir():
            raise InputError(f"{folder}: {what}: folder is not empty; give a new folder")
        replaced = Path(tempfile.mkdtemp(prefix=".replaced.", dir=tmp))
        for entry in sorted(tmp.iterdir(), key=lambda p: (p.name == last, p.name)):
            if entry == replaced:
                continue
            old = target / entry.name
            if old.exists() or old.is_symlink():
                old.rename(replaced / entry.name)
            entry.rename(old)
    except OSError as error:
        raise InputError(f"{folder}: cannot write {what} there ({error.strerror or error})") from None


@contextlib.contextmanager
def _interrupts_deferred():
    """Hold a Ctrl-C (SIGINT) or a SIGTERM (the CLI turns it into the same unwinding) until the block ends, then act
    on the first as usual: the renames that put a folder in place are not cut in half. Only the main thread can
    handle signals; elsewhere this does nothing, as it does for a signal without a Python handler."""
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = {n: signal.getsignal(n) for n in (signal.SIGINT, signal.SIGTERM)}
    held = [n for n, handler in previous.items() if callable(handler)]
    received = []
    for number in held:
        signal.signal(number, lambda number, frame: received.append((number, frame)))
    try:
        yield
    finally:
        for number in held:
            signal.signal(number, previous[number])
    if received:
        number, frame = received[0]
        previous[number](number, frame)
