"""Checks of scene-list fields: each returns the value in the form the specs use or raises
:class:`~ddsgen.errors.InputError` with one line ``FILE: KEY: problem``.
"""

from __future__ import annotations

import math
from typing import Any

from ddsgen.errors import InputError, did_you_mean, where


def check_keys(source, key: str, data: Any, allowed, what: str) -> dict:
    if not isinstance(data, dict):
        raise InputError(f"{where(source, key)}expected a mapping ({what}), got {describe(data)}")
    for name in data:
        if not isinstance(name, str) or name not in allowed:
            hint = did_you_mean(name, allowed, f"valid keys: {', '.join(allowed)}")
            sub = f"{key}.{name}" if key else str(name)
            raise InputError(f"{where(source, sub)}unknown key{hint}")
    return data


def describe(value: Any) -> str:
    if value is None:
        return "nothing (null)"
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def field_number(source, key: str, value: Any, *, low=None, high=None, low_open=False, integer=False, what="") -> float:
    if isinstance(value, str):
        try:
            value = float(value.strip())  # YAML 1.1 reads 1e-3 as a string
        except ValueError:
            pass
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        kind = "an integer" if integer else "a number"
        raise InputError(f"{where(source, key)}expected {kind}{' (' + what + ')' if what else ''}, got {describe(value)}")
    if not math.isfinite(value):
        raise InputError(f"{where(source, key)}must be a finite number, got {value!r}")
    if integer:
        if isinstance(value, float) and not value.is_integer():
            raise InputError(f"{where(source, key)}expected an integer, got {value!r}")
        value = int(value)
    else:
        value = float(value)
    if low is not None:
        if low_open and not value > low:
            raise InputError(f"{where(source, key)}must be > {low:g}, got {value!r}")
        if not low_open and value < low:
            raise InputError(f"{where(source, key)}must be >= {low:g}, got {value!r}")
    if high is not None and value > high:
        raise InputError(f"{where(source, key)}must be <= {high:g}, got {value!r}")
    return value


def field_range(source, key: str, value: Any, **limits) -> tuple:
    """A fixed number or a [lo, hi] list -> (lo, hi)."""
    if isinstance(value, (list, tuple)):
        if len(value) != 2:
            raise InputError(f"{where(source, key)}expected a number or a range [lo, hi], got {describe(value)}")
        lo = field_number(source, f"{key}[0]", value[0], **limits)
        hi = field_number(source, f"{key}[1]", value[1], **limits)
        if lo > hi:
            raise InputError(f"{where(source, key)}range [lo, hi] must have lo <= hi, got {describe(list(value))}")
        return (lo, hi)
    number = field_number(source, key, value, **limits)
    return (number, number)


def field_vector(source, key: str, value: Any, length: int, **limits) -> tuple[float, ...]:
    if length == 1 and not isinstance(value, (list, tuple)):
        return (field_number(source, key, value, **limits),)
    if not isinstance(value, (list, tuple)) or len(value) != length:
        raise InputError(f"{where(source, key)}expected a list of {length} numbers, got {describe(value)}")
    return tuple(field_number(source, f"{key}[{i}]", v, **limits) for i, v in enumerate(value))


def field_size2(source, key: str, value: Any) -> tuple[float, float]:
    """A square size (one number) or [x, y]."""
    if isinstance(value, (list, tuple)):
        return field_vector(source, key, value, 2, low=0, low_open=True, high=1e4)
    size = field_number(source, key, value, low=0, low_open=True, high=1e4)
    return (size, size)


def field_text(source, key: str, value: Any) -> str:
    if not isinstance(value, str) or not value.strip():
        raise InputError(f"{where(source, key)}expected a non-empty string, got {describe(value)}")
    return value.strip()
