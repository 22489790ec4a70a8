"""`tensortouch listen` against a real publisher on loopback zenoh."""
import argparse
import json
import socket
import subprocess
import sys
import threading
import time

import numpy as np
import pytest
from tensortouch.contracts import wire
from tensortouch.contracts.fields import CHANNELS
from tensortouch.runtime.apps.publisher import Publisher
from tensortouch.runtime.shells.listen import add_listen_parser, format_line


def free_endpoint() -> str:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return f"tcp/127.0.0.1:{s.getsockname()[1]}"


def parse(argv):
    parser = argparse.ArgumentParser(prog="tensortouch")
    add_listen_parser(parser.add_subparsers(dest="command"))
    return parser.parse_args(argv)


CONTACT = wire.Contact(id=3, uv_px=(30.0, 31.0), position_mm=(2.0, 1.0, 14.0), normal=(0, 0, 1),
                       area_mm2=5.25, force_n=(0.0, 0.1, -1.0), force_mag_n=1.005,
                       perimeter_px=15.0, circularity=0.9, priority=1.0, age_frames=2)


@pytest.fixture
def running_sensor():
    """A publisher (listening on a free port) sending all four streams at ~50 Hz from a thread."""
    ep = free_endpoint()
    pub = Publisher("dome01", listen=[ep], info=lambda: {"model": {"name": "tiny"}})
    stop = threading.Event()

    def loop():
        seq = 0
        fields = np.linspace(-1, 1, 15 * 16 * 16, dtype=np.float32).reshape(15, 16, 16)
        while not stop.is_set():
            t = time.time()
            pub.publish_fields(fields, seq, t)
            pub.publish_contacts([CONTACT], seq, t)
            pub.publish_wrench((0.0, 0.1, -1.0), (1.0, 2.0, 0.0), seq, t)
            pub.publish_status({"state": "contact", "fps": 50.0,
                                "timings_ms": {"infer": 9.0}}, seq, t)
            seq += 1
            time.sleep(0.02)

    th = threading.Thread(target=loop, daemon=True)
    th.start()
    try:
        yield ep
    finally:
        stop.set()
        th.join(5)
        pub.close()


def test_listen_prints_and_saves(running_sensor, tmp_path, capsys):
    args = parse(["listen", "dome01", "--connect", running_sensor, "--count", "12", "--timeout", "20",
                  "--save", str(tmp_path), "--info"])
    assert args.func(args) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0] == "alive: ['dome01']" and lines[1].startswith("info dome01: ")
    assert json.loads(lines[1].split(": ", 1)[1])["model"]["name"] == "tiny"
    msgs = lines[2:]
    assert len(msgs) == 12
    kinds = {line.split()[0] for line in msgs}
    assert kinds == {f"tensortouch/dome01/{k}" for k in wire.KINDS}
    contact_line = next(line for line in msgs if "/contacts" in line)
    assert "#3 |F|=1.005 N F=(0.000,0.100,-1.000) N at (2.00,1.00,14.00) mm area=5.25 mm2" in contact_line
    assert "state=contact" in next(line for line in msgs if "/status" in line)
    assert "15x16x16 float32" in next(line for line in msgs if "/fields" in line)

    folder = tmp_path / "dome01"
    npys = sorted((folder / "fields").glob("*.npy"))
    assert npys and not list((folder / "fields").glob("*.tmp"))
    arr = np.load(npys[0])
    assert arr.shape == (15, 16, 16) and arr.dtype == np.float32
    np.testing.assert_allclose(arr.ravel(), np.linspace(-1, 1, 15 * 16 * 16), atol=1e-3)
    meta = json.loads((folder / "fields" / "meta.json").read_text())
    assert meta["channels"] == list(CHANNELS)
    rec = json.loads((folder / "contacts.jsonl").read_text().splitlines()[0])
    assert wire.Contact.from_dict(rec["contacts"][0]) == CONTACT
    assert (folder / "status.jsonl").exists() and (folder / "wrench.jsonl").exists()


def test_listen_json_in_separate_process(running_sensor):
    """`python -m runtime.shells.listen` in another process: one JSON object per message line."""
    proc = subprocess.run([sys.executable, "-m", "tensortouch.runtime.shells.cli", "listen", "*", "--connect",
                           running_sensor, "--count", "8", "--timeout", "30", "--json",
                           "--kinds", "contacts,status"],
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    objs = [json.loads(line) for line in proc.stdout.splitlines()]
    assert len(objs) == 8 and {o["kind"] for o in objs} == {"contacts", "status"}
    c = next(o for o in objs if o["kind"] == "contacts")
    assert c["sensor_id"] == "dome01" and c["contacts"][0]["position_mm"] == [2.0, 1.0, 14.0]
    s = next(o for o in objs if o["kind"] == "status")
    assert s["timings_ms"] == {"infer": 9.0}


def test_listen_json_never_prints_a_message_holding_nan(running_sensor):
    """A forger (a client session of the sensor's peer) puts contacts and wrenches with NaN/Infinity: `listen --json`
    in another process prints only strict JSON (no NaN token) and says on stderr how many it dropped."""
    import zenoh
    from tensortouch.runtime.apps.publisher import zenoh_config

    forger = zenoh.open(zenoh_config(mode="client", connect=[running_sensor]))  # peers route for clients
    stop = threading.Event()

    def forge():
        c = CONTACT.to_dict()
        while not stop.is_set():
            body = {"schema": "tensortouch.contacts.v1", "sensor_id": "dome01", "seq": 1, "t": 1.0,
                    "contacts": [{**c, "force_n": [float("nan"), 0.0, 0.0]}]}
            forger.put("tensortouch/dome01/contacts", json.dumps(body), encoding=wire.ENCODINGS["contacts"])
            forger.put("tensortouch/dome01/wrench",
                       '{"schema":"tensortouch.wrench.v1","sensor_id":"dome01","seq":1,"t":1.0,"frame":"gel",'
                       '"force_n":[NaN,0,0],"torque_nmm":[0,0,-Infinity]}', encoding=wire.ENCODINGS["wrench"])
            time.sleep(0.01)

    th = threading.Thread(target=forge, daemon=True)
    th.start()
    try:
        proc = subprocess.run([sys.executable, "-m", "tensortouch.runtime.shells.cli", "listen", "dome01",
                               "--connect", running_sensor, "--count", "40", "--timeout", "30", "--json",
                               "--kinds", "contacts,wrench"], capture_output=True, text=True, timeout=60)
    finally:
        stop.set()
        th.join(5)
        forger.close()
    assert proc.returncode == 0, proc.stderr

    def refuse(token):
        raise AssertionError(f"listen printed {token}")
    objs = [json.loads(line, parse_constant=refuse) for line in proc.stdout.splitlines()]
    assert len(objs) == 40
    assert all(o["force_n"] == [0.0, 0.1, -1.0] for o in objs if o["kind"] == "wrench")
    assert all(c["force_n"] == [0.0, 0.1, -1.0] for o in objs if o["kind"] == "contacts" for c in o["contacts"])
    assert "held NaN or infinite numbers and were dropped" in proc.stderr, proc.stderr


def test_listen_nothing_running_exits_1_with_hint(capsys):
    args = parse(["listen", "--connect", free_endpoint(), "--timeout", "1"])
    assert args.func(args) == 1
    assert "no messages" in capsys.readouterr().err


def test_listen_rejects_unknown_kind():
    from tensortouch.contracts.errors import CommandError

    args = parse(["listen", "--kinds", "fields,pressure", "--timeout", "1"])
    with pytest.raises(CommandError, match="pressure"):
        args.func(args)


def test_format_line_status_and_wrench():
    st = wire.decode_status(wire.encode_status({"state": "stable", "flags": ["camera_stalled"],
                                                "fps": 0.0, "timings_ms": {"capture": 33.3}},
                                               4, 1.0, "s1"))
    assert format_line("status", st) == ("tensortouch/s1/status   seq=4 t=1.000 state=stable fps=0.0 "
                                         "flags=camera_stalled timings_ms: capture=33.30")
    w = wire.decode_wrench(wire.encode_wrench((0, 0, -2), (0.5, 0, 0), 4, 1.0, "s1"))
    assert "F=(0.000,0.000,-2.000) N tau=(0.50,0.00,0.00) N*mm" in format_line("wrench", w)


def _fields(sensor="dome01", seq=0):
    data = np.arange(15 * 4 * 4, dtype=np.float32).reshape(15, 4, 4)
    return wire.FieldsFrame(sensor_id=sensor, seq=seq, t=float(seq), data=data)


def test_thinning_keeps_every_nth_fields_frame_per_sensor_and_a_channel_subset():
    from tensortouch.runtime.shells.listen import Thinning, parse_channels

    chans = parse_channels("fn_z,displacement")
    assert chans == ("disp_x", "disp_y", "disp_z", "fn_z")            # model order, modality expanded
    thin = Thinning(3, chans)
    kept = [thin("fields", _fields(s, i)) for i in range(7) for s in ("a", "b")]
    assert [(m.sensor_id, m.seq) for m in kept if m is not None] == [("a", 0), ("b", 0), ("a", 3), ("b", 3),
                                                                      ("a", 6), ("b", 6)]
    m = next(m for m in kept if m is not None)
    assert m.channels == chans and m.units == ("mm", "mm", "mm", "MPa") and m.data.shape == (4, 4, 4)
    np.testing.assert_array_equal(m.data[3], _fields().data[CHANNELS.index("fn_z")])
    assert thin("wrench", "w") == "w"                                  # the other streams pass
    for bad in ("fn_q", ",", ""):
        with pytest.raises(Exception, match="--channels"):
            parse_channels(bad)


def test_rate_meter_warns_once_with_the_rate():
    from tensortouch.runtime.shells.listen import RateMeter

    meter = RateMeter(warn_mb_s=1.0, after_s=2.0)
    big = wire.FieldsFrame(sensor_id="d", seq=0, t=0.0, data=np.zeros((15, 128, 128), np.float32))   # 983 kB
    lines = [meter.add("fields", big, t / 30) for t in range(121)]     # 30 frames/s for 4 s
    warned = [x for x in lines if x]
    # at 2 s: 60 frames after the first x 0.983 MB / 2 s = 29.5 MB/s, 106 GB per hour
    assert len(warned) == 1 and "29.5 MB/s (106.2 GB per hour)" in warned[0] and "--fields-every" in warned[0]
    quiet = RateMeter(warn_mb_s=1.0, after_s=2.0)
    assert not any(quiet.add("fields", big, t) for t in range(10))     # 1 frame/s: 0.98 MB/s


def test_listen_saves_thinned_fields_from_a_running_sensor(running_sensor, tmp_path, capsys):
    args = parse(["listen", "dome01", "--connect", running_sensor, "--kinds", "fields", "--count", "4",
                  "--timeout", "20", "--fields-every", "3", "--channels", "disp_z,fn_z", "--save", str(tmp_path)])
    assert args.func(args) == 0
    lines = capsys.readouterr().out.splitlines()
    assert len(lines) == 4 and all("2x16x16 float32" in x for x in lines)
    npys = sorted((tmp_path / "dome01" / "fields").glob("*.npy"))
    seqs = [int(p.stem) for p in npys]
    assert len(seqs) == 4 and all(b - a == 3 for a, b in zip(seqs, seqs[1:])), seqs   # every 3rd of a steady stream
    assert np.load(npys[0]).shape == (2, 16, 16)
    meta = json.loads((tmp_path / "dome01" / "fields" / "meta.json").read_text())
    assert meta["channels"] == ["disp_z", "fn_z"] and meta["units"] == ["mm", "MPa"]
