"""The one exception type that means "the user's input is wrong".

The CLI turns an :class:`InputError` into one line on stderr and exit code 2;
anything else is a bug and keeps its traceback.
"""


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
