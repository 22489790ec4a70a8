"""A stand-in for an rmw_zenoh subscriber, run as its own process by tests/test_ros2_e2e.py.

It imports nothing from the project: it knows only rmw_zenoh's conventions. It listens on a Zenoh
endpoint (the place of rmw_zenohd), finds publishers from their `@ros2_lv` liveliness tokens
alone, subscribes to the data keys it derives from those tokens, checks each 33-byte attachment
and decodes every payload with rosbags' CDR deserializer. It also records the runtime's own
`tensortouch/*/{wrench,contacts}` JSON to compare values. Prints one JSON report on stdout.

    python tests/ros2_fake_subscriber.py ENDPOINT DOMAIN TIMEOUT_S TOPICS MIN_MSGS BUSIEST_MSGS

ENDPOINT `connect:tcp/HOST:PORT` connects there instead (an rmw_zenoh node's default, with no router).

It stops once TOPICS publishers were found, each delivered MIN_MSGS messages and the busiest one
BUSIEST_MSGS, or after TIMEOUT_S seconds.
"""
from __future__ import annotations

import json
import struct
import sys
import threading
import time

import numpy as np
import zenoh
from rosbags.typesys import Stores, get_typestore

TS = get_typestore(Stores.ROS2_JAZZY)


def ros_type(dds: str) -> str:
    pkg, kind, _, name = dds.split("::")
    return f"{pkg}/{kind}/{name.rstrip('_')}"


def summarize(rtype: str, msg) -> dict:
    def stamp(h):
        return h.stamp.sec + h.stamp.nanosec * 1e-9
    if rtype == "geometry_msgs/msg/WrenchStamped":
        f, m = msg.wrench.force, msg.wrench.torque
        return {"t": stamp(msg.header), "frame": msg.header.frame_id, "force": [f.x, f.y, f.z],
                "torque": [m.x, m.y, m.z]}
    if rtype == "sensor_msgs/msg/Image":
        a = np.frombuffer(bytes(msg.data), "<f4").reshape(msg.height, msg.width)
        return {"t": stamp(msg.header), "frame": msg.header.frame_id, "shape": [msg.height, msg.width],
                "encoding": msg.encoding, "step": msg.step, "min": float(a.min()), "max": float(a.max())}
    if rtype == "sensor_msgs/msg/PointCloud2":
        names = [f.name for f in msg.fields]
        dt = np.dtype({"names": names, "formats": ["<u4" if f.datatype == 6 else "<f4" for f in msg.fields],
                       "offsets": [f.offset for f in msg.fields], "itemsize": msg.point_step})
        pts = np.frombuffer(bytes(msg.data), dt, count=msg.width)
        return {"t": stamp(msg.header), "frame": msg.header.frame_id, "fields": names, "n": int(msg.width),
                "points": [{n: float(p[n]) for n in names} for p in pts[:5]],
                "z_range": [float(pts["z"].min()), float(pts["z"].max())] if len(pts) else None}
    if rtype == "diagnostic_msgs/msg/DiagnosticArray":
        return {"t": stamp(msg.header), "status": [
            {"level": int(s.level), "name": s.name, "message": s.message, "hardware_id": s.hardware_id,
             "values": {kv.key: kv.value for kv in s.values}} for s in msg.status]}
    if rtype == "tf2_msgs/msg/TFMessage":
        return {"transforms": [{"parent": tr.header.frame_id, "child": tr.child_frame_id,
                                "w": tr.transform.rotation.w} for tr in msg.transforms]}
    return {}


def main() -> int:
    endpoint, domain, timeout = sys.argv[1], sys.argv[2], float(sys.argv[3])
    n_topics, min_msgs, busiest = (int(v) for v in sys.argv[4:7])
    cfg = zenoh.Config()
    cfg.insert_json5("mode", '"peer"')
    cfg.insert_json5("scouting/multicast/enabled", "false")
    if endpoint.startswith("connect:"):      # as an rmw_zenoh node without a router: connect out
        cfg.insert_json5("connect/endpoints", json.dumps([endpoint.removeprefix("connect:")]))
    else:                                    # in the place of rmw_zenohd: listen
        cfg.insert_json5("listen/endpoints", json.dumps([endpoint]))
    session = zenoh.open(cfg)
    lock = threading.Lock()
    report = {"nodes": [], "publishers": {}, "own": {"wrench": [], "contacts": []}, "bad": []}
    subs = []

    def on_data(topic):
        def cb(sample):
            try:
                att = sample.attachment.to_bytes() if sample.attachment is not None else b""
                if len(att) != 33 or att[16] != 16:
                    raise ValueError(f"attachment of {len(att)} bytes")
                seq, t_ns = struct.unpack_from("<qq", att)
                entry = report["publishers"][topic]
                msg = TS.deserialize_cdr(sample.payload.to_bytes(), entry["type"])
                with lock:
                    entry["seqs"].append(seq)
                    entry["gids"].add(att[17:].hex())
                    entry["age_s"].append(time.time() - t_ns * 1e-9)
                    if len(entry["msgs"]) < 400:
                        entry["msgs"].append(summarize(entry["type"], msg))
            except Exception as exc:  # noqa: BLE001 - reported, the test fails on it
                with lock:
                    report["bad"].append(f"{topic}: {type(exc).__name__}: {exc}")
        return cb

    def on_token(sample):
        if sample.kind != zenoh.SampleKind.PUT:
            return
        parts = str(sample.key_expr).split("/")
        if parts[0] != "@ros2_lv" or parts[1] != domain:
            return
        if parts[5] == "NN":
            with lock:
                report["nodes"].append({"zid": parts[2], "namespace": parts[7].replace("%", "/"),
                                        "node": parts[8]})
            return
        if parts[5] != "MP" or len(parts) != 13:
            return
        topic = parts[9].replace("%", "/")
        key = f"{parts[1]}/{topic.strip('/')}/{parts[10]}/{parts[11]}"
        with lock:
            if topic in report["publishers"]:
                return
            report["publishers"][topic] = {"type": ros_type(parts[10]), "hash": parts[11], "qos": parts[12],
                                           "key": key, "token": str(sample.key_expr), "seqs": [],
                                           "gids": set(), "age_s": [], "msgs": []}
        subs.append(session.declare_subscriber(key, on_data(topic)))

    def on_own(kind):
        def cb(sample):
            with lock:
                if len(report["own"][kind]) < 400:
                    report["own"][kind].append(json.loads(sample.payload.to_bytes()))
        return cb

    subs.append(session.declare_subscriber("tensortouch/*/wrench", on_own("wrench")))
    subs.append(session.declare_subscriber("tensortouch/*/contacts", on_own("contacts")))
    tokens = session.liveliness().declare_subscriber(f"@ros2_lv/{domain}/**", on_token, history=True)
    print("ready", flush=True)

    def done():
        with lock:
            counts = [len(p["seqs"]) for p in report["publishers"].values()]
        return len(counts) >= n_topics and min(counts) >= min_msgs and max(counts) >= busiest

    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline and not done():
        time.sleep(0.1)
    with lock:
        for entry in report["publishers"].values():
            entry["gids"] = sorted(entry["gids"])
        out = json.dumps(report)
    tokens.undeclare()
    for s in subs:
        s.undeclare()
    session.close()
    print(out, flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
