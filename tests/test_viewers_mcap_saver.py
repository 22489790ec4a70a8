"""`tensortouch listen --save out.mcap`: MCAP with Foxglove's schemas, read back with the `mcap` reader
and the protobuf descriptors stored in the file itself."""
import json

import numpy as np
import pytest

pytest.importorskip("foxglove")
mcap_reader = pytest.importorskip("mcap.reader")

from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
from tensortouch.contracts import wire
from tensortouch.tools.viewers.mcap_saver import McapSaver

from tests import test_listen
from tests.test_listen import CONTACT
from tests.viewers_util import listen_save

sensor_fixture = test_listen.running_sensor          # a publisher on loopback (its endpoint)


def read_mcap(path):
    """{topic: [(schema name, encoding, decoded message)]} with protobuf decoded from the file's schemas."""
    out = {}
    classes = {}
    with open(path, "rb") as fh:
        for schema, channel, message in mcap_reader.make_reader(fh).iter_messages():
            if schema.encoding == "protobuf":
                if schema.name not in classes:
                    pool = descriptor_pool.DescriptorPool()
                    fds = descriptor_pb2.FileDescriptorSet.FromString(schema.data)
                    for f in fds.file:
                        pool.Add(f)
                    classes[schema.name] = message_factory.GetMessageClass(pool.FindMessageTypeByName(schema.name))
                msg = classes[schema.name].FromString(message.data)
            else:
                msg = json.loads(message.data)
            out.setdefault(channel.topic, []).append((schema.name, schema.encoding, msg))
    return out


def frames():
    fields = np.linspace(-1, 1, 15 * 8 * 6, dtype=np.float32).reshape(15, 8, 6)
    payload, att, _ = wire.encode_fields(fields, 5, 12.5, "dome01")
    return (wire.decode_fields(payload, att),
            wire.decode_contacts(wire.encode_contacts([CONTACT], 5, 12.5, "dome01")),
            wire.decode_wrench(wire.encode_wrench((0, 0.1, -1.0), (1.0, 2.0, 0.0), 5, 12.5, "dome01")),
            wire.decode_status(wire.encode_status({"state": "contact", "fps": 50.0}, 5, 12.5, "dome01")))


def test_mcap_schemas_and_values(tmp_path):
    f, c, w, s = frames()
    saver = McapSaver(tmp_path / "rec.mcap")
    for kind, msg in (("fields", f), ("contacts", c), ("wrench", w), ("status", s)):
        saver.save(kind, msg)
    assert not (tmp_path / "rec.mcap").exists()                  # written as .partial until closed
    saver.close()
    got = read_mcap(tmp_path / "rec.mcap")
    base = "/tensortouch/dome01"
    assert got[f"{base}/fields/fn_z"][0][0] == "foxglove.RawImage"
    assert got[f"{base}/contacts"][0][0] == "foxglove.PointCloud"
    assert got[f"{base}/contact_arrows"][0][0] == "foxglove.SceneUpdate"
    assert got[f"{base}/wrench"][0][:2] == ("tensortouch.wrench.v1", "jsonschema")
    assert got[f"{base}/status"][0][2]["state"] == "contact"
    assert len([t for t in got if t.startswith(f"{base}/fields/")]) == 15
    img = got[f"{base}/fields/fn_z"][0][2]
    assert (img.width, img.height, img.encoding, img.step, img.frame_id) == (6, 8, "32FC1", 24, "dome01_gel")
    np.testing.assert_array_equal(np.frombuffer(img.data, "<f4").reshape(8, 6), f.channel("fn_z"))
    assert img.timestamp.seconds == 12 and img.timestamp.nanos == 500_000_000
    pc = got[f"{base}/contacts"][0][2]
    names = [fl.name for fl in pc.fields]
    pts = np.frombuffer(pc.data, "<f4").reshape(-1, pc.point_stride // 4)
    row = dict(zip(names, pts[0]))
    assert row["x"] == pytest.approx(2e-3) and row["z"] == pytest.approx(0.014)     # m
    assert row["fz"] == pytest.approx(-1.0) and row["force"] == pytest.approx(1.005)  # N
    assert row["area"] == pytest.approx(5.25) and row["id"] == 3
    arrow = got[f"{base}/contact_arrows"][0][2].entities[0].arrows[0]
    fmag = float(np.linalg.norm(CONTACT.force_n))
    assert arrow.shaft_length + arrow.head_length == pytest.approx(0.01 * fmag, rel=1e-6)   # 10 mm per N
    # the arrow (+x of its pose) points along the force and ends at the contact
    q = arrow.pose.orientation
    x_axis = np.array([1 - 2 * (q.y**2 + q.z**2), 2 * (q.x * q.y + q.w * q.z), 2 * (q.x * q.z - q.w * q.y)])
    np.testing.assert_allclose(x_axis, np.array(CONTACT.force_n) / fmag, atol=1e-6)
    tip = np.array([arrow.pose.position.x, arrow.pose.position.y, arrow.pose.position.z]) + x_axis * 0.01 * fmag
    np.testing.assert_allclose(tip, np.array(CONTACT.position_mm) * 1e-3, atol=1e-7)
    assert got[f"{base}/wrench"][0][2]["torque_nmm"] == [1.0, 2.0, 0.0]


def test_listen_save_mcap_from_a_running_sensor(sensor_fixture, tmp_path):
    out = tmp_path / "out.mcap"
    r = listen_save(sensor_fixture, out, tmp_path / "site")
    assert r.returncode == 0, r.stderr[-2000:]
    got = read_mcap(out)
    kinds = {t.rsplit("/", 1)[-1] for t in got}
    assert {"fn_z", "contacts", "contact_arrows", "wrench", "status"} <= kinds, sorted(got)
    assert all(m[0] == "foxglove.RawImage" for t, v in got.items() if "/fields/" in t for m in v)


def test_listen_save_mcap_without_the_extra_says_how_to_get_it(tmp_path):
    from importlib import metadata

    from tensortouch.contracts.errors import CommandError
    from tensortouch.runtime.shells.listen import SAVER_GROUP, open_saver

    if any(ep.name == "rrd" for ep in metadata.entry_points(group=SAVER_GROUP)):
        pytest.skip("the viewers extra is installed here")
    with pytest.raises(CommandError, match=r"viewers extra"):
        open_saver(tmp_path / "x.rrd")
    assert open_saver(tmp_path / "folder").__class__.__name__ == "Saver"
