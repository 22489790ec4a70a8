"""Names that become paths: sensor ids, recipe and model-package names, key chunks (docs/wire.md Keys).

One pattern for all of them, and one way to turn a name into a path under a root: `check_name` refuses
anything but 1-64 characters of letters, digits, `_`, `.`, `-` starting with a letter or digit (so no
`/`, no `..`, nothing absolute, nothing hidden), and `confined` joins it under its root and refuses a
result that resolves outside that root (a symlink inside the root pointing out, for instance).
"""
from __future__ import annotations

import re
from pathlib import Path

from .errors import TensorTouchError

NAME_PATTERN = r"[A-Za-z0-9][A-Za-z0-9_.\-]{0,63}"
_NAME = re.compile(rf"\A{NAME_PATTERN}\Z")


def is_name(value) -> bool:
    return isinstance(value, str) and _NAME.match(value) is not None


def check_name(value, what: str, error: type[Exception] = TensorTouchError) -> str:
    """Return `value` if it matches NAME_PATTERN; else raise `error` naming `what` and the pattern."""
    if not is_name(value):
        shown = repr(value)[:80] if isinstance(value, str) else f"a {type(value).__name__}"
        raise error(f"{what} {shown}: expected {NAME_PATTERN} (1-64 characters of [A-Za-z0-9_.-] starting "
                    "with a letter or digit; it becomes a folder or file name)")
    return value


def confined(root: str | Path, name: str, what: str, error: type[Exception] = TensorTouchError) -> Path:
    """`root / name` for a checked `name`, refused unless it resolves to a direct child of `root`."""
    root = Path(root)
    path = root / check_name(name, what, error)
    if path.resolve().parent != root.resolve():
        raise error(f"{what} {name!r}: {path} resolves outside {root}; refusing it")
    return path
