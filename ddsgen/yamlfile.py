"""Reading a user's YAML file (preset, scene list) with one-line errors."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import yaml

from ddsgen.errors import InputError


def read_yaml(path: Path, what: str) -> Any:
    """Parse ``path`` as YAML; any problem is an :class:`InputError` naming the file (and line).

    Args:
        path: the file.
        what: what the file is, for messages ("preset", "scene list").
    """
    if not path.is_file():
        raise InputError(f"{path}: {what} file not found")
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as error:
        raise InputError(f"{path}: cannot read {what} ({error.__class__.__name__}: {error})") from None
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError as error:
        mark = getattr(error, "problem_mark", None)
        at = f" at line {mark.line + 1}" if mark else ""
        problem = getattr(error, "problem", None) or str(error).splitlines()[0]
        raise InputError(f"{path}: malformed YAML{at}: {problem}") from None
