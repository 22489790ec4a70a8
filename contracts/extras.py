"""Optional extras: which one a command or a missing module needs, and the one line that says how to
install it in the form that fits this installation.

An editable checkout (`pip install -e .`: this file's folder's parent holds pyproject.toml) is told `pip install -e '.[train]'` (the checkout's path when
the shell is elsewhere); an installed wheel `pip install 'tensortouch[train]'`. The extras and their
distributions are read from the installed package's own metadata (pyproject's
`[project.optional-dependencies]`), never from a list kept here; only import names that differ from
their distribution's name are spelled out.

A command declares the extra it needs with `parser.set_defaults(extra="train")` (a group's parser
declares it for all its subcommands); the `tensortouch` shell checks it before the command runs, and
turns a `ModuleNotFoundError` of a module some extra provides into the same line (exit 2).
"""
from __future__ import annotations

import os
import re
from functools import lru_cache
from importlib import metadata
from pathlib import Path

from .errors import CommandError

DIST = "tensortouch"
# import name -> distribution name, where the two differ (the rest import under their own name)
IMPORT_TO_DIST = {"foxglove": "foxglove-sdk", "rerun": "rerun-sdk", "sklearn": "scikit-learn",
                  "pinocchio": "pin", "example_robot_data": "example-robot-data", "zenoh": "eclipse-zenoh",
                  "cv2": "opencv-python-headless", "usb": "pyusb", "can": "python-can", "serial": "pyserial"}
# where a distribution is in several extras, the one to name (the smaller install)
PREFERRED = ("viewers", "cluster", "hand", "lerobot", "train")


class MissingExtra(CommandError):
    """A command needs an optional extra that is not installed (the message says how to install it)."""


def _norm(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


@lru_cache(maxsize=1)
def extras() -> dict[str, tuple[str, ...]]:
    """extra name -> the distributions it adds (normalized names), from the installed metadata."""
    out: dict[str, list[str]] = {}
    for req in metadata.requires(DIST) or ():
        m = re.search(r"""extra\s*==\s*["']([^"']+)["']""", req)
        name = re.match(r"\s*([A-Za-z0-9][A-Za-z0-9._-]*)", req)
        if m and name:
            out.setdefault(m.group(1), []).append(_norm(name.group(1)))
    return {k: tuple(v) for k, v in out.items()}


def extra_of_module(module: str, prefer: str | None = None) -> str | None:
    """The extra whose distributions provide the top-level `module` (None: no extra does)."""
    top = module.split(".")[0]
    dist = _norm(IMPORT_TO_DIST.get(top, top))
    having = [e for e, dists in extras().items() if dist in dists and e != "test"]
    if not having:
        return None
    if prefer in having:
        return prefer
    return sorted(having, key=lambda e: PREFERRED.index(e) if e in PREFERRED else len(PREFERRED))[0]


def missing(extra: str) -> list[str]:
    """The distributions of `extra` that are not installed (an unknown extra: [])."""
    out = []
    for dist in extras().get(extra, ()):
        try:
            metadata.version(dist)
        except metadata.PackageNotFoundError:
            out.append(dist)
    return out


def _editable_checkout() -> Path | None:
    """The checkout this code runs from (an editable install: pyproject.toml beside contracts/), else None
    (an installed wheel: contracts/ lies under site-packages/tensortouch/)."""
    root = Path(__file__).resolve().parents[1]
    try:
        text = (root / "pyproject.toml").read_text(encoding="utf-8")
    except OSError:
        return None
    return root if re.search(r'(?m)^name\s*=\s*"tensortouch"', text) else None


def install_command(extra: str) -> str:
    """`pip install ...` for `extra`, in the form that fits how tensortouch was installed."""
    checkout = _editable_checkout()
    if checkout is None:
        return f"pip install '{DIST}[{extra}]'"
    try:
        here = Path.cwd().resolve() == checkout.resolve()
    except OSError:
        here = False
    where = "." if here else os.fspath(checkout)
    return f"pip install -e '{where}[{extra}]'"


def hint(extra: str, module: str | None = None) -> str:
    """One line: needs `extra` (`module` is what was found missing), and how to install it."""
    gone = f" ({module} not installed)" if module else ""
    return f"needs the {extra} extra{gone}: {install_command(extra)}"


def require(extra: str) -> None:
    """Raise MissingExtra (one line naming the extra) unless every distribution of `extra` is installed."""
    gone = missing(extra)
    if gone:
        raise MissingExtra(hint(extra, gone[0] + (f" and {len(gone) - 1} more" if len(gone) > 1 else "")))


def hint_for_import_error(exc: ImportError, prefer: str | None = None) -> str | None:
    """The one-line hint for an ImportError of a module some extra provides (None: not an extra's)."""
    name = getattr(exc, "name", None)
    if not name:
        m = re.search(r"No module named '([^']+)'", str(exc))
        name = m.group(1) if m else None
    if not name:
        return None
    extra = extra_of_module(name, prefer)
    if extra is None:
        return None
    return hint(extra, name.split(".")[0])
