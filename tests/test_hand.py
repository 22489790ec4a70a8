"""A whole hand in one process: config parsing, N sensors over one real Zenoh session, CAN summary."""
import time
import uuid

import numpy as np
import pytest
from tensortouch.contracts.errors import TensorTouchError
from tensortouch.runtime.apps.hand import Hand
from tensortouch.runtime.apps.subscriber import Subscriber, alive_sensors, query_info
from tensortouch.runtime.shells.hand_cli import register_hand

from tests.hand_util import hand_cfg, make_package, make_store, make_video, wait_until

SERIALS = ("TT-A", "TT-B", "TT-C")


@pytest.fixture(scope="module")
def rig(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("hand")
    pkg = make_package(tmp / "models" / "difference-32")
    make_store(tmp / "store", SERIALS)
    videos = {s: make_video(tmp / f"{s}.avi", seed=i, dx=25.0 - 20 * i) for i, s in enumerate(SERIALS)}
    return tmp, pkg, videos


def test_missing_calibration_stops_with_clear_message(rig):
    tmp, pkg, videos = rig
    cfg = hand_cfg(tmp, pkg, {"TT-A": f"file:{videos['TT-A']}", "TT-NOPE": f"file:{videos['TT-B']}"})
    with pytest.raises(TensorTouchError, match="finger 'f1' \\(sensor TT-NOPE\\).*no calibration"):
        Hand(cfg)


def test_three_fingers_publish_independently_with_can_summary(rig):
    can = pytest.importorskip("can")
    tmp, pkg, videos = rig
    channel = f"hand-{uuid.uuid4().hex[:8]}"
    cfg = hand_cfg(tmp, pkg, {s: f"file:{videos[s]}" for s in SERIALS},
                   can={"interface": "virtual", "channel": channel, "id_base": 0x320, "rate_hz": 100})
    rx = can.Bus(interface="virtual", channel=channel)
    contacts = {s: [] for s in SERIALS}
    statuses = {s: [] for s in SERIALS}
    with Hand(cfg) as hand, Subscriber("*", connect=list(cfg.listen),
                                       on_contacts=lambda m: contacts[m.sensor_id].append(m),
                                       on_status=lambda m: statuses[m["sensor_id"]].append(m)) as sub:
        assert wait_until(lambda: set(alive_sensors(sub, 0.5)) == set(SERIALS), 10)
        assert wait_until(lambda: all(any(m.contacts for m in contacts[s]) for s in SERIALS), 20), \
            {s: len(v) for s, v in contacts.items()}
        info = query_info(sub, "TT-B")
        assert info["finger"] == "f1" and info["hand"] == "test-hand" and info["can_slot"] == 1
        # every running status names its finger (wire status member `finger`, docs/wire.md)
        assert wait_until(lambda: all(statuses[s] for s in SERIALS), 5)
        for i, s in enumerate(SERIALS):
            assert {(m["finger"], m["hand"]) for m in statuses[s]} == {(f"f{i}", "test-hand")}, s
        from tensortouch.runtime.shells.listen import format_line

        assert " finger=f1 state=" in format_line("status", statuses["TT-B"][-1])   # `tensortouch listen`
        fields = sub.wait_for("fields", 5.0)
        assert fields.data.shape == (15, 32, 32)
        from tensortouch.contracts.can_frame import SummaryDecoder

        dec = SummaryDecoder(0x320, 3)
        seen_contact = set()
        t0 = time.monotonic()
        while time.monotonic() - t0 < 4.0 and len(seen_contact) < 3:
            m = rx.recv(0.1)
            if m is not None and dec.feed(m.arbitration_id, m.data) is not None:
                for slot, s in dec.fingers.items():
                    if s.count:
                        seen_contact.add(slot)
        summ = hand.summary()
    rx.shutdown()
    assert seen_contact == {0, 1, 2}
    assert all(s.has("alive") for s in dec.fingers.values())
    # each finger pressed at its own place: strongest-contact x positions differ in the CAN summary
    # (dx = +25, +5, -15 px from the gel centre) and agree in sign with the Zenoh contacts
    for i, s in enumerate(SERIALS):
        last = [c for m in contacts[s] for c in m.contacts]
        assert last, s
        assert summ[f"f{i}"]["frames"] > 30 and summ[f"f{i}"]["state"] == "running"
    xs = [np.median([c.position_mm[0] for m in contacts[s] for c in m.contacts]) for s in SERIALS]
    assert xs[0] > xs[1] > xs[2], xs


def test_shared_model_session_and_independent_baselines(rig):
    tmp, pkg, videos = rig
    cfg = hand_cfg(tmp, pkg, {s: f"file:{videos[s]}" for s in SERIALS[:2]}, share_model=True)
    hand = Hand(cfg)
    try:
        a, b = (hand.fingers[n].pipeline for n in ("f0", "f1"))
        assert a.model is b.model and len(hand.models) == 1
        assert a.baseline is not b.baseline and a.cal is not b.cal
    finally:
        hand.stop()
    cfg = hand_cfg(tmp, pkg, {s: f"file:{videos[s]}" for s in SERIALS[:2]}, share_model=False)
    hand = Hand(cfg)
    try:
        a, b = (hand.fingers[n].pipeline for n in ("f0", "f1"))
        assert a.model.inner is not b.model.inner and len(hand.models) == 2
        assert a.model.gate is b.model.gate               # one inference gate for the whole hand
    finally:
        hand.stop()


def test_starting_a_hand_sets_opencv_threads_for_the_process(rig):
    import cv2

    tmp, pkg, videos = rig
    before = cv2.getNumThreads()
    cv2.setNumThreads(2)
    try:
        hand = Hand(hand_cfg(tmp, pkg, {SERIALS[0]: f"file:{videos[SERIALS[0]]}"}, opencv_threads=1)).start()
        try:
            assert cv2.getNumThreads() == 1
        finally:
            hand.stop()
    finally:
        cv2.setNumThreads(before)


def test_hand_fields_every_reaches_each_fingers_loop(rig):
    """hand.fields_every = 3 is each finger's LoopConfig.fields_every (the loop's thinning itself:
    tests/test_runtime_speed.py)."""
    tmp, pkg, videos = rig
    hand = Hand(hand_cfg(tmp, pkg, {SERIALS[0]: f"file:{videos[SERIALS[0]]}"}, fields_every=3)).start()
    try:
        finger = next(iter(hand.fingers.values()))
        assert wait_until(lambda: finger.loop is not None and finger.loop.frames >= 3, 60)
        assert finger.loop.cfg.fields_every == 3
    finally:
        hand.stop()


def test_finite_replays_end_and_cli_runs(rig, capsys):
    import argparse

    tmp, pkg, videos = rig
    toml = tmp / "cli_hand.toml"
    toml.write_text(f"""
[hand]
name = "cli"
model = "{pkg}"
calibration_store = "{tmp / 'store'}"
[zenoh]
listen = ["tcp/127.0.0.1:0"]
[[finger]]
name = "a"
serial = "TT-A"
source = "file:{videos['TT-A']}"
[[finger]]
name = "b"
serial = "TT-B"
source = "file:{videos['TT-B']}"
""")
    parser = argparse.ArgumentParser()
    register_hand(parser.add_subparsers())
    args = parser.parse_args(["hand", str(toml), "--fast", "--duration", "60"])
    t0 = time.monotonic()
    assert args.func(args) == 0
    assert time.monotonic() - t0 < 60
    err = capsys.readouterr().err
    assert "2 finger(s)" in err
    assert err.count(" ended ") == 2 and "    90 frames" in err


