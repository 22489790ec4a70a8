"""`tensortouch listen`: subscribe to sensors over Zenoh, print one line per message, optionally save.

    tensortouch listen                     # every sensor at the meeting point, tcp/127.0.0.1:7447
    tensortouch listen dome01 --connect tcp/10.0.0.5:7447 --count 100 --save out/ --json

Saving: <DIR>/<sensor>/fields/<seq>.npy (float32 (15,H,W), written atomically) plus meta.json
(channels, units), and contacts.jsonl / wrench.jsonl / status.jsonl (one message per line).
Fields are most of a recording (15 x 128 x 128 float32 = 983 kB a frame, about 30 MB/s at 30 frames/s):
`--fields-every N` keeps every N-th fields frame of each sensor, `--channels` a subset of the channels,
and a recording that grows faster than SIZE_WARN_MB_S says so once, with its rate.
"""
from __future__ import annotations

import json
import logging
import os
import queue
import sys
import time
from pathlib import Path
from typing import Any

from ...contracts.errors import SessionError
from ...contracts.files import atomic_write
from ..apps.zenoh_session import add_zenoh_options, config_from_args, describe

log = logging.getLogger(__name__)

KINDS = ("fields", "contacts", "wrench", "status")


def add_listen_parser(subparsers) -> None:
    p = subparsers.add_parser("listen", help="print/save what sensors publish over Zenoh",
                              description=__doc__.splitlines()[0])
    p.add_argument("sensor", nargs="?", default="*", help="sensor id, or * for all (default)")
    add_zenoh_options(p, "subscriber")
    p.add_argument("--count", type=int, default=0, help="stop after N messages (0 = no limit)")
    p.add_argument("--timeout", type=float, default=0.0,
                   help="stop after this many seconds (0 = no limit)")
    p.add_argument("--kinds", default=",".join(KINDS),
                   help=f"comma-separated streams to show (default {','.join(KINDS)})")
    p.add_argument("--save", type=Path, metavar="DIR|FILE",
                   help="DIR: fields as .npy, the rest as JSONL; FILE.mcap: MCAP with Foxglove schemas; "
                        "FILE.rrd: a Rerun recording (.mcap/.rrd need the viewers extra)")
    p.add_argument("--fields-every", type=int, default=1, metavar="N",
                   help="show and save the fields of every N-th frame of each sensor only (the other streams: all)")
    p.add_argument("--channels", metavar="CH,CH",
                   help="show and save only these field channels, by name (disp_z,fn_z) or modality "
                        "(displacement, contact_normal, ...; docs/fields.md) (default: all 15)")
    p.add_argument("--json", action="store_true", help="one JSON object per line instead of text")
    p.add_argument("--info", action="store_true",
                   help="first list alive sensors and print their info (queryable)")
    p.set_defaults(func=run_listen)


# --------------------------------------------------------------------------- pure summaries

def _fmt(v, nd: int = 3) -> str:
    return "(" + ",".join(f"{x:.{nd}f}" for x in v) + ")"


def summarize(kind: str, msg: Any) -> dict:
    """Decoded message -> small JSON-ready summary (units in the key names)."""
    import numpy as np

    if kind == "status":
        base = {k: msg.get(k) for k in ("sensor_id", "seq", "t", "state", "flags", "fps",
                                        "timings_ms", "model_hash", "calibration_version", "finger")}
        return {"kind": kind, **base}
    base = {"kind": kind, "sensor_id": msg.sensor_id, "seq": msg.seq, "t": msg.t}
    if kind == "fields":
        from ...contracts.fields import MODALITIES

        absmax = {name: float(np.nanmax(np.abs(msg.data[sl]))) if msg.data.size else 0.0
                  for name, sl in MODALITIES.items()} if len(msg.channels) == 15 else {}
        return {**base, "shape": list(msg.data.shape), "dtype": str(msg.data.dtype),
                "units": sorted(set(msg.units)), "absmax": absmax, "clipped": list(msg.clipped)}
    if kind == "contacts":
        return {**base, "n": len(msg.contacts), "contacts": [
            {"id": c.id, "position_mm": list(c.position_mm), "force_n": list(c.force_n),
             "force_mag_n": c.force_mag_n, "area_mm2": c.area_mm2} for c in msg.contacts]}
    return {**base, "force_n": list(msg.force_n), "torque_nmm": list(msg.torque_nmm)}


def format_line(kind: str, msg: Any) -> str:
    """One human-readable line per message."""
    s = summarize(kind, msg)
    head = f"tensortouch/{s['sensor_id']}/{kind:<8} seq={s['seq']} t={s['t']:.3f}"
    if kind == "fields":
        mx = " ".join(f"{k}={v:.3g}" for k, v in s["absmax"].items())
        unit_note = "disp mm, stress/traction MPa"
        clip = f" CLIPPED={','.join(s['clipped'])}" if s["clipped"] else ""
        return f"{head} {'x'.join(map(str, s['shape']))} {s['dtype']} |max| {mx} ({unit_note}){clip}"
    if kind == "contacts":
        parts = [f"#{c['id']} |F|={c['force_mag_n']:.3f} N F={_fmt(c['force_n'])} N "
                 f"at {_fmt(c['position_mm'], 2)} mm area={c['area_mm2']:.2f} mm2"
                 for c in s["contacts"]]
        return f"{head} {s['n']} contact(s)" + (": " + "; ".join(parts) if parts else "")
    if kind == "wrench":
        return f"{head} F={_fmt(s['force_n'])} N tau={_fmt(s['torque_nmm'], 2)} N*mm"
    timings = " ".join(f"{k}={v:.2f}" for k, v in (s["timings_ms"] or {}).items()
                       if isinstance(v, (int, float)))
    fps = f"{s['fps']:.1f}" if isinstance(s["fps"], (int, float)) else "-"
    finger = f" finger={s['finger']}" if s.get("finger") else ""
    return (f"{head}{finger} state={s['state']} fps={fps} flags={','.join(s['flags']) or '-'} "
            f"timings_ms: {timings or '-'}")


# --------------------------------------------------------------------------- thinning

SIZE_WARN_MB_S = 2.0          # a recording growing faster than this says so once (7.2 GB per hour)


def parse_channels(text: str | None) -> tuple[str, ...] | None:
    """`--channels` -> channel names in model order (None: all). Names or modality groups, comma-separated."""
    from ...contracts.errors import CommandError
    from ...contracts.fields import CHANNELS, MODALITIES

    if text is None:
        return None
    chosen: set[str] = set()
    for word in (w.strip() for w in text.split(",")):
        if word in CHANNELS:
            chosen.add(word)
        elif word in MODALITIES:
            chosen.update(CHANNELS[MODALITIES[word]])
        elif word:
            raise CommandError(f"--channels {text!r}: unknown {word!r}; expected channel names "
                               f"({', '.join(CHANNELS)}) or modalities ({', '.join(MODALITIES)})")
    if not chosen:
        raise CommandError(f"--channels {text!r}: expected at least one channel")
    return tuple(c for c in CHANNELS if c in chosen)


class Thinning:
    """Which fields frames are kept (every `every`-th per sensor) and which of their channels."""

    def __init__(self, every: int = 1, channels: tuple[str, ...] | None = None):
        from ...contracts.errors import CommandError

        if every < 1:
            raise CommandError(f"--fields-every {every}: expected 1 or more")
        self.every, self.channels = int(every), channels
        self._seen: dict[str, int] = {}

    def __call__(self, kind: str, msg: Any) -> Any | None:
        """The message to show and save (a fields frame cut to the channels), or None to drop it."""
        if kind != "fields":
            return msg
        n = self._seen.get(msg.sensor_id, 0)
        self._seen[msg.sensor_id] = n + 1
        if n % self.every:
            return None
        if self.channels is None:
            return msg
        import dataclasses

        keep = [i for i, c in enumerate(msg.channels) if c in self.channels]
        return dataclasses.replace(msg, data=msg.data[keep], channels=tuple(msg.channels[i] for i in keep),
                                   units=tuple(msg.units[i] for i in keep),
                                   clipped=tuple(c for c in msg.clipped if c in self.channels))


class RateMeter:
    """Bytes a recording receives per second (field data as float32 plus the small messages as JSON),
    and the one warning when it is more than `warn_mb_s`."""

    def __init__(self, warn_mb_s: float = SIZE_WARN_MB_S, after_s: float = 2.0):
        self.warn_mb_s, self.after_s = warn_mb_s, after_s
        self.bytes = 0
        self.started: float | None = None
        self.warned = False

    def add(self, kind: str, msg: Any, now: float) -> str | None:
        """Count one saved message; returns the warning line once, when the rate is known and too high."""
        if self.started is None:        # the clock starts with the first message: the rate counts the later ones
            self.started = now
            return None
        self.bytes += msg.data.size * 4 if kind == "fields" else 200
        elapsed = now - self.started
        if self.warned or elapsed < self.after_s:
            return None
        rate = self.bytes / elapsed / 1e6
        if rate <= self.warn_mb_s:
            return None
        self.warned = True
        return (f"tensortouch listen: the recording grows about {rate:.1f} MB/s ({rate * 3.6:.1f} GB per hour), "
                f"mostly fields; thin it with --fields-every N (every N-th fields frame) and/or "
                f"--channels disp_z,fn_z (a channel subset)")


# --------------------------------------------------------------------------- saving

class Saver:
    """Writes decoded messages under DIR/<sensor>/ (fields .npy atomically, others as JSONL).

    A failed write (disk full, ...) raises SessionError naming the file, and leaves nothing
    half-written: a partial .npy temp file is removed, a JSONL file is cut back to its last
    complete line. Folder names are sensor ids checked against the id pattern, so nothing lands
    outside DIR; at most `max_open` JSONL files are open at once (least recently used closed first)."""

    def __init__(self, root: Path, max_open: int = 16):
        from collections import OrderedDict

        self.root = Path(root)
        self.max_open = max(1, int(max_open))
        self._files: OrderedDict[tuple[str, str], int] = OrderedDict()  # (sensor, kind) -> append fd
        self._meta_written: set[str] = set()

    def _folder(self, sensor: Any) -> Path:
        from ...contracts.wire import check_sensor_id

        folder = self.root / check_sensor_id(sensor)
        if folder.resolve().parent != self.root.resolve():
            raise SessionError(f"{folder}: sensor folder would be outside {self.root}")
        return folder

    def _fd(self, sensor: str, kind: str, folder: Path, path: Path) -> int:
        fd = self._files.get((sensor, kind))
        if fd is not None:
            self._files.move_to_end((sensor, kind))
            return fd
        while len(self._files) >= self.max_open:
            os.close(self._files.popitem(last=False)[1])
        folder.mkdir(parents=True, exist_ok=True)
        fd = self._files[(sensor, kind)] = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o644)
        return fd

    def save(self, kind: str, msg: Any) -> Path:
        import numpy as np

        sensor = msg["sensor_id"] if isinstance(msg, dict) else msg.sensor_id
        folder = self._folder(sensor)
        if kind == "fields":
            fdir = folder / "fields"
            fdir.mkdir(parents=True, exist_ok=True)
            if sensor not in self._meta_written:
                _atomic_write(fdir / "meta.json", json.dumps(
                    {"channels": list(msg.channels), "units": list(msg.units), "dtype": "float32",
                     "layout": "(C, H, W)"}, indent=1).encode())
                self._meta_written.add(sensor)
            path = fdir / f"{msg.seq:08d}.npy"
            _atomic_write(path, lambda fh: np.save(fh, msg.data))
            return path
        if kind == "contacts":
            record = {"seq": msg.seq, "t": msg.t, "contacts": [c.to_dict() for c in msg.contacts]}
        elif kind == "wrench":
            record = {"seq": msg.seq, "t": msg.t, "force_n": list(msg.force_n),
                      "torque_nmm": list(msg.torque_nmm)}
        else:
            record = msg
        path = folder / f"{kind}.jsonl"
        data = (json.dumps(record, separators=(",", ":")) + "\n").encode("utf-8")
        try:
            fd = self._fd(sensor, kind, folder, path)
            end = os.lseek(fd, 0, os.SEEK_END)
            done = 0
            try:
                while done < len(data):
                    done += os.write(fd, data[done:])
            except OSError:
                os.ftruncate(fd, end)                       # no partial line stays behind
                raise
        except OSError as exc:
            raise SessionError(f"{path}: cannot save a {kind} message ({exc}); the file keeps its complete "
                               "lines (disk full?)") from exc
        return path

    def close(self) -> None:
        for fd in self._files.values():
            os.close(fd)
        self._files.clear()


def _atomic_write(path: Path, data) -> None:
    """contracts.files.atomic_write; a failure is a SessionError naming `path`."""
    try:
        atomic_write(path, data, fsync=False, mkdir=False)
    except OSError as exc:
        raise SessionError(f"{path}: cannot save ({exc}); nothing half-written was kept (disk full?)") from exc


SAVER_GROUP = "tensortouch.savers"       # entry points: file suffix -> factory(path) with save()/close()
FILE_SAVERS = {"mcap": "MCAP (Foxglove schemas)", "rrd": "Rerun recording"}


def open_saver(path: Path):
    """`--save` target: a file whose suffix names a `tensortouch.savers` entry point (`out.mcap`,
    `out.rrd`, from the `viewers` extra) gets that recorder; anything else is a folder (Saver)."""
    from importlib import metadata

    from ...contracts.errors import CommandError
    from ...contracts.extras import hint, missing

    suffix = Path(path).suffix.lower().lstrip(".")
    eps = [ep for ep in metadata.entry_points(group=SAVER_GROUP) if suffix and ep.name == suffix]
    if suffix in FILE_SAVERS and (not eps or missing("viewers")):
        gone = missing("viewers")
        raise CommandError(f"--save {path}: writing a {FILE_SAVERS[suffix]} "
                           + hint("viewers", gone[0] if gone else None))
    if not eps:
        return Saver(path)
    try:
        factory = eps[0].load()
        return factory(path)
    except ImportError as exc:  # a recorder plugin whose own packages are missing
        raise CommandError(f"--save {path}: the .{suffix} recorder is unavailable ({exc})") from None


# --------------------------------------------------------------------------- shell

NOTHING_YET_S = 3.0     # a listen that has received nothing says so after this long


def nothing_yet_hint(sensor: str, where: str, decode_errors: int = 0) -> str:
    """What a listen that receives nothing prints (once, and it keeps waiting)."""
    bad = f" {decode_errors} message(s) arrived that could not be decoded (wire version?)." if decode_errors else ""
    return (f"tensortouch listen: nothing from {sensor!r} yet after {NOTHING_YET_S:.0f} s ({where}); "
            f"still waiting.{bad} Try: start a sensor with `tensortouch run` (it listens on the same "
            "meeting point), check the sensor id (`tensortouch listen '*' --info` lists the alive "
            "ones), or give the sensor's endpoint with --connect.")

def run_listen(args) -> int:
    from ...contracts.errors import CommandError
    from ..apps.subscriber import Subscriber, alive_sensors, query_info, queued_callbacks

    kinds = tuple(k.strip() for k in args.kinds.split(",") if k.strip())
    unknown = [k for k in kinds if k not in KINDS]
    if unknown:
        raise CommandError(f"--kinds {args.kinds!r}: unknown {unknown}; expected some of {KINDS}")
    thin = Thinning(args.fields_every, parse_channels(args.channels))
    meter = RateMeter()
    inbox, callbacks = queued_callbacks(kinds)     # the printer may fall behind: drop, never stall zenoh
    cfg = config_from_args(args, "subscriber")
    where = describe(args, "subscriber")
    saver = open_saver(args.save) if args.save else None
    described: set[str] = set()           # sensors whose info went to a saver that wants it
    out = sys.stdout
    n = 0
    with Subscriber(args.sensor, zenoh_config=cfg, **callbacks) as sub:
        if args.info:
            time.sleep(0.3)  # let the session discover its peers
            sensors = alive_sensors(sub)
            print(json.dumps({"alive": sensors}) if args.json else f"alive: {sensors or 'none'}",
                  file=out, flush=True)
            for sid in sensors:
                if args.sensor not in ("*", sid):
                    continue
                try:
                    info = query_info(sub, sid)
                except Exception as exc:  # noqa: BLE001 - report and go on listening
                    info = {"sensor_id": sid, "error": str(exc)}
                print(json.dumps({"info": info}) if args.json else f"info {sid}: {json.dumps(info)}",
                      file=out, flush=True)
        started = time.monotonic()
        deadline = started + args.timeout if args.timeout > 0 else None
        hinted = False
        try:
            while not (args.count and n >= args.count):
                wait = 0.5 if deadline is None else min(0.5, deadline - time.monotonic())
                if wait <= 0:
                    break
                try:
                    kind, msg = inbox.get(timeout=wait)
                except queue.Empty:
                    if n == 0 and not hinted and time.monotonic() - started >= NOTHING_YET_S:
                        hinted = True
                        print(nothing_yet_hint(args.sensor, where, sub.errors), file=sys.stderr, flush=True)
                    continue
                msg = thin(kind, msg)
                if msg is None:
                    continue
                n += 1
                line = json.dumps(summarize(kind, msg)) if args.json else format_line(kind, msg)
                if saver is not None:
                    sid = msg["sensor_id"] if isinstance(msg, dict) else msg.sensor_id
                    if hasattr(saver, "on_info") and sid not in described:
                        described.add(sid)
                        try:
                            saver.on_info(query_info(sub, sid))
                        except Exception as exc:  # noqa: BLE001 - the recording goes on without it
                            log.warning("sensor %s: no info for the recording: %s", sid, exc)
                    saver.save(kind, msg)
                    warning = meter.add(kind, msg, time.monotonic())
                    if warning:
                        print(warning, file=sys.stderr, flush=True)
                print(line, file=out, flush=True)
        except KeyboardInterrupt:
            pass
        finally:
            if saver is not None:
                saver.close()
        if sub.errors:
            nf = f" ({sub.non_finite} of them held NaN or infinite numbers and were dropped)" if sub.non_finite else ""
            print(f"note: {sub.errors} message(s) could not be decoded{nf}; last: {sub.last_error}",
                  file=sys.stderr)
    if n == 0:
        print(f"tensortouch listen: no messages from {args.sensor!r} ({where}); is a sensor running?",
              file=sys.stderr)
        return 1
    return 0

