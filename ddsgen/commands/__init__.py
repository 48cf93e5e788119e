"""One module per CLI command; each defines a click command named like the module."""


def split_names(values) -> list[str]:
    """Names from a repeatable, comma-separated option: ("a,b", "c") -> ["a", "b", "c"]."""
    return [name.strip() for value in values for name in value.split(",") if name.strip()]
