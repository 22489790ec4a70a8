"""Gel temperature for the effects that need it (e.g. `temperature_softening`).

A live sensor would read a thermistor; on a replayed session the recording's own
`temperature.csv` (t, celsius; docs/session.md) is the source. `TemperatureTrack` is the pure
core: the temperature at a time of the recording's clock, linear between samples, held at the ends
(a looping replay folds its frame times back first: `ReplayCamera.recording_time`).
"""
from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from ...contracts.errors import SessionError

log = logging.getLogger(__name__)


class TemperatureTrack:
    """Temperature (°C) as a function of the frame clock (s)."""

    def __init__(self, t: np.ndarray, celsius: np.ndarray):
        t = np.asarray(t, dtype=np.float64).ravel()
        c = np.asarray(celsius, dtype=np.float64).ravel()
        if t.size == 0 or t.size != c.size:
            raise SessionError(f"temperature track: expected equal, non-empty t and celsius columns, "
                               f"got {t.size} and {c.size} values")
        if not np.all(np.isfinite(t)) or not np.all(np.isfinite(c)):
            raise SessionError("temperature track: t and celsius must be finite numbers")
        if t.size > 1 and np.any(np.diff(t) <= 0):
            raise SessionError("temperature track: t must be strictly increasing")
        self.t, self.celsius = t, c

    def __call__(self, t: float) -> float:
        return float(np.interp(float(t), self.t, self.celsius))

    @classmethod
    def from_session(cls, folder: str | Path) -> "TemperatureTrack | None":
        """The session's temperature stream, or None when it records none."""
        from ...contracts.session import load_session

        session = load_session(folder, check_frames=False)
        if not session.has("temperature"):
            return None
        data = session.table("temperature")
        if len(data) == 0:
            return None
        log.info("temperature from %s (%d samples, %.2f–%.2f °C)", session.path, len(data),
                 float(data[:, 1].min()), float(data[:, 1].max()))
        try:
            return cls(data[:, 0], data[:, 1])
        except SessionError as exc:
            raise SessionError(f"{session.path}/temperature.csv: {exc}") from None
