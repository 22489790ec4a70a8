"""Malformed-input corpus: every bad input named in docs/runtime.md "Errors" gives one line naming the file
or field and what was expected, exit 2, no traceback.

Three layers, all generated here from a fixed seed (nothing downloaded, nothing large committed):
- named cases, each through its loader in-process (the error type and the named field are checked);
- a handful of the same through real `tensortouch` subprocesses (exit 2, exactly one stderr line);
- seeded fuzz: >= 500 mutated documents per format (model manifest, calibration manifest, session,
  MCAP bag, ROS1 bag) through the loaders in-process: each either loads or raises the project's error
  with a one-line message; any other exception fails the test.
"""
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from tensortouch.contracts.errors import TensorTouchError
from tensortouch.contracts.session import STREAM_COLUMNS, load_session, new_manifest, write_table
from tensortouch.contracts.store import CalibrationStore, sha256_file
from tensortouch.runtime.stages.model import FieldModel, load_package

from tests.conftest import dome_calibration
from tests.hand_util import make_package

ROOT = Path(__file__).resolve().parents[1]
FUZZ_CASES = 500


# ------------------------------------------------------------------------------------------ builders
def tiny_session(folder: Path, n: int = 4, wrench=None, poses=None) -> Path:
    """A small valid session (PNG frames) with optional wrench/poses rows."""
    import cv2

    folder.mkdir(parents=True, exist_ok=True)
    (folder / "frames").mkdir(exist_ok=True)
    for i in range(n):
        cv2.imwrite(str(folder / "frames" / f"{i:06d}.png"), np.full((8, 8, 3), 10 * i, np.uint8))
    write_table(folder / "frames.csv", STREAM_COLUMNS["frames"], np.stack([np.arange(n) / 30, np.arange(n)], 1))
    streams = {"frames": {"file": "frames.csv", "images": "frames", "rows": n}}
    if wrench is not None:
        write_table(folder / "wrench.csv", STREAM_COLUMNS["wrench"], wrench)
        streams["wrench"] = {"file": "wrench.csv", "ft_to_indenter": {"rotation_wxyz": [1, 0, 0, 0],
                                                                       "translation_mm": [0, 0, 0]}}
    if poses is not None:
        write_table(folder / "poses.csv", STREAM_COLUMNS["poses"], poses)
        streams["poses"] = {"file": "poses.csv"}
    (folder / "session.json").write_text(json.dumps(new_manifest("BAD-1", streams)))
    return folder


def symbolic_model_package(folder: Path) -> Path:
    """A package whose graph declares symbolic H, W and really outputs twice the input size:
    (1, 6, 32, 32) in → (1, 15, 64, 64) out (channels tiled, then a nearest 2x resize)."""
    import onnx
    from onnx import TensorProto, helper

    folder = make_package(folder)
    x = helper.make_tensor_value_info("input", TensorProto.FLOAT, ["n", 6, "h", "w"])
    y = helper.make_tensor_value_info("fields", TensorProto.FLOAT, ["n", 15, "h", "w"])
    ints = lambda name, v: helper.make_tensor(name, TensorProto.INT64, [len(v)], v)
    inits = [ints("s0", [0]), ints("s1", [15]), ints("ax", [1]),
             helper.make_tensor("roi", TensorProto.FLOAT, [0], []),
             helper.make_tensor("scales", TensorProto.FLOAT, [4], [1.0, 1.0, 2.0, 2.0])]
    nodes = [helper.make_node("Concat", ["input", "input", "input"], ["c"], axis=1),
             helper.make_node("Slice", ["c", "s0", "s1", "ax"], ["sl"]),
             helper.make_node("Resize", ["sl", "roi", "scales"], ["fields"], mode="nearest")]
    model = helper.make_model(helper.make_graph(nodes, "symbolic", [x], [y], initializer=inits),
                              opset_imports=[helper.make_opsetid("", 13)])
    model.ir_version = 8
    for name in ("model.fp32.onnx", "model.int8.onnx"):
        onnx.save(model, str(folder / name))
    manifest = json.loads((folder / "manifest.json").read_text())
    manifest["files"] = {n: {"sha256": sha256_file(folder / n)} for n in ("model.fp32.onnx", "model.int8.onnx")}
    (folder / "manifest.json").write_text(json.dumps(manifest))
    return folder


def nested_list_avi(path: Path, depth: int = 5000) -> Path:
    """RIFF AVI made of `depth` nested LIST chunks (a recursion bomb for a recursive chunk walker)."""
    import struct

    body = b""
    for _ in range(depth):
        body = b"LIST" + struct.pack("<I", len(body) + 4) + b"movi" + body
    path.write_bytes(b"RIFF" + struct.pack("<I", len(body) + 4) + b"AVI " + body)
    return path


def mcap_bytes(kind: str = "json", n: int = 3, stamps=None, wrench_nan: bool = False) -> bytes:
    """A small MCAP recording: /cam images (json encoding) and optionally /ft wrench, /pose poses."""
    import io

    from mcap.writer import Writer

    buf = io.BytesIO()
    w = Writer(buf)
    w.start()
    sid = w.register_schema("Msg", "jsonschema", b"{}")
    cam = w.register_channel("/cam", "json", sid)
    img = np.full((4, 4, 3), 7, np.uint8)
    for i in range(n):
        msg = {"height": 4, "width": 4, "encoding": "bgr8", "step": 12, "data": img.ravel().tolist()}
        w.add_message(cam, (i + 1) * 10**8, json.dumps(msg).encode(), 0)
    if kind in ("wrench", "poses"):
        ch = w.register_channel("/x", "json", sid)
        for i, t in enumerate(stamps if stamps is not None else range(n)):
            if kind == "wrench":
                f = float("nan") if wrench_nan and i == 1 else 1.0
                msg = {"wrench": {"force": {"x": f, "y": 0, "z": 0}, "torque": {"x": 0, "y": 0, "z": 0}}}
            else:
                msg = {"pose": {"position": {"x": 0, "y": 0, "z": 0}, "orientation": {"w": 1, "x": 0, "y": 0, "z": 0}}}
            w.add_message(ch, int((t + 1) * 10**8), json.dumps(msg, allow_nan=True).encode(), 0)
    w.finish()
    return buf.getvalue()


def cdr_mcap_bytes(payloads) -> bytes:
    """An MCAP file with a ROS 2 sensor_msgs/Image channel (cdr) carrying the given raw payloads."""
    import io

    from mcap.writer import Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    typ = "sensor_msgs/msg/Image"
    buf = io.BytesIO()
    w = Writer(buf)
    w.start(profile="ros2")
    sid = w.register_schema(typ, "ros2msg", ts.generate_msgdef(typ, ros_version=2)[0].encode())
    ch = w.register_channel("/cam", "cdr", sid)
    for i, data in enumerate(payloads):
        w.add_message(ch, (i + 1) * 10**8, data, 0)
    w.finish()
    return buf.getvalue()


def good_cdr_image() -> bytes:
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    t = ts.types
    m = t["sensor_msgs/msg/Image"](header=t["std_msgs/msg/Header"](stamp=t["builtin_interfaces/msg/Time"](
        sec=1, nanosec=0), frame_id="c"), height=4, width=4, encoding="bgr8", is_bigendian=0, step=12,
        data=np.full(48, 7, np.uint8))
    return bytes(ts.serialize_cdr(m, "sensor_msgs/msg/Image"))


def ros1_bag_bytes(tmp: Path) -> bytes:
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS1_NOETIC)
    bag = tmp / "seed.bag"
    img = ts.types["sensor_msgs/msg/Image"]
    hdr = ts.types["std_msgs/msg/Header"]
    stamp = ts.types["builtin_interfaces/msg/Time"]
    with Writer(bag) as w:
        c = w.add_connection("/cam", "sensor_msgs/msg/Image", typestore=ts)
        for i in range(3):
            m = img(header=hdr(seq=i, stamp=stamp(sec=1 + i, nanosec=0), frame_id="c"), height=4, width=4,
                    encoding="bgr8", is_bigendian=0, step=12, data=np.full(48, 7, np.uint8))
            w.write(c, (1 + i) * 10**9, ts.serialize_ros1(m, "sensor_msgs/msg/Image"))
    return bag.read_bytes()


# ------------------------------------------------------------------------------------------ helpers
def one_line(exc: BaseException) -> str:
    msg = str(exc)
    assert isinstance(exc, TensorTouchError), f"{type(exc).__name__}: {msg}"
    assert msg and "\n" not in msg and "Traceback" not in msg, msg
    return msg


def raises_one_line(fn, *args, match=None, **kw) -> str:
    try:
        fn(*args, **kw)
    except Exception as exc:  # noqa: BLE001 - the point: which exception, and its message
        msg = one_line(exc)
        if match is not None:
            assert match in msg, msg
        return msg
    pytest.fail(f"{fn.__name__}{args} accepted a bad input")


def cli_many(cases):
    """`tensortouch ARGV` for each ARGV as real subprocesses, run side by side → [(exit code, stderr lines)]."""
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    procs = [subprocess.Popen([sys.executable, "-m", "tensortouch.runtime.shells.cli", *map(str, argv)], stdout=subprocess.DEVNULL,
                              stderr=subprocess.PIPE, text=True, cwd=ROOT, env=env) for argv in cases]
    out = []
    for p in procs:
        _, err = p.communicate(timeout=180)
        out.append((p.returncode, [line for line in err.splitlines() if not line.startswith("INFO ")]))
    return out


# ------------------------------------------------------------------------------------------ named cases
def test_model_manifest_bad_inputs(tmp_path):
    pkg = make_package(tmp_path / "pkg")
    good = json.loads((pkg / "manifest.json").read_text())

    def with_manifest(text: bytes | str):
        (pkg / "manifest.json").write_bytes(text if isinstance(text, bytes) else text.encode())
        return pkg

    raises_one_line(load_package, with_manifest(json.dumps([good])), match="expected a JSON object, got list")
    raises_one_line(load_package, with_manifest(b"\xff\xfe{\x00"), match="not UTF-8")
    raises_one_line(load_package, with_manifest("[" * 100000), match="not valid JSON")
    for value, want in (("abc", "threshold_n is 'abc'"), (-1, "threshold_n is -1"),
                        (0, "threshold_n is 0")):
        raises_one_line(load_package, with_manifest(json.dumps({**good, "runtime": {"contacts": {"threshold_n": value}}})),
                        match=want)
    raises_one_line(load_package, with_manifest(json.dumps({**good, "runtime": {"contacts": {"merge_n": -0.5}}})),
                    match="merge_n")
    for value in (1.0, 1.5, -0.1, "half"):             # a share of the peak: [0, 1)
        raises_one_line(load_package, with_manifest(json.dumps({**good, "runtime": {"contacts": {"split_dip": value}}})),
                        match="split_dip is")
    for value in ("yes", 1, 0, [True]):                 # the tare: a boolean or null, nothing truthy
        raises_one_line(load_package, with_manifest(json.dumps({**good, "runtime": {"tare": value}})),
                        match="runtime.tare is")
    raises_one_line(load_package, with_manifest(json.dumps({**good, "files": {}})), match="files is empty")
    raises_one_line(load_package, with_manifest(json.dumps({**good, "files": {"model.int8.onnx": "abc"}})),
                    match="files.model.int8.onnx must be an object")
    raises_one_line(load_package, with_manifest(json.dumps({**good, "output": {**good["output"], "bounds": []}})),
                    match="output.bounds must be an object")
    with_manifest(json.dumps({**good, "runtime": {"contacts": {"threshold_n": 0.2, "merge_n": None}}}))
    assert load_package(pkg).manifest["runtime"]["contacts"]["threshold_n"] == 0.2


def test_model_with_symbolic_dims_and_wrong_output_size(tmp_path):
    pkg = load_package(symbolic_model_package(tmp_path / "sym"))
    raises_one_line(FieldModel, pkg, "fp32", match="output shape [1, 15, 64, 64] for a (1, 6, 32, 32) input")


def test_session_bad_inputs(tmp_path):
    s = tiny_session(tmp_path / "s")
    good = json.loads((s / "session.json").read_text())
    (s / "session.json").write_text(json.dumps([good]))
    raises_one_line(load_session, s, match="session.json: expected a JSON object, got list")
    (s / "session.json").write_bytes(b'{"schema": "\xff"}')
    raises_one_line(load_session, s, match="not UTF-8")
    (s / "session.json").write_text(json.dumps({**good, "streams": {"frames": ["frames.csv"]}}))
    raises_one_line(load_session, s, match="streams.frames must be an object")
    (s / "session.json").write_text(json.dumps({**good, "streams": {"frames": {**good["streams"]["frames"],
                                                                            "file": "../../etc/passwd"}}}))
    raises_one_line(load_session, s, match="streams.frames.file")
    (s / "session.json").write_text(json.dumps(good))
    load_session(s)
    (s / "frames.csv").write_bytes(b"t,index\n0.0,0\n\xff\xfe,1\n")
    raises_one_line(load_session, s, match="frames.csv: not UTF-8")
    (s / "frames.csv").write_text("t,index\n" + "9" * 200000 + ",0\n")
    raises_one_line(load_session, s, match="frames.csv:2: not readable as CSV (field larger than field limit")
    (s / "frames.csv").write_text("t,index\n0,0\n0\x00,1\n")
    raises_one_line(load_session, s, match="frames.csv")


def test_hand_config_not_utf8(tmp_path):
    from tensortouch.runtime.apps.hand_config import load_hand_config

    cfg = tmp_path / "hand.toml"
    cfg.write_bytes(b'[hand]\nname = "h\xff"\n')
    raises_one_line(load_hand_config, cfg, match="hand.toml: not UTF-8")
    cfg.write_text('[hand\nname = "h"\n')
    raises_one_line(load_hand_config, cfg, match="not valid TOML")


def test_avi_of_nested_list_chunks(tmp_path):
    s = tiny_session(tmp_path / "s")
    meta = json.loads((s / "session.json").read_text())
    nested_list_avi(s / "frames.avi")
    meta["streams"]["frames"] = {"file": "frames.csv", "video": "frames.avi", "rows": 4}
    (s / "session.json").write_text(json.dumps(meta))
    raises_one_line(load_session, s, match="0 complete frames but frames.csv lists 4")


def test_calibration_manifest_bad_inputs(tmp_path):
    store = CalibrationStore(tmp_path / "calib")
    dome_calibration(store.root, "TT-BAD", size=16)
    path = store.root / "TT-BAD" / "versions" / "v0001" / "calibration.json"
    good = json.loads(path.read_text())
    for text, want in ((json.dumps([good]), "expected a JSON object, got list"),
                       (b"\xff{}", "not UTF-8"),
                       (json.dumps({**good, "files": {}}), "files must be a non-empty object"),
                       (json.dumps({**good, "gel_center_px": "12,3"}), "gel_center_px must be")):
        path.write_bytes(text if isinstance(text, bytes) else text.encode())
        raises_one_line(store.load, "TT-BAD", match=want)


def test_fit_material_model_and_mode_spellings(tmp_path):
    from tensortouch.tools.fe.fitting import (
        fit_report,
        load_test_data,
        model_name,
        synthetic_test_data,
    )

    assert [model_name(m) for m in ("Yeoh", "NEO-HOOKEAN", "neo hookean", "NH", "Mooney-Rivlin", "MR", "Ogden")] == \
        ["yeoh", "neo_hookean", "neo_hookean", "neo_hookean", "mooney_rivlin", "mooney_rivlin", "ogden"]
    for bad in ("ogden3", "Yeo", "arruda_boyce"):
        raises_one_line(model_name, bad, match=repr(bad))
    report = fit_report(synthetic_test_data(), models=["Yeoh"])
    assert report["fits"][0]["model"] == "yeoh"
    csv = tmp_path / "m.csv"
    csv.write_text("mode,stretch,stress_MPa\n" + "".join(f"{m},{1 + 0.1 * i},{0.01 * i}\n"
                   for i, m in enumerate(["uniaxial", "Equibiaxial", "equi-biaxial", "biaxial", "UNIAXIAL"])))
    assert list(load_test_data(csv).mode) == ["uniaxial", "biaxial", "biaxial", "biaxial", "uniaxial"]
    csv.write_text("mode,stretch,stress_MPa\nshear,1.1,0.01\n")
    raises_one_line(load_test_data, csv, match="column mode")
    csv.write_text("mode,stretch,stress_MPa\nuniaxial,abc,0.01\n")
    raises_one_line(load_test_data, csv, match="column stretch")
    csv.write_bytes(b"mode,stretch,stress_MPa\nuni\xffaxial,1,1\n")
    raises_one_line(load_test_data, csv, match="not UTF-8")


MAP = {"sensor_id": "IMP-1", "clock": "log", "frames": {"topic": "/cam"}}


@pytest.mark.parametrize("name,make,want", [
    ("empty.mcap", lambda tmp: b"", "cannot read as a MCAP file"),
    ("random.mcap", lambda tmp: np.random.default_rng(1).bytes(4000), "cannot read as a MCAP file"),
    ("truncated.mcap", lambda tmp: mcap_bytes()[:300], "cannot read as a MCAP file"),
    ("truncated-cdr.mcap", lambda tmp: cdr_mcap_bytes([good_cdr_image()[:30]] * 2), "cannot read as a MCAP file"),
    ("random-cdr.mcap", lambda tmp: cdr_mcap_bytes([np.random.default_rng(4).bytes(80)]), "cannot read as a MCAP"),
    ("wrong-type-cdr.mcap", lambda tmp: cdr_mcap_bytes([good_cdr_image()[:4] + b"\xff" * 60]), "cannot read as a MCAP"),
    ("empty.bag", lambda tmp: b"", "cannot read as a ROS bag"),
    ("random.bag", lambda tmp: np.random.default_rng(2).bytes(4000), "cannot read as a ROS bag"),
    ("truncated.bag", lambda tmp: ros1_bag_bytes(tmp)[:700], "cannot read as a ROS bag"),
])
def test_session_import_of_broken_recordings(tmp_path, name, make, want):
    from tensortouch.tools.sessions.bags import TopicMap, convert

    bag = tmp_path / name
    bag.write_bytes(make(tmp_path))
    raises_one_line(convert, bag, TopicMap.load(MAP), tmp_path / "out", match=want)


def test_session_import_mis_typed_messages_and_maps(tmp_path):
    import io

    from mcap.writer import Writer
    from tensortouch.tools.sessions.bags import TopicMap, convert

    buf = io.BytesIO()                       # JSON messages whose fields have the wrong types
    w = Writer(buf)
    w.start()
    sid = w.register_schema("Msg", "jsonschema", b"{}")
    ch = w.register_channel("/cam", "json", sid)
    for i, msg in enumerate([{"height": "four", "width": 4, "encoding": "bgr8", "step": 12, "data": [1, 2]},
                             [1, 2, 3], "just a string"]):
        w.add_message(ch, (i + 1) * 10**8, json.dumps(msg).encode(), 0)
    w.finish()
    bag = tmp_path / "mistyped.mcap"
    bag.write_bytes(buf.getvalue())
    raises_one_line(convert, bag, TopicMap.load(MAP), tmp_path / "o1", match="cannot read as a MCAP file")
    bag.write_bytes(mcap_bytes(n=2)[:-1] + b"\x00" * 64)  # footer garbage (CDR-less MCAP, broken tail)
    raises_one_line(convert, bag, TopicMap.load(MAP), tmp_path / "o2")
    raises_one_line(TopicMap.load, {**MAP, "wrench": [{"topic": "/ft"}]}, match="wrench[0].indenter must be given")
    raises_one_line(TopicMap.load, {**MAP, "poses": [{"topic": "/p", "indenter": "0"}]}, match="poses[0].indenter")
    raises_one_line(TopicMap.load, {**MAP, "poses": {"topic": "/p"}}, match="poses must be a list")
    raises_one_line(TopicMap.load, {**MAP, "frames": "/cam"}, match="frames.topic")
    raises_one_line(TopicMap.load, {**MAP, "ft_to_indenter": {"rotation_wxyz": [1, 0, 0]}}, match="ft_to_indenter")
    m = tmp_path / "map.json"
    m.write_text(json.dumps([MAP]))
    raises_one_line(TopicMap.load, m, match="got list")
    m.write_bytes(b'{"sensor_id": "\xff"}')
    raises_one_line(TopicMap.load, m, match="not UTF-8")


@pytest.mark.parametrize("kind,kw,want", [
    ("poses", {"stamps": [0, 1, 1, 2]}, "clock not strictly increasing"),
    ("wrench", {"wrench_nan": True}, "non-finite value in stream 'wrench'"),
])
def test_session_import_refuses_what_session_check_rejects(tmp_path, kind, kw, want):
    from tensortouch.tools.sessions.bags import TopicMap, convert

    bag = tmp_path / "rec.mcap"
    bag.write_bytes(mcap_bytes(kind, n=4, **kw))
    m = TopicMap.load({**MAP, kind: [{"topic": "/x", "indenter": 0}]})
    msg = raises_one_line(convert, bag, m, tmp_path / "out", match=want)
    assert "fails the session check" in msg
    assert not (tmp_path / "out" / "session.json").exists()      # no output that `session check` would reject


# ------------------------------------------------------------------------------------------ CLI end to end
def test_cli_one_line_exit_2(tmp_path):
    """A handful of the cases above through real `tensortouch` subprocesses."""
    s = tiny_session(tmp_path / "arr")
    (s / "session.json").write_text("[]")
    pkg = make_package(tmp_path / "pkg")
    manifest = json.loads((pkg / "manifest.json").read_text())
    (pkg / "manifest.json").write_text(json.dumps({**manifest, "runtime": {"contacts": {"threshold_n": "abc"}}}))
    store = tmp_path / "calib"
    dome_calibration(store, "TT-CLI", size=16)
    cal_json = store / "TT-CLI" / "versions" / "v0001" / "calibration.json"
    cal_json.write_text(json.dumps([json.loads(cal_json.read_text())]))
    bag = tmp_path / "random.mcap"
    bag.write_bytes(np.random.default_rng(3).bytes(2000))
    mapf = tmp_path / "map.json"
    mapf.write_text(json.dumps({**MAP, "wrench": [{"topic": "/ft"}]}))
    cases = [
        (["session", "check", s], "session.json: expected a JSON object"),
        (["run", "--model", pkg, "--sensor", "TT-CLI"], "runtime.contacts.threshold_n is 'abc'"),
        (["calib", "show", "TT-CLI", "--store", store], "calibration.json: expected a JSON object"),
        (["session", "import", bag, "--map", mapf, "--out", tmp_path / "o"], "wrench[0].indenter must be given"),
        (["fe", "fit-material", "synthetic", "--models", "ogden3"], "unknown material model 'ogden3'"),
    ]
    for (argv, want), (rc, lines) in zip(cases, cli_many([argv for argv, _ in cases])):
        assert rc == 2 and len(lines) == 1 and want in lines[0], (argv, rc, lines)
        assert "Traceback" not in lines[0]


# ------------------------------------------------------------------------------------------ seeded fuzz
def _mutate_json(rng, doc):
    """One random structural mutation of a JSON document (a deep copy is changed)."""
    doc = json.loads(json.dumps(doc))
    junk = [None, True, -1, 0, 1e308, "abc", "", [], {}, [1, 2], {"a": 1}, "../../x", "/etc/passwd",
            float("nan"), float("inf"), "\u0000", [[[]]], 3.5, "v0001", "0" * 64]

    def paths(node, prefix=()):
        out = [prefix]
        if isinstance(node, dict):
            for k, v in node.items():
                out += paths(v, prefix + (k,))
        elif isinstance(node, list):
            for i, v in enumerate(node[:4]):
                out += paths(v, prefix + (i,))
        return out

    for _ in range(int(rng.integers(1, 4))):
        all_paths = paths(doc)
        target = all_paths[int(rng.integers(len(all_paths)))]
        op = int(rng.integers(4))
        if not target:
            doc = junk[int(rng.integers(len(junk)))] if op == 0 else [doc]
            continue
        parent = doc
        for k in target[:-1]:
            parent = parent[k]
        key = target[-1]
        if op == 0 and isinstance(parent, dict):
            del parent[key]
        elif op == 1:
            parent[key] = junk[int(rng.integers(len(junk)))]
        elif op == 2:
            parent[key] = [parent[key]]
        else:
            parent[key] = {"x": parent[key]}
    return doc


def _mutate_bytes(rng, data: bytes) -> bytes:
    data = bytearray(data)
    op = int(rng.integers(4))
    if op == 0 and data:
        return bytes(data[:int(rng.integers(len(data)))])                     # truncated
    if op == 1:
        for _ in range(int(rng.integers(1, 8))):                               # flipped bytes
            if data:
                data[int(rng.integers(len(data)))] = int(rng.integers(256))
        return bytes(data)
    if op == 2:
        at = int(rng.integers(len(data) + 1))                                  # inserted garbage
        return bytes(data[:at]) + rng.bytes(int(rng.integers(1, 64))) + bytes(data[at:])
    return bytes(data).replace(b'"', b"\xff", int(rng.integers(1, 3)))        # non-UTF-8


def _fuzz_text(rng, doc) -> bytes:
    if rng.random() < 0.75:
        return json.dumps(_mutate_json(rng, doc)).encode()
    return _mutate_bytes(rng, json.dumps(doc).encode())


def _loads_or_one_line(fn, *args):
    try:
        fn(*args)
        return "ok"
    except Exception as exc:  # noqa: BLE001 - anything but the project's one-line error fails
        one_line(exc)
        return "refused"


def test_fuzz_model_manifests(tmp_path):
    pkg = make_package(tmp_path / "pkg")
    good = json.loads((pkg / "manifest.json").read_text())
    rng = np.random.default_rng(2026)
    outcome = []
    for _ in range(FUZZ_CASES):
        (pkg / "manifest.json").write_bytes(_fuzz_text(rng, good))
        outcome.append(_loads_or_one_line(load_package, pkg))
    assert outcome.count("refused") > FUZZ_CASES // 2, outcome.count("refused")


def test_fuzz_calibration_manifests(tmp_path):
    store = CalibrationStore(tmp_path / "calib")
    dome_calibration(store.root, "TT-FUZZ", size=8)
    path = store.root / "TT-FUZZ" / "versions" / "v0001" / "calibration.json"
    good = json.loads(path.read_text())
    rng = np.random.default_rng(2027)
    outcome = []
    for i in range(FUZZ_CASES):
        path.write_bytes(_fuzz_text(rng, good))
        if i % 10 == 0:     # the pointer too
            (store.root / "TT-FUZZ" / "CURRENT").write_bytes(_mutate_bytes(rng, b"v0001\n"))
        outcome.append(_loads_or_one_line(store.load, "TT-FUZZ"))
        (store.root / "TT-FUZZ" / "CURRENT").write_text("v0001\n")
    assert outcome.count("refused") > FUZZ_CASES // 2


def test_fuzz_sessions(tmp_path):
    s = tiny_session(tmp_path / "s", wrench=np.array([[0.0, 0, 1, 2, 3, 0, 0, 0], [0.1, 0, 1, 2, 3, 0, 0, 0]]))
    good = json.loads((s / "session.json").read_text())
    csv_good = (s / "wrench.csv").read_bytes()
    rng = np.random.default_rng(2028)
    outcome = []
    for _ in range(FUZZ_CASES):
        if rng.random() < 0.7:
            (s / "session.json").write_bytes(_fuzz_text(rng, good))
        else:
            (s / "wrench.csv").write_bytes(_mutate_bytes(rng, csv_good))
        outcome.append(_loads_or_one_line(lambda p: [load_session(p).table(n) for n in good["streams"]], s))
        (s / "session.json").write_text(json.dumps(good))
        (s / "wrench.csv").write_bytes(csv_good)
    assert outcome.count("refused") > FUZZ_CASES // 3


@pytest.mark.parametrize("fmt", ["mcap", "bag"])
def test_fuzz_bags(tmp_path, fmt):
    from tensortouch.tools.sessions.bags import TopicMap, convert

    seed = mcap_bytes() if fmt == "mcap" else ros1_bag_bytes(tmp_path)
    m = TopicMap.load(MAP)
    rng = np.random.default_rng(2029 if fmt == "mcap" else 2030)
    outcome = []
    bag = tmp_path / f"fuzz.{fmt}"
    for i in range(FUZZ_CASES):
        bag.write_bytes(_mutate_bytes(rng, seed))
        outcome.append(_loads_or_one_line(convert, bag, m, tmp_path / f"out{i % 2}"))
    assert outcome.count("refused") > FUZZ_CASES // 3, outcome.count("refused")
