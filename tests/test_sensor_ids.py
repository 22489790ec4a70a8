"""One pattern for sensor ids, key chunks and the folders made from them, enforced where ids come in:
the wire decoders, received keys, the command line, and `listen --save` (which also keeps a bounded
number of files open however many ids arrive). The hostile publisher is a real Zenoh session."""
import argparse
import json
import os
import threading
import time

import pytest
import zenoh
from tensortouch.contracts import wire
from tensortouch.contracts.errors import TensorTouchError
from tensortouch.runtime.apps.zenoh_session import zenoh_config
from tensortouch.runtime.shells.listen import Saver, add_listen_parser, run_listen

from tests.test_listen import free_endpoint

BAD_IDS = ["..", ".", ".hidden", "a/b", "a b", "", "x" * 65, "*", "dome<script>", "-lead", "é"]
GOOD_IDS = ["TWIN-DEMO", "dome01", "a", "TT-0001.left_2", "x" * 64]


@pytest.mark.parametrize("bad", BAD_IDS)
def test_bad_ids_are_refused_at_every_entry(bad):
    with pytest.raises(wire.WireError, match="expected"):
        wire.check_sensor_id(bad)
    with pytest.raises(wire.WireError):
        wire.decode_status(json.dumps({"schema": wire.SCHEMAS["status"], "sensor_id": bad, "seq": 1,
                                       "t": 0.0, "state": "stable", "flags": [], "timings_ms": {}}))
    with pytest.raises(wire.WireError):
        wire.decode_wrench(json.dumps({"schema": wire.SCHEMAS["wrench"], "sensor_id": bad, "seq": 1, "t": 0.0,
                                       "frame": "gel", "force_n": [0, 0, 0], "torque_nmm": [0, 0, 0]}))
    if "/" not in bad:
        with pytest.raises(wire.WireError):
            wire.parse_key(f"tensortouch/{bad}/status")
    with pytest.raises(TensorTouchError):
        Saver("/tmp/never-written").save("status", {"sensor_id": bad, "seq": 1})


@pytest.mark.parametrize("good", GOOD_IDS)
def test_good_ids_pass(good):
    assert wire.check_sensor_id(good) == good
    assert wire.parse_key(wire.key(good, "status")) == (good, "status")


def test_listen_rejects_a_bad_id_on_the_command_line():
    parser = argparse.ArgumentParser()
    add_listen_parser(parser.add_subparsers(dest="command"))
    args = parser.parse_args(["listen", "../x", "--connect", free_endpoint(), "--timeout", "1"])
    with pytest.raises(TensorTouchError, match="sensor id"):
        run_listen(args)


def _open_fds() -> int:
    return len(os.listdir("/proc/self/fd"))


def test_saver_keeps_open_files_bounded(tmp_path):
    saver = Saver(tmp_path / "rec", max_open=8)
    before = _open_fds()
    for i in range(300):
        for kind, msg in (("status", {"sensor_id": f"fake{i}", "seq": 1}),
                          ("wrench", wire.Wrench(f"fake{i}", 1, 0.0, (0, 0, 1), (0, 0, 0)))):
            saver.save(kind, msg)
    assert _open_fds() - before <= 8
    saver.save("status", {"sensor_id": "fake0", "seq": 2})           # reopened, appended
    saver.close()
    assert (tmp_path / "rec" / "fake0" / "status.jsonl").read_text().count("\n") == 2
    assert len(list((tmp_path / "rec").iterdir())) == 300
    assert sorted(p.name for p in tmp_path.iterdir()) == ["rec"]


def test_hostile_publisher_cannot_make_listen_save_outside_dir(tmp_path):
    """A real Zenoh peer publishes status messages under bad ids (in the key and in the payload)
    next to a genuine one; `listen --save DIR` saves the genuine one and nothing outside DIR."""
    ep = free_endpoint()
    session = zenoh.open(zenoh_config(listen=[ep]))
    stop = threading.Event()
    enc = zenoh.Encoding(wire.ENCODINGS["status"])

    def status(sensor_id, seq):
        return json.dumps({"schema": wire.SCHEMAS["status"], "sensor_id": sensor_id, "seq": seq, "t": 0.0,
                           "state": "stable", "flags": [], "timings_ms": {}})

    def flood():
        seq = 0
        while not stop.is_set():
            for key_id, body_id in (("..", ".."), ("x", ".."), ("..", "x"), (".hidden", ".hidden")):
                try:
                    session.put(f"tensortouch/{key_id}/status", status(body_id, seq), encoding=enc)
                except zenoh.ZError:
                    pass
            session.put("tensortouch/good1/status", status("good1", seq), encoding=enc)
            seq += 1
            time.sleep(0.02)

    th = threading.Thread(target=flood, daemon=True)
    th.start()
    save = tmp_path / "rec" / "DIR"
    parser = argparse.ArgumentParser()
    add_listen_parser(parser.add_subparsers(dest="command"))
    args = parser.parse_args(["listen", "--connect", ep, "--count", "10", "--timeout", "20", "--save", str(save),
                              "--json"])
    try:
        assert run_listen(args) == 0
    finally:
        stop.set()
        th.join(5)
        session.close()
    assert sorted(p.name for p in save.iterdir()) == ["good1"]
    assert sorted(p.name for p in (tmp_path / "rec").iterdir()) == ["DIR"]
