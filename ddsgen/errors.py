"""The one exception type that means "the user's input is wrong".

The CLI turns an :class:`InputError` into one line on stderr and exit code 2;
anything else is a bug and keeps its traceback.
"""

import difflib


class InputError(Exception):
    """Bad user input: a malformed preset, scene list, mesh or scan folder.

    The message must be one line that names the file (and key) and the problem,
    e.g. ``presets/x.yaml: baseline_m: must be > 0, got -0.075``.
    """

    def __init__(self, message: str):
        super().__init__(" ".join(str(message).split()))


def where(source, key: str | None = None) -> str:
    """Prefix ``'file: key: '`` used by every validation message."""
    prefix = f"{source}: " if source else ""
    return prefix + (f"{key}: " if key else "")


def did_you_mean(name, known, otherwise: str = "") -> str:
    """`` (did you mean 'a'?)`` or `` (did you mean 'a' or 'b'?)`` with the one or two entries of ``known`` closest
    to ``name`` (a misspelt key is often near two: focal_lenght_px is nearest focal_y_px, then focal_px); else
    `` (OTHERWISE)`` when ``otherwise`` is given, else ""."""
    near = difflib.get_close_matches(str(name), [str(k) for k in known], n=2)
    if near:
        return f" (did you mean {' or '.join(repr(n) for n in near)}?)"
    return f" ({otherwise})" if otherwise else ""
