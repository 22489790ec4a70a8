"""The session contract: one recording (real rig or digital twin) as a directory.

```
<session>/
  session.json          manifest (schema, schema_version, sensor_id, units, clock, streams, provenance)
  poses.csv             t,indenter,x,y,z,qw,qx,qy,qz        (s, -, mm, unit quaternion)
  wrench.csv            t,indenter,fx,fy,fz,tx,ty,tz        (s, -, N in the F/T frame, N*mm)
  frames.csv            t,index                              (s, frame number in the image stream)
  frames.avi | frames/  image stream: a video file or a folder of PNGs 000000.png, 000001.png, ...
  temperature.csv       t,celsius
  truth/                twin-only ground truth; no deploy or workbench stage reads it
```

Only `frames` is required; the other streams are listed in the manifest when present; `wrench`
needs `streams.wrench.ft_to_indenter` {rotation_wxyz, translation_mm}: p_indenter = R p_ft + t.
Validation names the problem: missing stream, unit mismatch, non-monotonic clock, truncated rows
or frames, a value no recording holds (contracts/session_schema.py: ranges, unit quaternions) (video frames are counted from the AVI's RIFF headers, PNGs checked for their end). This module
is pure (json + numpy + csv) so both the runtime (replay) and `tools/` (twin, training, workbench)
read sessions through the same code. See docs/session.md.
"""
from __future__ import annotations

import csv
import io
import json
import struct
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .errors import SessionError
from .files import atomic_write, atomic_write_json
from .names import check_name
from .session_schema import check_manifest_values, check_rows
from .units import HOUSE, accepted, to_house

SCHEMA = "tensortouch.session"
SCHEMA_VERSION = 1
UNITS = dict(HOUSE)   # the house units every stream is read in (contracts/units.py lists the other spellings)

STREAM_COLUMNS = {
    "poses": ["t", "indenter", "x", "y", "z", "qw", "qx", "qy", "qz"],
    "wrench": ["t", "indenter", "fx", "fy", "fz", "tx", "ty", "tz"],
    "frames": ["t", "index"],
    "temperature": ["t", "celsius"],
}
# the physical quantity of each stream column (None: a count, an id or a unitless value)
COLUMN_QUANTITIES = {
    "poses": ["time", None, "length", "length", "length", None, None, None, None],
    "wrench": ["time", None, "force", "force", "force", "torque", "torque", "torque"],
    "frames": ["time", None],
    "temperature": ["time", "temperature"],
}
STREAM_FILES = {"poses": "poses.csv", "wrench": "wrench.csv", "frames": "frames.csv",
                "temperature": "temperature.csv"}


@dataclass
class Session:
    """A validated session: manifest plus lazily loaded streams."""

    path: Path
    manifest: dict
    _cache: dict = field(default_factory=dict, repr=False)

    @property
    def sensor_id(self) -> str:
        return self.manifest["sensor_id"]

    @property
    def streams(self) -> dict:
        return self.manifest["streams"]

    def has(self, stream: str) -> bool:
        return stream in self.streams

    def table(self, stream: str) -> np.ndarray:
        """A stream as a float64 array with the columns of STREAM_COLUMNS[stream], in house units, the
        sensor frame and the camera's clock (the stream's rig calibration applied: `to_house_frame`)."""
        if stream not in self._cache:
            if stream not in self.streams:
                raise SessionError(f"{self.path / 'session.json'}: no stream '{stream}' "
                                   f"(present: {sorted(self.streams)})")
            self._cache[stream] = to_house_frame(self.recorded(stream), stream, self.streams[stream])
        return self._cache[stream]

    def recorded(self, stream: str) -> np.ndarray:
        """A stream as its file holds it, in house units but without its rig calibration (clock offset,
        F/T bias, mocap extrinsic: `to_house_frame`) — what a tool rewriting the file works on."""
        if stream not in self.streams:
            raise SessionError(f"{self.path / 'session.json'}: no stream '{stream}' (present: {sorted(self.streams)})")
        info = self.streams[stream]
        table = read_table(self.path / info.get("file", STREAM_FILES[stream]), STREAM_COLUMNS[stream])
        return to_house_units(table, stream, self.manifest.get("units", {}))

    def with_table(self, stream: str, table: np.ndarray) -> Session:
        """A copy in memory whose `stream` is `table` (house units, the stream's columns); the other
        streams, the manifest and the files it points to are this session's."""
        if stream not in self.streams:
            raise SessionError(f"{self.path / 'session.json'}: no stream '{stream}' to replace")
        table = np.asarray(table, dtype=np.float64)
        if table.ndim != 2 or table.shape[1] != len(STREAM_COLUMNS[stream]):
            raise SessionError(f"{self.path}: stream '{stream}' needs {len(STREAM_COLUMNS[stream])} columns "
                               f"({','.join(STREAM_COLUMNS[stream])}), got shape {table.shape}")
        return Session(self.path, self.manifest, {**self._cache, stream: table})

    def image_source(self) -> tuple[str, Path]:
        """('video', file) or ('images', folder) holding the camera frames."""
        info = self.streams["frames"]
        if "video" in info:
            return "video", self.path / info["video"]
        if "images" in info:
            return "images", self.path / info["images"]
        raise SessionError(f"{self.path / 'session.json'}: streams.frames needs 'video' or 'images'")


def read_table(path: Path, columns: list[str]) -> np.ndarray:
    """Read a CSV stream; the header must name exactly `columns` in order."""
    path = Path(path)
    if not path.is_file():
        raise SessionError(f"{path}: stream file missing (expected columns {','.join(columns)})")
    lineno = 1
    try:
        with open(path, newline="", encoding="utf-8") as fh:
            reader = csv.reader(fh)
            header = next(reader, None)
            if header != columns:
                raise SessionError(f"{path}: header {str(header)[:200]} does not match expected {columns}")
            rows = []
            for lineno, row in enumerate(reader, start=2):
                if len(row) != len(columns):
                    raise SessionError(f"{path}:{lineno}: {len(row)} values, expected {len(columns)} "
                                       f"(truncated file?)")
                try:
                    rows.append([float(v) for v in row])
                except ValueError:
                    raise SessionError(f"{path}:{lineno}: non-numeric value in {str(row)[:200]}") from None
    except UnicodeDecodeError as exc:
        raise SessionError(f"{path}: not UTF-8 text ({exc.reason} at byte {exc.start}); expected CSV with "
                           f"columns {','.join(columns)}") from None
    except csv.Error as exc:
        raise SessionError(f"{path}:{lineno + 1}: not readable as CSV ({exc}); expected numbers in columns "
                           f"{','.join(columns)}") from None
    except OSError as exc:
        raise SessionError(f"{path}: cannot read ({exc.strerror or exc})") from None
    data = np.asarray(rows, dtype=np.float64).reshape(-1, len(columns))
    return data


def _column_maps(stream: str, units: dict) -> list[tuple[int, float, float]]:
    """(column, scale, offset) of each column of `stream` whose unit in `units` is not the house one
    (house = scale·v + offset)."""
    out = []
    for col, quantity in enumerate(COLUMN_QUANTITIES.get(stream, [])):
        if quantity in units:
            scale, offset = to_house(quantity, units[quantity])
            if scale != 1.0 or offset != 0.0:
                out.append((col, scale, offset))
    return out


def to_house_units(table: np.ndarray, stream: str, units: dict) -> np.ndarray:
    """A stream table read in the manifest's `units`, converted to the house units (a copy when any
    column changes)."""
    maps = _column_maps(stream, units)
    out = table.copy() if maps else table
    for col, scale, offset in maps:
        out[:, col] = out[:, col] * scale + offset
    return out


CSV_FORMAT = "%.9g"           # every number of a stream file written by write_table


def write_table(path: Path, columns: list[str], data: np.ndarray) -> None:
    """Write a CSV stream atomically (write to a temp file, then rename)."""
    path = Path(path)
    data = np.asarray(data, dtype=np.float64).reshape(-1, len(columns))
    def write(fh):
        fh.write((",".join(columns) + "\n").encode())
        np.savetxt(fh, data, delimiter=",", fmt=CSV_FORMAT)

    atomic_write(path, write, mkdir=False)


def as_written(data: np.ndarray) -> np.ndarray:
    """`data` as write_table's file gives it back to read_table (the same text, the same parse)."""
    data = np.asarray(data, dtype=np.float64)
    buf = io.StringIO()
    np.savetxt(buf, data.reshape(len(data), -1), delimiter=",", fmt=CSV_FORMAT)
    return np.asarray([[float(v) for v in line.split(",")] for line in buf.getvalue().splitlines()],
                      dtype=np.float64).reshape(data.shape)


def validate_manifest(manifest: dict, where: str = "session.json") -> None:
    """Raise SessionError naming the first field that breaks the contract."""
    if not isinstance(manifest, dict):
        raise SessionError(f"{where}: expected a JSON object, got {type(manifest).__name__}")
    if manifest.get("schema") != SCHEMA:
        raise SessionError(f"{where}: schema is {manifest.get('schema')!r}, expected {SCHEMA!r}")
    version = manifest.get("schema_version")
    if not isinstance(version, int) or version > SCHEMA_VERSION:
        raise SessionError(f"{where}: schema_version {version!r} not supported (this runtime reads <= {SCHEMA_VERSION})")
    check_name(manifest.get("sensor_id"), f"{where}: sensor_id", SessionError)   # it names folders and keys
    units = manifest.get("units", {})
    if not isinstance(units, dict):
        raise SessionError(f"{where}: units must be an object such as {UNITS}")
    for key, unit in units.items():
        if key in UNITS and to_house(key, unit) is None:
            raise SessionError(f"{where}: units.{key} is {unit!r}, expected one of {accepted(key)} "
                               "(streams are read in mm, N, N*mm, s, degC)")
    streams = manifest.get("streams")
    if not isinstance(streams, dict) or "frames" not in streams:
        raise SessionError(f"{where}: streams must be an object with at least 'frames'")
    unknown = set(streams) - set(STREAM_COLUMNS)
    if unknown:
        raise SessionError(f"{where}: unknown streams {sorted(unknown)} (known: {sorted(STREAM_COLUMNS)})")
    for name, info in streams.items():
        if not isinstance(info, dict):
            raise SessionError(f"{where}: streams.{name} must be an object such as {{\"file\": \"{name}.csv\"}}")
        for key in ("file", "video", "images"):
            if key in info and not (isinstance(info[key], str) and _plain_name(info[key])):
                raise SessionError(f"{where}: streams.{name}.{key} is {info[key]!r}, expected a file name "
                                   f"inside the session folder")
        for key in ("rows", "bytes"):
            if info.get(key) is not None and (not isinstance(info[key], int) or isinstance(info[key], bool)
                                              or info[key] < 0):
                raise SessionError(f"{where}: streams.{name}.{key} is {info[key]!r}, expected a count >= 0")
        _check_stream_calibration(name, info, where)
    check_manifest_values(manifest, where)     # numbers: finite, unit quaternion, ranges (session_schema.py)


POSE_FRAMES = ("sensor", "mocap")


def quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product of (..., 4) quaternions in w, x, y, z order."""
    aw, ax, ay, az = np.moveaxis(np.asarray(a, np.float64), -1, 0)
    bw, bx, by, bz = np.moveaxis(np.asarray(b, np.float64), -1, 0)
    return np.stack([aw * bw - ax * bx - ay * by - az * bz, aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx, aw * bz + ax * by - ay * bx + az * bw], axis=-1)


def quat_matrix(q: np.ndarray) -> np.ndarray:
    """(..., 4) unit quaternions (w, x, y, z) → (..., 3, 3) rotation matrices."""
    w, x, y, z = np.moveaxis(np.asarray(q, np.float64), -1, 0)
    return np.stack([np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
                     np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
                     np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1)], -2)


def mocap_to_sensor(poses: np.ndarray, rotation_wxyz, translation_mm) -> np.ndarray:
    """Pose rows (t, indenter, x, y, z, qw, qx, qy, qz) in the mocap frame → the sensor frame with the
    extrinsic p_sensor = R p_mocap + t (R from `rotation_wxyz`, normalised), q_sensor = q_R ⊗ q_mocap;
    quaternions kept with qw ≥ 0."""
    q = np.asarray(rotation_wxyz, np.float64)
    q = q / np.linalg.norm(q)
    out = np.array(poses, dtype=np.float64, copy=True)
    out[:, 2:5] = out[:, 2:5] @ quat_matrix(q).T + np.asarray(translation_mm, np.float64)
    qs = quat_mul(q, out[:, 5:9])
    out[:, 5:9] = qs * np.where(qs[:, :1] < 0, -1.0, 1.0)
    return out


def to_house_frame(table: np.ndarray, stream: str, info: dict) -> np.ndarray:
    """A stream's rig calibration, applied as every stage reads it (house units first): the stream's clock
    offset (`clock_offset_s`: its stamps run that far ahead of the camera's, t − offset), the F/T `bias`
    ({indenter id: six numbers in N and N*mm}, subtracted from that indenter's rows) and, for poses
    recorded in the mocap frame
    (`frame: "mocap"`), the `mocap_to_sensor` extrinsic. Streams without these fields are unchanged."""
    offset = info.get("clock_offset_s")
    bias = info.get("bias") if stream == "wrench" else None
    mocap = stream == "poses" and info.get("frame") == "mocap"
    if offset is None and bias is None and not mocap:
        return table
    table = np.array(table, dtype=np.float64, copy=True)
    if offset is not None:
        table[:, 0] -= float(offset)
    if bias is not None:
        for k, b in bias.items():
            table[table[:, 1] == int(k), 2:8] -= np.asarray(b, np.float64)
    if mocap:
        ext = info["mocap_to_sensor"]
        table = mocap_to_sensor(table, ext["rotation_wxyz"], ext["translation_mm"])
    return table


def _numbers(value, n: int) -> bool:
    return (isinstance(value, list) and len(value) == n
            and all(isinstance(v, (int, float)) and not isinstance(v, bool) and np.isfinite(v) for v in value))


def _check_stream_calibration(name: str, info: dict, where: str) -> None:
    """The rig-calibration fields of a stream (to_house_frame), each checked by type and size."""
    off = info.get("clock_offset_s")
    if off is not None and not (_numbers([off], 1) and abs(off) <= 60.0):
        raise SessionError(f"{where}: streams.{name}.clock_offset_s is {off!r}, expected seconds (|offset| <= 60)")
    bias = info.get("bias") if name == "wrench" else None
    if bias is not None and not (isinstance(bias, dict) and all(
            isinstance(k, str) and k.isdigit() and _numbers(v, 6) for k, v in bias.items())):
        raise SessionError(f"{where}: streams.wrench.bias is {str(bias)[:200]}, expected {{indenter id: 6 finite "
                           "numbers (fx, fy, fz in N, tx, ty, tz in N*mm)}}")
    if name == "poses" and "frame" in info:
        if info["frame"] not in POSE_FRAMES:
            raise SessionError(f"{where}: streams.poses.frame is {info['frame']!r}, expected one of {list(POSE_FRAMES)}")
        if info["frame"] == "mocap":
            ext = info.get("mocap_to_sensor")
            if not (isinstance(ext, dict) and _numbers(ext.get("rotation_wxyz"), 4) and
                    _numbers(ext.get("translation_mm"), 3) and np.linalg.norm(ext["rotation_wxyz"]) > 0.5):
                raise SessionError(f"{where}: streams.poses.mocap_to_sensor must give rotation_wxyz (a unit "
                                   "quaternion, 4 numbers) and translation_mm (3 numbers): "
                                   "p_sensor = R p_mocap + t (poses recorded in the mocap frame)")


def _plain_name(name: str) -> bool:
    """A relative path inside the session folder (no absolute path, no '..')."""
    p = Path(name)
    return bool(name) and not p.is_absolute() and ".." not in p.parts and "\x00" not in name


def _check_clock(name: str, t: np.ndarray, per_indenter: np.ndarray | None, where: Path) -> None:
    groups = [t] if per_indenter is None else [t[per_indenter == k] for k in np.unique(per_indenter)]
    for g in groups:
        if g.size > 1 and np.any(np.diff(g) <= 0):
            bad = int(np.argmax(np.diff(g) <= 0)) + 1
            raise SessionError(f"{where}: stream '{name}' clock not strictly increasing at row {bad + 1} "
                               f"(t={g[bad]:.6f} s after {g[bad - 1]:.6f} s)")


def avi_frame_count(path: Path) -> int:
    """Complete video chunks ('##dc'/'##db') in an AVI file's 'movi' lists, read from the RIFF
    chunk headers only (pure Python; a truncated file counts only the chunks that are whole)."""
    size = path.stat().st_size
    count = 0
    with open(path, "rb") as fh:
        stack = [(0, size, False)]            # (position, end, inside 'movi') of each open list
        while stack:
            pos, end, in_movi = stack.pop()
            if pos + 8 > end:
                continue
            fh.seek(pos)
            head = fh.read(12)
            if len(head) < 8:
                continue
            cid, clen = head[:4], struct.unpack("<I", head[4:8])[0]
            body_end = pos + 8 + clen
            stack.append((body_end + (clen & 1), end, in_movi))          # the next sibling, after the children
            if cid in (b"RIFF", b"LIST"):
                stack.append((pos + 12, min(body_end, end), head[8:12] == b"movi" or in_movi))
            elif in_movi and cid[2:4] in (b"dc", b"db") and body_end <= size:
                count += 1
    return count


def _check_video(src: Path, info: dict, n: int) -> None:
    if not src.is_file():
        raise SessionError(f"{src}: frame video missing")
    size = src.stat().st_size
    if isinstance(info.get("bytes"), int) and size < info["bytes"]:
        raise SessionError(f"{src}: {size} bytes but the manifest recorded {info['bytes']} (truncated frames)")
    if src.suffix.lower() == ".avi":
        count = avi_frame_count(src)
        if count < n:
            raise SessionError(f"{src}: {count} complete frames but frames.csv lists {n} (truncated frames)")


_PNG_END = b"\x00\x00\x00\x00IEND\xaeB`\x82"


def _check_pngs(src: Path, indices: np.ndarray) -> None:
    """Every listed frame NNNNNN.png exists and ends with its IEND chunk (not cut short)."""
    for i in indices.astype(int):
        f = src / f"{i:06d}.png"
        try:
            with open(f, "rb") as fh:
                fh.seek(max(f.stat().st_size - 12, 0))
                tail = fh.read(12)
        except OSError:
            raise SessionError(f"{f}: frame {i} listed in frames.csv is missing (truncated frames)") from None
        if tail != _PNG_END:
            raise SessionError(f"{f}: PNG is cut short (truncated frames)")


def _check_wrench(session: "Session", where: Path) -> None:
    info = session.streams["wrench"]
    tf = info.get("ft_to_indenter")
    if not isinstance(tf, dict) or not isinstance(tf.get("rotation_wxyz"), list) or len(tf["rotation_wxyz"]) != 4 \
            or not isinstance(tf.get("translation_mm"), list) or len(tf["translation_mm"]) != 3:
        raise SessionError(f"{where}: streams.wrench.ft_to_indenter must give rotation_wxyz (4 numbers) and "
                           "translation_mm (3 numbers): p_indenter = R p_ft + t")
    if session.has("poses"):
        extra = set(np.unique(session.table("wrench")[:, 1])) - set(np.unique(session.table("poses")[:, 1]))
        if extra:
            raise SessionError(f"{where}: wrench has indenter ids {sorted(int(e) for e in extra)} with no poses")


def load_session(path: str | Path, check_frames: bool = True) -> Session:
    """Open and validate a session directory. Raises SessionError naming the problem."""
    path = Path(path)
    manifest_path = path / "session.json"
    if not manifest_path.is_file():
        raise SessionError(f"{path}: not a session (no session.json)")
    try:
        manifest = json.loads(manifest_path.read_bytes().decode("utf-8"))
    except UnicodeDecodeError as exc:
        raise SessionError(f"{manifest_path}: not UTF-8 text ({exc.reason} at byte {exc.start}); "
                           f"expected a JSON object") from None
    except (json.JSONDecodeError, RecursionError) as exc:
        raise SessionError(f"{manifest_path}: not valid JSON ({str(exc)[:200]})") from None
    validate_manifest(manifest, str(manifest_path))
    session = Session(path, manifest)
    for name in session.streams:
        table = session.table(name)
        where = path / session.streams[name].get("file", STREAM_FILES[name])
        if not np.all(np.isfinite(table)):
            row = int(np.argmax(~np.all(np.isfinite(table), axis=1))) + 2
            raise SessionError(f"{where}:{row}: non-finite value in stream '{name}'")
        check_rows(name, table, STREAM_COLUMNS[name], where)
        rows = session.streams[name].get("rows")
        if isinstance(rows, int) and len(table) != rows:
            raise SessionError(f"{where}: {len(table)} rows but the manifest recorded {rows} (truncated stream)")
        ind = table[:, 1] if name in ("poses", "wrench") else None
        _check_clock(name, table[:, 0], ind, where)
    if session.has("wrench"):
        _check_wrench(session, manifest_path)
    if check_frames:
        kind, src = session.image_source()
        n = len(session.table("frames"))
        if kind == "images":
            if not src.is_dir():
                raise SessionError(f"{src}: frame folder missing")
            count = len(list(src.glob("*.png")))
            if count < n:
                raise SessionError(f"{src}: {count} images but frames.csv lists {n} (truncated frames)")
            _check_pngs(src, session.table("frames")[:, 1])
        else:
            _check_video(src, session.streams["frames"], n)
    return session


def rewrite_in_units(path: str | Path, units: dict | None = None) -> Session:
    """Rewrite a session folder's stream files in `units` (default: the house units) in place, each
    file atomically and the manifest last. A tool that copies a recording and rewrites one stream
    calls this first, so every stream stays in the units its manifest states."""
    session = load_session(path, check_frames=False)
    current = {**UNITS, **session.manifest.get("units", {})}
    target = {**current, **dict(units or UNITS)}
    bad = {k: u for k, u in target.items() if k in UNITS and to_house(k, u) is None}
    if bad:
        raise SessionError(f"{session.path}: cannot write in units {bad} (accepted: see contracts/units.py)")
    if all(to_house(k, target[k]) == to_house(k, current[k]) for k in UNITS):
        return session
    for name, info in session.streams.items():
        table = session.recorded(name).copy()          # house units, the file's frame and clock
        for col, scale, offset in _column_maps(name, target):
            table[:, col] = (table[:, col] - offset) / scale
        write_table(session.path / info.get("file", STREAM_FILES[name]), STREAM_COLUMNS[name], table)
    write_manifest(session.path, dict(session.manifest, units=target))
    return load_session(session.path, check_frames=False)


CALIBRATION_FIELDS = ("clock_offset_s", "bias", "mocap_to_sensor")


def write_stream(path: str | Path, stream: str, table: np.ndarray) -> Session:
    """Replace a stream's file with `table` as `Session.table` reads it (house units, sensor frame, camera
    clock). The recording is first rewritten in house units (`rewrite_in_units`); the stream's
    rig-calibration fields leave the manifest (they are in the numbers now); the file first, the
    manifest last. Returns the session as it now reads."""
    session = rewrite_in_units(path)
    info = {k: v for k, v in session.streams[stream].items() if k not in CALIBRATION_FIELDS}
    if stream == "poses" and "frame" in info:
        info["frame"] = "sensor"
    info["rows"] = int(len(table))
    write_table(session.path / info.get("file", STREAM_FILES[stream]), STREAM_COLUMNS[stream], table)
    write_manifest(session.path, dict(session.manifest, streams={**session.streams, stream: info}))
    return load_session(session.path, check_frames=False)


def write_manifest(path: str | Path, manifest: dict) -> None:
    """Validate and atomically write session.json."""
    path = Path(path)
    validate_manifest(manifest, str(path / "session.json"))
    atomic_write_json(path / "session.json", manifest, indent=2, sort_keys=True, mkdir=False)


def new_manifest(sensor_id: str, streams: dict, provenance: dict | None = None, clock: dict | None = None) -> dict:
    """A manifest with the house units; `streams` maps stream name -> info dict."""
    return {
        "schema": SCHEMA,
        "schema_version": SCHEMA_VERSION,
        "sensor_id": sensor_id,
        "units": dict(UNITS),
        "clock": clock or {"source": "monotonic", "t0": 0.0},
        "streams": streams,
        "provenance": provenance or {},
    }
