"""Seeded malformed *values* for every numeric field of the five formats people write by hand: calibration,
model manifest, recipe, hand config and session. Each case puts one generated value (huge, tiny,
negative, zero, NaN, ±inf, a wrong type, missing, nested, a boundary, or a plausible value) into one
field of a valid document; whether it must be accepted is decided from the format's declared schema
(the ranges the loaders declare, with the fixture's other values for fields that depend on each other),
never by expecting a refusal blindly. A refusal is one line naming the field (or file) and exit 2; no
case may take 10 s. Calibration and session go through the CLI's own dispatch (`calib show`,
`session check`) in-process; manifest, recipe and hand config through the loaders the CLI calls (the
CLI turns their TensorTouchError into that line and exit 2: test_cli_subprocess_shape below shows it
for each format in real subprocesses).
"""
from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
import pytest
from tensortouch.contracts.errors import TensorTouchError
from tensortouch.contracts.schema import Range

from tests.conftest import dome_calibration
from tests.hand_util import make_package

CASES = 520                 # per format
MAX_S = 10.0                # no case may take longer before it is refused (or accepted)
MISSING = object()


@dataclass
class Slot:
    """One numeric (or choice) field: where it is, its type and its plausible values."""

    path: tuple
    kind: str = "float"                     # float | int | choice
    rng: Range = field(default_factory=Range)
    extra: Callable[[float], bool] = lambda v: True   # ties to the fixture's other fields
    required: bool = False
    nullable: bool = False
    choices: tuple = ()

    def expect(self, v) -> bool:
        if v is MISSING:
            return not self.required
        if v is None:
            return self.nullable
        if self.kind == "choice":
            return isinstance(v, str) and v in self.choices
        if isinstance(v, bool) or not isinstance(v, (int, float)) or (self.kind == "int" and not isinstance(v, int)):
            return False
        try:
            f = float(v)
        except OverflowError:
            return False
        if self.kind == "int" and abs(v) >= 2 ** 63:
            return False
        exact = v if isinstance(v, int) else f          # integers compared exactly (2**63 - 1 is not a float)
        return math.isfinite(f) and self.rng.holds(exact) and self.extra(exact)

    def name(self) -> str:
        return ".".join(str(p) for p in self.path)


def generate(rng: np.random.Generator, slot: Slot):
    """One value for `slot` from a random family."""
    lo = slot.rng.lo if slot.rng.lo is not None else -1e6
    hi = slot.rng.hi if slot.rng.hi is not None else 1e6
    families = [
        lambda: [1e9, 1e308, 10 ** 30, 2 ** 63, 2 ** 64 + 1, 1e19][int(rng.integers(6))],          # huge
        lambda: [1e-300, 5e-324, 1e-9, -1e-300][int(rng.integers(4))],                               # tiny
        lambda: [-1, -1e308, -0.5, -(10 ** 30), -(2 ** 63) - 1][int(rng.integers(5))],                # negative
        lambda: [0, 0.0, -0.0][int(rng.integers(3))],                                                 # zero
        lambda: [math.nan, math.inf, -math.inf][int(rng.integers(3))],                               # non-finite
        lambda: ["x", "", True, False, None, "1.5", "many"][int(rng.integers(7))],                   # wrong type
        lambda: MISSING,                                                                              # missing
        lambda: [[1], {"v": 1}, [[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[1]]]]]]]]]]]]]]]]]]]]]]]]]]]]]]]]]]]]]]]],
                 [1.0, 2.0]][int(rng.integers(4))],                                                  # nested
        lambda: _inside(rng, slot, lo, hi),                                                           # plausible
        lambda: _inside(rng, slot, lo, hi),
        lambda: _boundary(rng, slot, lo, hi),                                                         # edges
    ]
    if slot.kind == "choice":
        families.append(lambda: slot.choices[int(rng.integers(len(slot.choices)))])
    return families[int(rng.integers(len(families)))]()


def _inside(rng, slot, lo, hi):
    lo, hi = max(lo, -1e6), min(hi, 1e6)
    if slot.kind == "choice":
        return slot.choices[int(rng.integers(len(slot.choices)))]
    if slot.kind == "int":
        v = int(rng.integers(int(math.ceil(lo)), int(math.floor(hi)) + 1))
        return float(v) if rng.random() < 0.15 else v          # 64.0 in an integer field: still refused
    return float(rng.uniform(lo, hi))


def _boundary(rng, slot, lo, hi):
    if slot.kind == "choice":
        return slot.choices[0].upper() + "x"
    vals = [lo, hi, lo - 1, hi + 1] if slot.kind == "int" else \
        [lo, hi, float(np.nextafter(lo, -np.inf)), float(np.nextafter(hi, np.inf))]
    v = vals[int(rng.integers(len(vals)))]
    return int(v) if slot.kind == "int" and math.isfinite(v) else v


def put(doc, path, v):
    node = doc
    for k in path[:-1]:
        node = node[k]
    if v is MISSING:
        if isinstance(node, list):
            node.pop(path[-1])
        else:
            node.pop(path[-1], None)
    else:
        node[path[-1]] = v


def toml_doc(doc: dict) -> str:
    """A TOML document of top-level keys (tables inline); None means 'not written'."""
    def val(v):
        if isinstance(v, bool):
            return "true" if v else "false"
        if isinstance(v, int):
            return str(v)
        if isinstance(v, float):
            return "nan" if math.isnan(v) else ("inf" if v > 0 else "-inf") if math.isinf(v) else repr(v)
        if isinstance(v, str):
            return json.dumps(v)
        if isinstance(v, (list, tuple)):
            return "[" + ", ".join(val(x) for x in v if x is not None) + "]"
        if isinstance(v, dict):
            return "{" + ", ".join(f"{json.dumps(str(k))} = {val(x)}" for k, x in v.items() if x is not None) + "}"
        raise TypeError(type(v))

    return "".join(f"{json.dumps(k)} = {val(v)}\n" for k, v in doc.items() if v is not None)


def run_corpus(slots, seed, attempt, toml=False):
    """CASES cases over `slots`: attempt(slot, value) -> (exit code, message lines); checks the outcome."""
    rng = np.random.default_rng(seed)
    accepted = refused = 0
    for i in range(CASES):
        slot = slots[int(rng.integers(len(slots)))]
        v = generate(rng, slot)
        want = slot.expect(MISSING if (toml and v is None) else v)
        t0 = time.monotonic()
        rc, lines = attempt(slot, v)
        took = time.monotonic() - t0
        where = f"case {i}: {slot.name()} = {v!r:.80}"
        assert took < MAX_S, f"{where}: took {took:.1f} s"
        if want:
            assert rc == 0, f"{where}: plausible value refused: {lines}"
            accepted += 1
        else:
            assert rc == 2, f"{where}: implausible value accepted"
            assert len(lines) == 1 and "Traceback" not in lines[0], f"{where}: {lines}"
            named = [str(p) for p in slot.path if isinstance(p, str)]
            assert any(n in lines[0] for n in named), f"{where}: message does not name the field: {lines[0]}"
            refused += 1
    assert accepted >= CASES // 10 and refused >= CASES // 3, (accepted, refused)
    return accepted, refused


def loader_outcome(fn, *args):
    """What the CLI makes of a loader call: (0, []) or (2, [one line]); any other exception fails."""
    try:
        fn(*args)
        return 0, []
    except TensorTouchError as exc:
        return 2, str(exc).splitlines() or [""]


@pytest.fixture(scope="module")
def cli():
    """`tensortouch ARGV` in-process through the CLI's own dispatch (parser built once): (exit code, stderr lines)."""
    from tensortouch.runtime.shells.cli import build_parser, dispatch

    parser, _ = build_parser()

    def run(argv, capture):
        capture.readouterr()
        rc = dispatch(parser.parse_args([str(a) for a in argv]))
        err = capture.readouterr().err
        return rc, [line for line in err.splitlines() if line and not line.startswith("INFO ")]
    return run


# ------------------------------------------------------------------------------------------ calibration
def calibration_slots():
    from tensortouch.contracts.calibration_schema import CAMERA_PX, GEL_MM, MIN_RADIUS_PX

    # the fixture: 160x120 camera, centre (80, 60), radius 50 px, 8x8 tables
    return [Slot(("camera", "width"), "int", Range(max(CAMERA_PX.lo, 80), CAMERA_PX.hi), required=True),
            Slot(("camera", "height"), "int", Range(max(CAMERA_PX.lo, 60), CAMERA_PX.hi), required=True),
            Slot(("gel_center_px", 0), rng=Range(0, 160), required=True),
            Slot(("gel_center_px", 1), rng=Range(0, 120), required=True),
            Slot(("gel_radius_px",), rng=Range(MIN_RADIUS_PX, 160), required=True),
            Slot(("model_size", 0), "int", Range(8, 8), required=True),
            Slot(("model_size", 1), "int", Range(8, 8), required=True),
            Slot(("schema_version",), "int", Range(0, 1)),
            Slot(("gel", "shape"), "choice", choices=("dome", "flattened_dome"))] + \
        [Slot(("gel", k), rng=r) for k, r in GEL_MM.items()]


def test_calibration_values(tmp_path, cli, capsys):
    root = tmp_path / "store"
    dome_calibration(root, "TT-VAL", size=8, image=(160, 120), radius_px=50.0)
    path = root / "TT-VAL" / "versions" / "v0001" / "calibration.json"
    good = json.loads(path.read_text())
    good["gel"] = {"shape": "flattened_dome", "base_radius_mm": 12.0, "cap_height_mm": 6.0, "skirt_mm": 2.0,
                   "radius_mm": 15.0, "center_z_mm": -7.0, "height_mm": 8.0}

    def attempt(slot, v):
        doc = json.loads(json.dumps(good))
        put(doc, slot.path, v)
        path.write_text(json.dumps(doc))
        return cli(["calib", "show", "TT-VAL", "--store", root], capsys)

    run_corpus(calibration_slots(), 4601, attempt)


# ------------------------------------------------------------------------------------------ model manifest
def manifest_slots(good):
    from tensortouch.contracts.fields import CHANNELS
    from tensortouch.contracts.manifest_schema import BOUND_LIMIT
    from tensortouch.runtime.stages.model import CONTACT_LIMIT, POSITIVE

    bounds = good["output"]["bounds"]
    slots = [Slot(("input", "size", 0), "int", Range(32, 32), required=True),
             Slot(("input", "size", 1), "int", Range(32, 32), required=True),
             Slot(("input", "range", 0), rng=Range(-1e6, 1e6), extra=lambda v: v < 1.0, required=True),
             Slot(("input", "range", 1), rng=Range(-1e6, 1e6), extra=lambda v: v > 0.0, required=True),
             Slot(("input", "dtype"), "choice", choices=("float32",)),
             Slot(("input", "layout"), "choice", choices=("NCHW",)),
             Slot(("schema_version",), "int", Range(1, 1), required=True)]
    for c in CHANNELS:
        lo, hi = bounds[c]
        slots.append(Slot(("output", "bounds", c, 0), rng=Range(-BOUND_LIMIT, BOUND_LIMIT),
                          extra=lambda v, hi=hi: v <= hi, required=True))
        slots.append(Slot(("output", "bounds", c, 1), rng=Range(-BOUND_LIMIT, BOUND_LIMIT),
                          extra=lambda v, lo=lo: v >= lo, required=True))
    for k in ("threshold_n", "weak_threshold_n", "min_total_n", "merge_n", "support_radius_px", "support_floor_n",
              "match_gate_mm", "min_pixels", "stable_frames", "max_contacts"):
        kind = "int" if k in ("min_pixels", "stable_frames", "max_contacts") else "float"
        slots.append(Slot(("runtime", "contacts", k), kind, Range(0, CONTACT_LIMIT, lo_open=k in POSITIVE),
                          nullable=True))
    return slots


def test_manifest_values(tmp_path):
    from tensortouch.runtime.stages.model import load_package

    pkg = make_package(tmp_path / "pkg")
    good = json.loads((pkg / "manifest.json").read_text())
    good["runtime"] = {"contacts": {"threshold_n": 0.002, "weak_threshold_n": 0.001, "min_total_n": 0.1, "merge_n": 0.001,
                                    "support_radius_px": 10.0, "support_floor_n": 0.0001, "match_gate_mm": 4.0,
                                    "min_pixels": 3, "stable_frames": 5, "max_contacts": 16}}

    def attempt(slot, v):
        doc = json.loads(json.dumps(good))
        put(doc, slot.path, v)
        (pkg / "manifest.json").write_text(json.dumps(doc))
        return loader_outcome(load_package, pkg)

    run_corpus(manifest_slots(good), 4602, attempt)


# ------------------------------------------------------------------------------------------ recipe
def recipe_slots():
    import typing

    from tensortouch.tools.train.build import BUILD_LIMITS, CHOICES, SESSION_LIMITS, BuildConfig, SessionSpec

    hints = typing.get_type_hints(BuildConfig)
    slots = [Slot(("build", k), "int" if hints[k] is int else "float", r) for k, r in BUILD_LIMITS.items()]
    slots += [Slot(("build", k), "choice", choices=c) for k, c in CHOICES.items()]
    spec = typing.get_type_hints(SessionSpec)
    for k, r in SESSION_LIMITS.items():
        if isinstance(r, Range):
            slots.append(Slot(("sessions", "train", 0, k), "int" if spec[k] is int else "float", r,
                              required=k in ("seed", "pokes")))
        else:
            slots.append(Slot(("sessions", "train", 0, k), "choice", choices=r))
    return slots


def test_recipe_values(tmp_path):
    from tensortouch.tools.train.build import BUILD_LIMITS, BuildConfig
    from tensortouch.tools.train.recipe import load_recipe
    from tensortouch.tools.train.runner import step_configs

    defaults = BuildConfig()
    good = {"name": "values", "about": "seeded values",
            "sessions": {"train": [{"serial": "TWIN-T01", "seed": 101, "pokes": 5, "frames": "mjpg", "quality": 65}],
                         "heldout": [{"serial": "TWIN-H01", "seed": 201, "pokes": 5}]},
            "build": {k: getattr(defaults, k) for k in BUILD_LIMITS} | {"physics": "hertz-fallback"}}
    path = tmp_path / "values.toml"

    def attempt(slot, v):
        doc = json.loads(json.dumps(good))
        put(doc, slot.path, v)
        path.write_text(toml_doc(doc))
        return loader_outcome(lambda: step_configs(load_recipe(path)))

    run_corpus(recipe_slots(), 4603, attempt, toml=True)


def test_every_numeric_field_has_a_declared_range():
    from tensortouch.contracts.schema import undeclared_ranges
    from tensortouch.drivers.can_bus import CanConfig
    from tensortouch.runtime.apps.hand_config import LIMITS, FingerConfig, HandConfig
    from tensortouch.runtime.apps.ros2_publisher import Ros2Config
    from tensortouch.tools.train.build import BUILD_LIMITS, SESSION_LIMITS, BuildConfig, SessionSpec

    assert undeclared_ranges(BuildConfig, BUILD_LIMITS) == []
    assert undeclared_ranges(SessionSpec, SESSION_LIMITS) == []
    for cls in (FingerConfig, HandConfig, CanConfig, Ros2Config):
        assert undeclared_ranges(cls, LIMITS[cls]) == [], cls.__name__


# ------------------------------------------------------------------------------------------ hand config
def hand_slots():
    import typing

    from tensortouch.drivers.can_bus import CanConfig
    from tensortouch.runtime.apps.hand_config import CAMERA_LIMITS, LIMITS, FingerConfig, HandConfig
    from tensortouch.runtime.apps.ros2_publisher import Ros2Config

    slots = []
    for table, cls in (("hand", HandConfig), ("can", CanConfig), ("ros2", Ros2Config)):
        hints = typing.get_type_hints(cls)
        for k, r in LIMITS[cls].items():
            if isinstance(r, tuple):
                slots.append(Slot((table, k), "choice", choices=r))
                continue
            tp = hints[k]
            if k == "mount_xyz_m":
                slots += [Slot((table, k, i), rng=r, required=True) for i in range(3)]
            elif k == "mount_xyzw":        # a unit quaternion (Ros2Config: |norm - 1| <= 1e-3) around (0, 0, 0, 1)
                slots += [Slot((table, k, i), rng=r, extra=lambda v: math.hypot(1.0, v) <= 1.001, required=True)
                          for i in range(3)]
                slots.append(Slot((table, k, 3), rng=r, extra=lambda v: abs(abs(v) - 1.0) <= 1e-3, required=True))
            else:
                extra = (lambda v: v + 1 <= 0x7FF) if k == "id_base" else (lambda v: True)   # 11-bit ids, 1 finger
                slots.append(Slot((table, k), "int" if int in (typing.get_args(tp) or (tp,)) else "float", r,
                                  extra=extra, nullable=type(None) in typing.get_args(tp)))
    slots.append(Slot(("finger", 0, "can_slot"), "int", LIMITS[FingerConfig]["can_slot"]))
    slots += [Slot(("camera", k), rng=CAMERA_LIMITS[k]) for k in ("speed", "fps")]
    return slots


def test_hand_config_values(tmp_path):
    from tensortouch.runtime.apps.hand_config import load_hand_config

    good = {"hand": {"name": "h", "threads": 1, "inference_workers": 2, "max_camera_failures": 20, "reconnect_s": 0.5,
                     "offline_after_s": 5.0, "status_every_s": 0.5, "model_poll_s": 1.0, "precision": "int8"},
            "zenoh": {"listen": ["tcp/127.0.0.1:7447"]},
            "can": {"interface": "virtual", "channel": "c0", "bitrate": 500000, "id_base": 0x300, "rate_hz": 100.0,
                    "send_timeout_s": 0.0, "reopen_after_errors": 20, "reopen_wait_s": 0.5, "stale_after_s": 0.25},
            "ros2": {"domain_id": 0, "depth": 10, "surface_every": 10, "surface_step": 2,
                     "mount_xyz_m": [0.0, 0.0, 0.0], "mount_xyzw": [0.0, 0.0, 0.0, 1.0]},
            "camera": {"speed": 1.0, "fps": 30.0},
            "finger": [{"name": "f0", "serial": "TT-1", "source": "usb:TT-1", "can_slot": 0}]}
    path = tmp_path / "hand.toml"

    def attempt(slot, v):
        doc = json.loads(json.dumps(good))
        put(doc, slot.path, v)
        path.write_text(toml_doc(doc))
        return loader_outcome(load_hand_config, path)

    run_corpus(hand_slots(), 4604, attempt, toml=True)


# ------------------------------------------------------------------------------------------ session
def session_slots():
    from tensortouch.contracts.session_schema import QUAT_NORM, RANGES, TIME_S

    def unit_w(v):
        return QUAT_NORM.holds(abs(v))

    def unit_xyz(v):
        return QUAT_NORM.holds(math.hypot(1.0, v))

    tf = ("json", "streams", "wrench", "ft_to_indenter")
    slots = [Slot(("json", "clock", "t0"), rng=TIME_S),
             Slot(tf + ("rotation_wxyz", 0), rng=RANGES["quat"], extra=unit_w, required=True),
             Slot(("json", "streams", "frames", "rows"), "int", Range(4, 4), nullable=True)]
    slots += [Slot(tf + ("rotation_wxyz", i), rng=RANGES["quat"], extra=unit_xyz, required=True) for i in (1, 2, 3)]
    slots += [Slot(tf + ("translation_mm", i), rng=RANGES["length"], required=True) for i in range(3)]
    # stream cells (CSV has no types: a cell is plausible when it reads as a number in range)
    slots += [Slot(("poses.csv", 1, c), "csv", RANGES["length"], required=True) for c in ("x", "y", "z")]
    slots += [Slot(("poses.csv", 1, "qw"), "csv", RANGES["quat"], extra=unit_w, required=True)]
    slots += [Slot(("poses.csv", 1, c), "csv", RANGES["quat"], extra=unit_xyz, required=True) for c in ("qx", "qy", "qz")]
    slots += [Slot(("wrench.csv", 0, c), "csv", RANGES["force"], required=True) for c in ("fx", "fy", "fz")]
    slots += [Slot(("wrench.csv", 0, c), "csv", RANGES["torque"], required=True) for c in ("tx", "ty", "tz")]
    return slots


def _csv_expect(slot, v):
    if v is MISSING:
        return False
    try:
        f = float(_cell(v))
    except (ValueError, OverflowError):
        return False
    return math.isfinite(f) and slot.rng.holds(f) and slot.extra(f)


def _cell(v) -> str:
    return "" if v is MISSING else str(v)


def test_session_values(tmp_path, cli, capsys):
    from tensortouch.contracts.session import STREAM_COLUMNS

    from tests.test_bad_inputs import tiny_session

    poses = np.array([[0.0, 0, 1, 2, 3, 1, 0, 0, 0], [0.1, 0, 1, 2, 3, 1, 0, 0, 0]])
    wrench = np.array([[0.0, 0, 1, 2, 3, 0, 0, 0], [0.1, 0, 1, 2, 3, 0, 0, 0]])
    s = tiny_session(tmp_path / "s", wrench=wrench, poses=poses)
    good_json = json.loads((s / "session.json").read_text())
    good_csv = {f: (s / f).read_text() for f in ("poses.csv", "wrench.csv")}

    def attempt(slot, v):
        (s / "session.json").write_text(json.dumps(good_json))
        for f, text in good_csv.items():
            (s / f).write_text(text)
        if slot.path[0] == "json":
            doc = json.loads(json.dumps(good_json))
            put(doc, slot.path[1:], v)
            (s / "session.json").write_text(json.dumps(doc))
        else:
            f, row, col = slot.path
            lines = good_csv[f].splitlines()
            cells = lines[row + 1].split(",")
            cells[STREAM_COLUMNS[f[:-4]].index(col)] = _cell(v)
            lines[row + 1] = ",".join(cells)
            (s / f).write_text("\n".join(lines) + "\n")
        return cli(["session", "check", s], capsys)

    run_corpus(session_slots_with_csv_oracle(), 4605, attempt)


def session_slots_with_csv_oracle():
    slots = session_slots()
    for slot in slots:
        if slot.kind == "csv":
            slot.expect = (lambda sl: (lambda v: _csv_expect(sl, v)))(slot)
    return slots


# ------------------------------------------------------------------------------------------ the cases
@pytest.mark.parametrize("item,want", [
    ("size=1e9", "size is 1000000000.0"), ("size=64.5", "size is 64.5"), ("epochs=nan", "epochs is nan"),
    ("batch=0", "batch is 0"), ("batch=1e308", "batch is 1e+308"), ('epochs="many"', "epochs is 'many'"),
    ("lr=inf", "lr is inf"), ("contact_stride=0", "contact_stride is 0"),
    ("quantization_samples=-1", "quantization_samples is -1"), ("fit_seed=18446744073709551616", "fit_seed is"),
    ("size=" + "[" * 3000 + "]" * 3000, "nested too deeply"), ("size=" + "[" * 40 + "1" + "]" * 40, "nested more than"),
])
def test_named_recipe_sets(item, want):
    from tensortouch.tools.train.recipe import load_recipe
    from tensortouch.tools.train.runner import step_configs

    rc, lines = loader_outcome(lambda: step_configs(load_recipe("tiny", [item])))
    assert rc == 2 and len(lines) == 1 and want in lines[0], lines


def test_named_recipe_files(tmp_path):
    from tensortouch.tools.train.recipe import load_recipe
    from tensortouch.tools.train.runner import step_configs

    base = 'name = "n"\n[sessions]\ntrain = [{serial = "TWIN-T01", seed = %s, pokes = 5}]\n[build]\nepochs = 2\n'
    for text, want in ((base % "18446744073709551616", "seed is 18446744073709551616"),
                       (base % "-1", "seed is -1"), (base % "1.5", "seed is 1.5"),
                       ("x = " + "[" * 5000 + "]" * 5000 + "\n", "nested too deeply"),
                       (('name = "n"\n[[steps]]\nname = "a"\nbuild = {epochs = 2}\n[[steps]]\nname = "b"\n'
                        'after = "a"\nbuild = {lr = inf}\n'), "(step b): lr is inf")):
        path = tmp_path / "r.toml"
        path.write_text(text)
        rc, lines = loader_outcome(lambda path=path: step_configs(load_recipe(path)))
        assert rc == 2 and len(lines) == 1 and want in lines[0], (text[:60], lines)


def test_named_manifest_cases(tmp_path):
    from tensortouch.runtime.stages.model import load_package

    pkg = make_package(tmp_path / "pkg")
    good = json.loads((pkg / "manifest.json").read_text())
    cases = [(("output", "bounds", "disp_x", 1), 10 ** 400, "output.bounds.disp_x[1]"),
             (("output", "bounds", "fn_z", 0), -(10 ** 30), "output.bounds.fn_z[0]"),
             (("input", "dtype"), "float64", "input.dtype"), (("input", "dtype"), 32, "input.dtype"),
             (("input", "channels"), [1, 2, 3, 4, 5, 6], "input.channels"),
             (("input", "channels"), "baseline_rgb,current_rgb", "input.channels"),
             (("input", "size", 0), 32.0, "input.size[0]"), (("input", "size", 1), 10 ** 12, "input.size[1]"),
             (("runtime",), {"contacts": {"stable_frames": 0}}, "stable_frames"),
             (("runtime",), {"contacts": {"min_pixels": 1e300}}, "min_pixels")]
    for path, v, want in cases:
        doc = json.loads(json.dumps(good))
        put(doc, path, v)
        (pkg / "manifest.json").write_text(json.dumps(doc))
        rc, lines = loader_outcome(load_package, pkg)
        assert rc == 2 and len(lines) == 1 and want in lines[0], (path, v, lines)


def test_named_calibration_cases(tmp_path, cli, capsys):
    root = tmp_path / "store"
    dome_calibration(root, "TT-N", size=8, image=(160, 120), radius_px=50.0)
    path = root / "TT-N" / "versions" / "v0001" / "calibration.json"
    good = json.loads(path.read_text())
    cases = [({"gel_radius_px": 1e9}, "gel_radius_px is 1000000000.0"), ({"gel_radius_px": 1e308}, "gel_radius_px"),
             ({"gel_radius_px": 2.0}, "gel_radius_px is 2.0"), ({"gel_center_px": [1e308, 60.0]}, "gel_center_px"),
             ({"gel_center_px": [-5.0, 60.0]}, "gel_center_px"),
             ({"gel": {"radius_mm": math.nan}}, "gel.radius_mm is nan"), ({"gel": {"radius_mm": math.inf}}, "gel.radius_mm"),
             ({"gel": {"center_z_mm": -math.inf}}, "gel.center_z_mm"), ({"gel": {"radius_mm": 0.0}}, "gel.radius_mm"),
             ({"gel": {"shape": "cube"}}, "gel.shape"), ({"camera": {"width": 40, "height": 120}}, "gel_center_px"),
             ({"camera": {"width": "160", "height": 120}}, "camera.width"),
             ({"provenance": {"pokes": math.nan}}, "provenance.pokes is nan")]
    for change, want in cases:
        path.write_text(json.dumps({**good, **change}))
        rc, lines = cli(["calib", "show", "TT-N", "--store", root], capsys)
        assert rc == 2 and len(lines) == 1 and want in lines[0], (change, lines)
    path.write_text(json.dumps({**good, "camera": None}))          # no camera block: radius bounded by CAMERA_PX
    assert cli(["calib", "show", "TT-N", "--store", root], capsys)[0] == 0


def test_named_hand_config_cases(tmp_path):
    from tensortouch.runtime.apps.hand_config import load_hand_config

    finger = '[[finger]]\nname = "f0"\nserial = "TT-1"\n'
    for text, want in (('[hand]\nthreads = "x"\n', "threads is 'x'"), ("[hand]\nthreads = 1e9\n", "threads is"),
                       ("[hand]\nreconnect_s = nan\n", "reconnect_s is nan"), ("[camera]\nspeed = 0\n", "speed is 0"),
                       ("[can]\nrate_hz = inf\n", "rate_hz is inf"), ('hand = 3\n', "[hand]"),
                       ("[hand]\nmodel_poll_s = -1\n", "model_poll_s is -1")):
        path = tmp_path / "h.toml"
        path.write_text(text + finger)
        rc, lines = loader_outcome(load_hand_config, path)
        assert rc == 2 and len(lines) == 1 and want in lines[0], (text, lines)


def test_named_session_cases(tmp_path, cli, capsys):
    from tests.test_bad_inputs import tiny_session

    poses = np.array([[0.0, 0, 1, 2, 3, 1, 0, 0, 0], [0.1, 0, 1, 2, -1e308, 1, 0, 0, 0]])
    s = tiny_session(tmp_path / "p", poses=poses)
    rc, lines = cli(["session", "check", s], capsys)
    assert rc == 2 and len(lines) == 1 and "poses.csv:3: z = -1e+308" in lines[0], lines
    wrench = np.array([[0.0, 0, 1, 2, 3, 0, 0, 0], [0.1, 0, 1, 2, 3, 0, 0, 0]])
    s = tiny_session(tmp_path / "w", wrench=wrench)
    good = json.loads((s / "session.json").read_text())
    tf = ("streams", "wrench", "ft_to_indenter")
    for path, v, want in ((tf + ("rotation_wxyz",), ["1", "0", "0", "0"], "rotation_wxyz[0] is '1'"),
                          (tf + ("rotation_wxyz",), [2, 0, 0, 0], "rotation_wxyz"),
                          (tf + ("rotation_wxyz", 1), math.nan, "rotation_wxyz[1] is nan"),
                          (tf + ("translation_mm", 2), math.inf, "translation_mm[2] is inf"),
                          (("clock", "t0"), math.nan, "clock.t0 is nan"),
                          (("provenance",), {"notes": -math.inf}, "provenance.notes is -inf")):
        doc = json.loads(json.dumps(good))
        put(doc, path, v)
        (s / "session.json").write_text(json.dumps(doc))
        rc, lines = cli(["session", "check", s], capsys)
        assert rc == 2 and len(lines) == 1 and want in lines[0], (path, v, lines)


@pytest.mark.parametrize("stretch", ["0", "-1", "1e300", "1e-300"])
def test_named_fit_material_stretches(tmp_path, cli, capsys, stretch):
    csv = tmp_path / "m.csv"
    csv.write_text(f"mode,stretch,stress_MPa\nuniaxial,1.1,0.01\nuniaxial,{stretch},0.02\nbiaxial,1.2,0.03\n")
    t0 = time.monotonic()
    rc, lines = cli(["fe", "fit-material", csv, "--models", "yeoh"], capsys)
    assert rc == 2 and len(lines) == 1 and "m.csv:3: column stretch" in lines[0], lines
    assert time.monotonic() - t0 < MAX_S


def test_cli_subprocess_shape(tmp_path):
    """One implausible value per format through real `tensortouch` processes: exit 2, one stderr line."""
    from tests.test_bad_inputs import cli_many, tiny_session

    store = tmp_path / "store"
    dome_calibration(store, "TT-SUB", size=8, image=(160, 120), radius_px=50.0)
    cal = store / "TT-SUB" / "versions" / "v0001" / "calibration.json"
    cal.write_text(json.dumps({**json.loads(cal.read_text()), "gel_radius_px": 1e9}))
    pkg = make_package(tmp_path / "pkg")
    man = json.loads((pkg / "manifest.json").read_text())
    man["output"]["bounds"]["disp_x"][1] = 10 ** 400
    (pkg / "manifest.json").write_text(json.dumps(man))
    hand = tmp_path / "hand.toml"
    hand.write_text('[hand]\nthreads = "x"\n[[finger]]\nname = "f0"\nserial = "TT-1"\n')
    s = tiny_session(tmp_path / "s", poses=np.array([[0.0, 0, 1, 2, -1e308, 1, 0, 0, 0]]))
    cases = [(["calib", "show", "TT-SUB", "--store", store], "gel_radius_px is 1000000000.0"),
             (["run", "--model", pkg, "--sensor", "TT-SUB"], "output.bounds.disp_x[1]"),
             (["hand", hand], "threads is 'x'"),
             (["train", "all", "--recipe", "tiny", "--set", "batch=0", "--root", tmp_path / "b"], "batch is 0"),
             (["session", "check", s], "z = -1e+308")]
    for (argv, want), (rc, lines) in zip(cases, cli_many([argv for argv, _ in cases])):
        assert rc == 2 and len(lines) == 1 and want in lines[0], (argv, rc, lines)
    assert not (tmp_path / "b").exists()          # refused before the build folder was made


