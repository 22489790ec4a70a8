"""Deploy-side subcommands of `tensortouch` (run, listen). Thin shells over runtime/ cores."""
from __future__ import annotations


def register(sub) -> None:
    """Add the deploy subcommands to the `tensortouch` parser."""
