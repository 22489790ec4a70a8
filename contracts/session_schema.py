"""Plausibility of a session (docs/session.md): the numbers of session.json and of every stream row.

contracts/session.py checks the session's shape (schema, streams, files, header, row lengths,
finite values, clocks) and calls these for what ties the numbers to a recording:

- session.json: no NaN or infinity anywhere (JSON's NaN/Infinity extensions), nesting at most
  schema.MAX_DEPTH deep; `clock.t0` (when present) a finite number; `streams.wrench.ft_to_indenter`
  a unit quaternion `rotation_wxyz` (4 numbers, norm within QUAT_NORM) and `translation_mm` (3
  numbers within ±MAX_MM).
- every stream row, in the house units (mm, N, N·mm, s, °C), inside COLUMN_RANGES: times, lengths
  (poses: a rig is at most MAX_MM across), quaternion components with a norm within QUAT_NORM,
  forces, torques, temperatures; indenter ids and frame indices whole numbers >= 0.

Every problem is one SessionError naming the file (and row) and the field.
"""
from __future__ import annotations

import math

import numpy as np

from .errors import SessionError
from .schema import MAX_DEPTH, Range, SchemaError, check_depth, finite_everywhere, number, numbers

MAX_MM = 10_000.0                    # 10 m: no mocap volume or F/T offset is larger
QUAT_NORM = Range(0.99, 1.01)        # a unit quaternion, as written to 9 significant digits or a bit looser
TIME_S = Range(-1e10, 1e10)          # monotonic clocks, recording clocks and Unix time alike
# (quantity or column kind) -> range in house units
RANGES = {"time": TIME_S, "length": Range(-MAX_MM, MAX_MM), "force": Range(-1e4, 1e4),
          "torque": Range(-1e7, 1e7), "temperature": Range(-100.0, 300.0), "quat": Range(-1.001, 1.001),
          "id": Range(0, 1e6), "index": Range(0, 1e9)}
# the kind of each column of each stream (contracts/session.py STREAM_COLUMNS order)
COLUMN_KINDS = {
    "poses": ["time", "id", "length", "length", "length", "quat", "quat", "quat", "quat"],
    "wrench": ["time", "id", "force", "force", "force", "torque", "torque", "torque"],
    "frames": ["time", "index"],
    "temperature": ["time", "temperature"],
}


def check_manifest_values(manifest: dict, where: str) -> None:
    """The numbers of session.json (already shape-checked by validate_manifest)."""
    try:
        check_depth(manifest, "session.json", MAX_DEPTH)
        finite_everywhere(manifest)
        clock = manifest.get("clock")
        if isinstance(clock, dict) and "t0" in clock:
            number(clock["t0"], "clock.t0", TIME_S)
        wrench = manifest["streams"].get("wrench")
        if isinstance(wrench, dict) and "ft_to_indenter" in wrench:
            check_ft_to_indenter(wrench["ft_to_indenter"], "streams.wrench.ft_to_indenter")
    except SchemaError as exc:
        raise SessionError(f"{where}: {exc}") from None


def check_ft_to_indenter(tf, path: str) -> None:
    """{rotation_wxyz: unit quaternion, translation_mm: 3 numbers}: p_indenter = R p_ft + t."""
    if not isinstance(tf, dict):
        raise SchemaError(f"{path} is {tf!r:.60}, expected {{\"rotation_wxyz\": [w, x, y, z], \"translation_mm\": [x, y, z]}}")
    q = numbers(tf.get("rotation_wxyz"), f"{path}.rotation_wxyz", 4, RANGES["quat"], "numbers (a unit quaternion)")
    norm = math.sqrt(sum(v * v for v in q))
    if not QUAT_NORM.holds(norm):
        raise SchemaError(f"{path}.rotation_wxyz has norm {norm:.6g}, expected a unit quaternion (norm in {QUAT_NORM})")
    numbers(tf.get("translation_mm"), f"{path}.translation_mm", 3, RANGES["length"], "numbers (mm)")




def check_rows(stream: str, table: np.ndarray, columns: list[str], where) -> None:
    """Every row of a (finite, house-unit) stream table inside COLUMN_RANGES; names file:row and column."""
    kinds = COLUMN_KINDS.get(stream)
    if kinds is None or not len(table):
        return
    for col, kind in enumerate(kinds):
        rng, v = RANGES[kind], table[:, col]
        bad = (v < rng.lo) | (v > rng.hi)
        if kind in ("id", "index"):
            bad |= v != np.round(v)
        if bad.any():
            row = int(np.argmax(bad))
            what = "a whole number" if kind in ("id", "index") else "a value"
            raise SessionError(f"{where}:{row + 2}: {columns[col]} = {v[row]:.6g}, expected {what} in {rng} "
                               f"({kind}{', house units' if kind not in ('id', 'index', 'quat') else ''})")
    if stream == "poses":
        norm = np.linalg.norm(table[:, 5:9], axis=1)
        bad = (norm < QUAT_NORM.lo) | (norm > QUAT_NORM.hi)
        if bad.any():
            row = int(np.argmax(bad))
            raise SessionError(f"{where}:{row + 2}: quaternion qw,qx,qy,qz has norm {norm[row]:.6g}, expected a "
                               f"unit quaternion (norm in {QUAT_NORM})")
