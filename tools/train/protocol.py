"""The evaluation protocol's unit sets: train, validation and sealed twin units, their plans drawn from
ONE documented distribution (tools/train/protocol.toml), checked as a whole, and the sealed set's
score log.

- `load_protocol(path)` reads and checks the file: a unit in one set only, unique seeds, each unit's
  seed inside its set's declared range, the ranges pairwise disjoint, the distribution's fields those of
  tools.twin.trajectory.TrajectoryConfig. Any problem is one ProtocolError line (exit 2 in the CLI).
- `Protocol.sessions(set)` → the set's sessions as SessionSpec fields (tools/train/build.py).
- `check_recipe_sessions(protocol, sessions, where)`: a recipe trains on train units only, holds out
  validation units only, never names a sealed unit or a seed in the sealed range.
- `expand_recipe_sessions`: a recipe may take a set's sessions by name, `train = { set = "train", first = 12 }`.
- `log_sealed_score(package, ...)`: a sealed set is scored once per package (its weights' sha256) and
  scorer version (`scorecard.SCORER_VERSION`);
  the log is `<package>/sealed_scores.json`, a second score of the same package on the same sealed set
  (the protocol's hash) is refused. A sealed set recorded anew with seeds no choice has seen (a new
  protocol hash) may score it once more; the log keeps every entry, so each score stays visible.

Pure core: `expand_units`, `check_sets`, `unit_pairs`, `sealed_entry`; shells read and write files.
"""
from __future__ import annotations

import hashlib
import itertools
import json
import time
import tomllib
from dataclasses import dataclass
from pathlib import Path

from ...contracts.errors import TensorTouchError
from ...contracts.names import check_name
from .package import SEALED_LOG

PROTOCOL_FILE = Path(__file__).resolve().parent / "protocol.toml"
SET_NAMES = ("train", "validation", "sealed")
TOP_KEYS = {"world", "frames", "qualities", "distribution", "sets"}


class ProtocolError(TensorTouchError, ValueError):
    """The protocol file, a recipe against it, or a sealed score breaks the protocol (one line)."""


@dataclass(frozen=True)
class Unit:
    serial: str
    seed: int
    pokes: int
    set: str


@dataclass
class Protocol:
    source: str
    doc: dict
    units: dict[str, list[Unit]]            # set name → its units, in order
    seed_ranges: dict[str, tuple[int, int]]

    @property
    def hash(self) -> str:
        return hashlib.sha256(json.dumps(self.doc, sort_keys=True).encode()).hexdigest()[:16]

    def set_of(self, serial: str) -> str | None:
        return next((s for s, us in self.units.items() if any(u.serial == serial for u in us)), None)

    def trajectory(self, index: int) -> dict:
        """The plan ranges of a set's `index`-th unit: the distribution with that unit's indenter pair."""
        dist = dict(self.doc["distribution"])
        dist["indenters"] = list(unit_pairs(dist["indenters"])[index % len(unit_pairs(dist["indenters"]))])
        return dist

    def sessions(self, name: str, first: int | None = None, pokes: int | None = None) -> list[dict]:
        """The set's sessions as SessionSpec fields (tools/train/build.py): every unit, or the first
        `first`; `pokes` keeps only the first that many pokes of each plan (a plan's first n pokes do not
        depend on its length)."""
        if name not in self.units:
            raise ProtocolError(f"{self.source}: no set {name!r} (sets: {', '.join(SET_NAMES)})")
        qs = self.doc.get("qualities", [80])
        return [{"serial": u.serial, "seed": u.seed, "pokes": min(u.pokes, pokes or u.pokes),
                 "frames": self.doc.get("frames", "mjpg"), "quality": int(qs[i % len(qs)]),
                 "trajectory": self.trajectory(i), "world": self.doc.get("world", "label")}
                for i, u in enumerate(self.units[name][:first])]


def unit_pairs(indenters) -> list[tuple[str, str]]:
    """Every pair of two different indenters of the list, in order: the pair rule of the distribution."""
    return list(itertools.combinations(indenters, 2))


def expand_units(spec, set_name: str, where: str) -> list[Unit]:
    """A set's `units`: a list of {serial, seed, pokes} tables, or one pattern table
    {prefix, first, count, seed, pokes} → serials prefix+NN (two digits or more), seeds seed, seed+1, …"""
    def integer(v, what):
        if not isinstance(v, int) or isinstance(v, bool) or v < 0:
            raise ProtocolError(f"{where}.{what}: expected a non-negative integer, got {v!r}")
        return v

    if isinstance(spec, dict):
        need = {"prefix", "first", "count", "seed", "pokes"}
        if set(spec) != need:
            raise ProtocolError(f"{where}: a unit pattern takes exactly {sorted(need)}, got {sorted(spec)}")
        if not isinstance(spec["prefix"], str) or not spec["prefix"]:
            raise ProtocolError(f"{where}.prefix: expected a serial prefix such as \"TWIN-T\"")
        first, count, seed = (integer(spec[k], k) for k in ("first", "count", "seed"))
        pokes = integer(spec["pokes"], "pokes")
        spec = [{"serial": f"{spec['prefix']}{first + i:02d}", "seed": seed + i, "pokes": pokes} for i in range(count)]
    if not isinstance(spec, list) or not spec:
        raise ProtocolError(f"{where}: expected a unit pattern table or a non-empty list of {{serial, seed, pokes}}")
    out = []
    for i, u in enumerate(spec):
        if not isinstance(u, dict) or set(u) != {"serial", "seed", "pokes"} or not isinstance(u["serial"], str):
            raise ProtocolError(f"{where}[{i}]: expected {{serial, seed, pokes}}, got {u!r}"[:300])
        check_name(u["serial"], f"{where}[{i}].serial (it names folders)", ProtocolError)
        if integer(u["pokes"], f"[{i}].pokes") < 1:
            raise ProtocolError(f"{where}[{i}].pokes: expected at least 1")
        out.append(Unit(u["serial"], integer(u["seed"], f"[{i}].seed"), u["pokes"], set_name))
    return out


def check_sets(units: dict[str, list[Unit]], ranges: dict[str, tuple[int, int]], where: str) -> None:
    """The sets as a whole: a unit in one set only, every seed used once and inside its set's range,
    the ranges pairwise disjoint. Raises ProtocolError naming the unit, seed or ranges."""
    for a, b in itertools.combinations(ranges, 2):
        (alo, ahi), (blo, bhi) = ranges[a], ranges[b]
        if alo <= bhi and blo <= ahi:
            raise ProtocolError(f"{where}: the seed ranges of {a!r} [{alo}, {ahi}] and {b!r} [{blo}, {bhi}] overlap")
    owner: dict[str, str] = {}
    seeds: dict[int, str] = {}
    for name, us in units.items():
        lo, hi = ranges[name]
        for u in us:
            if u.serial in owner:
                raise ProtocolError(f"{where}: unit {u.serial} is in set {owner[u.serial]!r} and in set {name!r}; "
                                    "a unit belongs to one set only")
            owner[u.serial] = name
            if u.seed in seeds:
                raise ProtocolError(f"{where}: seed {u.seed} is used by {seeds[u.seed]} and by {u.serial}")
            seeds[u.seed] = u.serial
            if not lo <= u.seed <= hi:
                raise ProtocolError(f"{where}: unit {u.serial} of set {name!r} has seed {u.seed}, outside the "
                                    f"set's seed range [{lo}, {hi}]")


def _check_distribution(dist, where: str) -> None:
    from ..twin.trajectory import INDENTER_SET, TrajectoryConfig, with_ranges

    if not isinstance(dist, dict):
        raise ProtocolError(f"{where}: [distribution] must be a table of TrajectoryConfig fields")
    try:
        with_ranges(TrajectoryConfig(), dist, f"{where} distribution")
    except ValueError as exc:
        raise ProtocolError(str(exc)) from None
    names = dist.get("indenters", TrajectoryConfig().indenters)
    bad = [n for n in names if n not in INDENTER_SET]
    if bad or len(set(names)) < 2:
        raise ProtocolError(f"{where}: distribution.indenters {list(names)}: expected two or more different "
                            f"names of {sorted(INDENTER_SET)}")
    if "indenters" not in dist:
        dist["indenters"] = list(names)


def parse_protocol(doc, where: str) -> Protocol:
    """A protocol document (as TOML reads it) → Protocol, checked (see the module's doc)."""
    if not isinstance(doc, dict) or set(doc) - TOP_KEYS:
        got = sorted(set(doc) - TOP_KEYS) if isinstance(doc, dict) else type(doc).__name__
        raise ProtocolError(f"{where}: expected the keys {sorted(TOP_KEYS)}, got {got}")
    if doc.get("world", "label") not in ("label", "rig"):
        raise ProtocolError(f"{where}: world = {doc['world']!r}; expected \"label\" or \"rig\"")
    if doc.get("frames", "mjpg") not in ("ffv1", "mjpg", "png"):
        raise ProtocolError(f"{where}: frames = {doc['frames']!r}; expected ffv1, mjpg or png")
    qs = doc.get("qualities", [80])
    if not isinstance(qs, list) or not qs or not all(isinstance(q, int) and 1 <= q <= 100 for q in qs):
        raise ProtocolError(f"{where}: qualities must be a list of MJPG qualities 1–100")
    _check_distribution(doc.get("distribution"), where)
    sets = doc.get("sets")
    if not isinstance(sets, dict) or set(sets) != set(SET_NAMES):
        raise ProtocolError(f"{where}: [sets] must hold exactly {list(SET_NAMES)}, got "
                            f"{sorted(sets) if isinstance(sets, dict) else sets!r}")
    units, ranges = {}, {}
    for name in SET_NAMES:
        s = sets[name]
        if not isinstance(s, dict) or set(s) != {"seeds", "units"}:
            raise ProtocolError(f"{where}: sets.{name} must hold exactly seeds = [lo, hi] and units")
        r = s["seeds"]
        if (not isinstance(r, list) or len(r) != 2 or not all(isinstance(x, int) and x >= 0 for x in r)
                or r[0] > r[1]):
            raise ProtocolError(f"{where}: sets.{name}.seeds = {r!r}; expected [lo, hi], 0 ≤ lo ≤ hi")
        ranges[name] = (r[0], r[1])
        units[name] = expand_units(s["units"], name, f"{where}: sets.{name}.units")
    check_sets(units, ranges, where)
    return Protocol(where, doc, units, ranges)


def load_protocol(path: str | Path | None = None) -> Protocol:
    path = Path(path) if path else PROTOCOL_FILE
    try:
        doc = tomllib.loads(path.read_text(encoding="utf-8"))
    except OSError as exc:
        raise ProtocolError(f"{path}: cannot read the protocol ({exc.strerror or exc})") from None
    except (ValueError, UnicodeDecodeError) as exc:
        raise ProtocolError(f"{path}: not a readable protocol ({str(exc)[:200]})") from None
    return parse_protocol(doc, str(path))


def check_recipe_sessions(protocol: Protocol, sessions: dict, where: str) -> None:
    """A recipe's [sessions] against the protocol: train sessions only on train units (or units the
    protocol does not name), held-out sessions only on validation units (or unnamed ones), no sealed unit
    anywhere, no seed in the sealed range."""
    lo, hi = protocol.seed_ranges["sealed"]
    role = {"train": "train", "heldout": "validation"}
    for key, specs in sessions.items():
        for i, s in enumerate(specs or []):
            serial = s["serial"] if isinstance(s, dict) else s.serial
            seed = s["seed"] if isinstance(s, dict) else s.seed
            at = f"{where}: sessions.{key}[{i}] ({serial}, seed {seed})"
            if lo <= seed <= hi:
                raise ProtocolError(f"{at}: the seed is in the sealed set's range [{lo}, {hi}]; no choice may see it")
            owner = protocol.set_of(serial)
            if owner is None:
                continue
            if owner != role.get(key):
                raise ProtocolError(f"{at}: {serial} is a {owner} unit (tools/train/protocol.toml); "
                                    f"sessions.{key} takes {role.get(key, key)} units")


RECIPE_SET_KEYS = {"set", "first", "pokes", "protocol"}


def expand_recipe_sessions(protocol: Protocol, sessions: dict, where: str) -> dict:
    """A recipe's [sessions] with each table form `{set = "train", first = 12, pokes = 8, protocol = HASH}`
    replaced by that set's sessions (`Protocol.sessions`): `train` takes the train set, `heldout` the
    validation set, never the sealed one; `protocol`, when given, must be the protocol file's hash (the
    sessions it names are then the ones the recipe was written against). Lists pass unchanged."""
    role = {"train": "train", "heldout": "validation"}
    out = {}
    for key, v in (sessions or {}).items():
        if not isinstance(v, dict):
            out[key] = v
            continue
        at = f"{where}: sessions.{key}"
        if not set(v) <= RECIPE_SET_KEYS or "set" not in v:
            raise ProtocolError(f"{at}: a table of sessions takes set (and optionally first, pokes, protocol), "
                                f"got {sorted(v)}")
        if v["set"] != role.get(key):
            raise ProtocolError(f"{at}: set = {v['set']!r}; sessions.{key} takes the {role.get(key, key)} set")
        for k in ("first", "pokes"):
            if k in v and (not isinstance(v[k], int) or isinstance(v[k], bool) or v[k] < 1):
                raise ProtocolError(f"{at}.{k}: expected a positive integer, got {v[k]!r}")
        if "protocol" in v and v["protocol"] != protocol.hash:
            raise ProtocolError(f"{at}.protocol = {v['protocol']!r}, but {protocol.source} is now {protocol.hash}: "
                                "the unit sets changed since the recipe was written")
        out[key] = protocol.sessions(v["set"], v.get("first"), v.get("pokes"))
    return out


# ----- the sealed set's score log -------------------------------------------------------------------
def package_id(manifest: dict) -> str:
    """A package's identity for the log: sha256 (16 hex) of its files' sha256 values, sorted by name."""
    files = manifest.get("files") or {}
    text = "\n".join(f"{k}:{files[k].get('sha256', '')}" for k in sorted(files))
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def sealed_entry(log: list[dict], pid: str, protocol_hash: str, units: list[str], headline: dict,
                 scorer: int | None = None) -> dict:
    """The new log entry of a sealed score; ProtocolError if this package was already scored on this
    sealed set (the same protocol hash) by this scorer version (tools.train.scorecard.SCORER_VERSION;
    entries without one are version 1; the log names when). A scorer fix re-measures what was scored, so
    the set may score the package once more under the new version; the earlier entry stays."""
    from .scorecard import SCORER_VERSION

    scorer = SCORER_VERSION if scorer is None else int(scorer)
    for e in log:
        if e.get("package_id") == pid and e.get("protocol") == protocol_hash and int(e.get("scorer", 1)) == scorer:
            raise ProtocolError(f"package {pid} was already scored on the sealed set at {e.get('when')} "
                                f"(protocol {e.get('protocol')}, scorer {scorer}); a sealed set is scored once per "
                                f"package")
    return {"package_id": pid, "protocol": protocol_hash, "scorer": scorer, "units": list(units),
            "when": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()), "headline": headline}


def read_sealed_log(package_dir: str | Path) -> list[dict]:
    p = Path(package_dir) / SEALED_LOG
    if not p.is_file():
        return []
    try:
        doc = json.loads(p.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise ProtocolError(f"{p}: unreadable sealed score log ({str(exc)[:120]})") from None
    if not isinstance(doc, list):
        raise ProtocolError(f"{p}: expected a list of sealed scores")
    return doc


def check_not_scored(package_dir: str | Path, protocol_hash: str, scorer: int | None = None) -> str:
    """Before a sealed score: the package's id, or ProtocolError when its log already holds one on this
    sealed set (protocol hash) by this scorer version."""
    man = json.loads((Path(package_dir) / "manifest.json").read_text(encoding="utf-8"))
    pid = package_id(man)
    sealed_entry(read_sealed_log(package_dir), pid, protocol_hash, [], {}, scorer)
    return pid


def log_sealed_score(package_dir: str | Path, protocol_hash: str, units: list[str], headline: dict,
                     scorer: int | None = None) -> dict:
    """Append the sealed score to `<package>/sealed_scores.json` (atomic, under a lock file)."""
    import fcntl

    from ...contracts.files import atomic_write_json

    folder = Path(package_dir)
    with open(folder / f".{SEALED_LOG}.lock", "w") as lk:
        fcntl.flock(lk, fcntl.LOCK_EX)
        log = read_sealed_log(folder)
        man = json.loads((folder / "manifest.json").read_text(encoding="utf-8"))
        entry = sealed_entry(log, package_id(man), protocol_hash, units, headline, scorer)
        atomic_write_json(folder / SEALED_LOG, log + [entry])
    return entry
