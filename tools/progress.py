"""The tools' one progress helper (tqdm): bars on stderr that log lines do not break into.

    cb = stage_progress("record")          # cb(stage, i, n): the callback the long jobs take
    tick = count_progress("network pass", "frame")    # tick(i, n)

While a bar is open, log records are written above it (tqdm's logging redirect).
Bars are drawn only on a terminal (`disable=None`): in CI logs and pipes the long jobs log instead.
"""
from __future__ import annotations

import sys


class StageProgress:
    """A callback `(stage, i, n)` that draws one bar per stage (a new stage or total starts a new bar)."""

    def __init__(self, desc: str = "", unit: str = "it"):
        self.desc, self.unit, self._bar, self._key, self._redirect = desc, unit, None, None, None

    def __call__(self, stage: str, i: int, n: int) -> None:
        key = (stage, n)
        if key != self._key:
            from tqdm import tqdm  # imported when a bar opens: registering a command needs none
            from tqdm.contrib.logging import logging_redirect_tqdm

            self.close()
            label = f"{self.desc} {stage}".strip()
            self._redirect = logging_redirect_tqdm()      # log lines go above the bar, not into it
            self._redirect.__enter__()
            self._bar = tqdm(total=n, desc=label, unit=self.unit, file=sys.stderr, disable=None,
                             dynamic_ncols=True, leave=True)
            self._key = key
        self._bar.n = i
        self._bar.refresh()
        if i >= n:
            self.close()

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()
        if self._redirect is not None:
            self._redirect.__exit__(None, None, None)
        self._bar, self._key, self._redirect = None, None, None


def stage_progress(desc: str = "", unit: str = "it") -> StageProgress:
    return StageProgress(desc, unit)


def count_progress(desc: str, unit: str = "it"):
    """A callback `(i, n)` for loops that only count (one bar)."""
    bar = StageProgress(desc, unit)
    return lambda i, n: bar("", i, n)

