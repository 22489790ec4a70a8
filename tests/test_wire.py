"""Pure wire-format encode/decode (contracts/wire.py): no network."""
import json

import numpy as np
import pytest
from tensortouch.contracts import wire
from tensortouch.contracts.errors import TensorTouchError
from tensortouch.contracts.fields import CHANNEL_UNITS, CHANNELS


def make_contact(i=1, f=(0.1, -0.2, -1.5), p=(1.0, 2.0, 14.0)):
    return wire.Contact(id=i, uv_px=(64.5, 60.25), position_mm=p, normal=(0.0, 0.0, 1.0),
                        area_mm2=3.5, force_n=f, force_mag_n=float(np.linalg.norm(f)),
                        perimeter_px=21.0, circularity=0.87, priority=1.5, age_frames=7)


def test_keys_and_parse():
    assert wire.key("dome01", "fields") == "tensortouch/dome01/fields"
    assert wire.alive_key("dome01") == "tensortouch/dome01/alive"
    assert wire.info_key("dome01") == "tensortouch/dome01/info"
    assert wire.key("*", "*") == "tensortouch/*/*"
    assert wire.parse_key("tensortouch/dome01/status") == ("dome01", "status")
    for bad in ("", "a/b", "a*", "$x", "a b", "-x"):
        with pytest.raises(wire.WireError, match="sensor id"):
            wire.key(bad, "fields")
    with pytest.raises(wire.WireError):
        wire.key("dome01", "nope")
    with pytest.raises(wire.WireError):
        wire.parse_key("other/dome01/fields")
    assert issubclass(wire.WireError, TensorTouchError)


def test_fields_round_trip_exact_for_half_values():
    rng = np.random.default_rng(0)
    f = rng.normal(scale=2.0, size=(15, 32, 48)).astype(np.float32)
    payload, att, clipped = wire.encode_fields(f, seq=42, t=12.5, sensor_id="dome01")
    assert isinstance(payload, bytes) and isinstance(att, bytes)
    assert len(payload) == 15 * 32 * 48 * 2 and clipped == ()
    # byte layout: little-endian float16, C-order (C, H, W)
    raw = np.frombuffer(payload, dtype="<f2").reshape(15, 32, 48)
    assert raw[3, 5, 7] == np.float16(f[3, 5, 7])
    head = json.loads(att)
    assert head["schema"] == "tensortouch.fields.v1" and head["shape"] == [15, 32, 48]
    assert head["channels"] == list(CHANNELS) and head["units"] == list(CHANNEL_UNITS)
    fr = wire.decode_fields(payload, att, wire.ENCODINGS["fields"])
    assert fr.sensor_id == "dome01" and fr.seq == 42 and fr.t == 12.5
    assert fr.data.dtype == np.float32 and fr.data.shape == (15, 32, 48)
    np.testing.assert_array_equal(fr.data, f.astype(np.float16).astype(np.float32))
    # half precision: relative error <= 2^-11 for normal numbers
    big = np.abs(f) > 1e-3
    assert np.max(np.abs(fr.data[big] - f[big]) / np.abs(f[big])) <= 2.0 ** -11
    assert fr.channels == CHANNELS and fr.units == CHANNEL_UNITS
    np.testing.assert_array_equal(fr.channel("sigma_zz"), fr.data[5])
    with pytest.raises(wire.WireError, match="no channel"):
        fr.channel("temperature")


def test_fields_overflow_clipped_and_flagged():
    f = np.zeros((15, 4, 4), np.float32)
    f[4, 0, 0] = 1e6
    f[10, 1, 1] = -np.inf
    f[12, 2, 2] = 65000.0          # representable: not clipped
    payload, att, clipped = wire.encode_fields(f, 1, 0.0, "s")
    assert clipped == ("sigma_yy", "fn_y")
    fr = wire.decode_fields(payload, att)
    assert fr.clipped == ("sigma_yy", "fn_y")
    assert fr.data[4, 0, 0] == 65504.0 and fr.data[10, 1, 1] == -65504.0
    assert fr.data[12, 2, 2] == np.float32(np.float16(65000.0))
    assert np.isfinite(fr.data).all()
    f[0, 3, 3] = np.nan            # NaN is not sent: the encoder names the channel
    with pytest.raises(wire.WireError, match="NaN in channel.*disp_x"):
        wire.encode_fields(f, 1, 0.0, "s")


def test_fields_bad_inputs():
    f = np.zeros((15, 8, 8), np.float32)
    payload, att, _ = wire.encode_fields(f, 1, 0.0, "s")
    with pytest.raises(wire.WireError, match="expected 1920"):
        wire.decode_fields(payload[:-2], att)
    with pytest.raises(wire.WireError, match="expected 1920"):
        wire.decode_fields(payload + b"\0\0", att)
    head = json.loads(att)
    wrong = json.dumps({**head, "schema": "tensortouch.fields.v2"}).encode()
    with pytest.raises(wire.WireError, match="tensortouch.fields.v2.*expected 'tensortouch.fields.v1'"):
        wire.decode_fields(payload, wrong)
    with pytest.raises(wire.WireError, match="schema"):
        wire.decode_fields(payload, att, "application/octet-stream;tensortouch.contacts.v1")
    with pytest.raises(wire.WireError, match="schema None"):
        wire.decode_fields(payload, att, "application/octet-stream")
    with pytest.raises(wire.WireError, match="missing attachment"):
        wire.decode_fields(payload, None)
    with pytest.raises(wire.WireError, match="JSON"):
        wire.decode_fields(payload, b"\xff\x00garbage")
    with pytest.raises(wire.WireError, match="shape"):
        wire.decode_fields(payload, json.dumps({**head, "shape": [14, 8, 8]}).encode())
    with pytest.raises(wire.WireError, match="missing field 'seq'"):
        wire.decode_fields(payload, json.dumps({k: v for k, v in head.items() if k != "seq"}).encode())
    with pytest.raises(wire.WireError, match="expected shape"):
        wire.encode_fields(np.zeros((14, 8, 8)), 1, 0.0, "s")
    with pytest.raises(wire.WireError, match="expected shape"):
        wire.encode_fields(np.zeros((8, 8)), 1, 0.0, "s")


def test_contacts_round_trip_and_validation():
    cs = [make_contact(1), make_contact(2, f=(0.0, 0.0, -0.4), p=(-3.0, 0.5, 13.0))]
    payload = wire.encode_contacts(cs, seq=7, t=1.25, sensor_id="dome01")
    obj = json.loads(payload)
    assert obj["schema"] == "tensortouch.contacts.v1" and len(obj["contacts"]) == 2
    fr = wire.decode_contacts(payload, wire.ENCODINGS["contacts"])
    assert fr.sensor_id == "dome01" and fr.seq == 7 and fr.t == 1.25
    assert fr.contacts == cs
    assert wire.Contact.from_dict(cs[0].to_dict()) == cs[0]
    # numpy values are accepted by the encoder
    c = make_contact(3, f=np.array([0.1, 0.2, 0.3], np.float32), p=np.array([1, 2, 3.0]))
    assert wire.decode_contacts(wire.encode_contacts([c], 1, 0.0, "s")).contacts[0].force_n == \
        pytest.approx((0.1, 0.2, 0.3), rel=1e-6)
    assert wire.decode_contacts(wire.encode_contacts([], 1, 0.0, "s")).contacts == []
    with pytest.raises(wire.WireError, match="non-finite"):
        wire.encode_contacts([make_contact(f=(np.nan, 0, 0))], 1, 0.0, "s")
    bad = dict(cs[0].to_dict())
    del bad["area_mm2"]
    with pytest.raises(wire.WireError, match="area_mm2"):
        wire.Contact.from_dict(bad)
    with pytest.raises(wire.WireError, match="force_n"):
        wire.Contact.from_dict({**cs[0].to_dict(), "force_n": [1, 2]})
    wrong = json.dumps({**obj, "schema": "tensortouch.wrench.v1"})
    with pytest.raises(wire.WireError, match="expected 'tensortouch.contacts.v1'"):
        wire.decode_contacts(wrong)
    with pytest.raises(wire.WireError, match="JSON object"):
        wire.decode_contacts(b"[1, 2]")


def test_wrench_from_contacts_and_round_trip():
    cs = [make_contact(1, f=(0.0, 0.0, -1.0), p=(2.0, 0.0, 10.0)),
          make_contact(2, f=(0.5, 0.0, 0.0), p=(0.0, 0.0, 14.0))]
    force, torque = wire.wrench_from_contacts(cs)
    np.testing.assert_allclose(force, [0.5, 0.0, -1.0])
    # tau = sum p x f: (2,0,10)x(0,0,-1) = (0,2,0); (0,0,14)x(0.5,0,0) = (0,7,0)
    np.testing.assert_allclose(torque, [0.0, 9.0, 0.0])
    w = wire.decode_wrench(wire.encode_wrench(force, torque, 5, 2.0, "dome01"), wire.ENCODINGS["wrench"])
    assert w.force_n == (0.5, 0.0, -1.0) and w.torque_nmm == (0.0, 9.0, 0.0)
    assert (w.sensor_id, w.seq, w.t) == ("dome01", 5, 2.0)
    with pytest.raises(wire.WireError, match="torque_nmm"):
        wire.encode_wrench(force, [1.0, 2.0], 5, 2.0, "s")
    with pytest.raises(wire.WireError, match="schema"):
        wire.decode_wrench(wire.encode_wrench(force, torque, 5, 2.0, "s"),
                           "application/json;tensortouch.status.v1")


def test_status_round_trip_and_sanitizing():
    st = {"state": "contact", "flags": ["frame_black", "camera_stalled", "frame_black"],
          "fps": float("nan"), "timings_ms": {"capture": 1.5, "infer": np.float32(8.25)},
          "model_hash": "sha256:ab", "calibration_version": 3, "extra": {"x": 1}}
    d = wire.decode_status(wire.encode_status(st, 9, 3.5, "dome01"), wire.ENCODINGS["status"])
    assert d["schema"] == "tensortouch.status.v1" and d["sensor_id"] == "dome01"
    assert d["flags"] == ["camera_stalled", "frame_black"]
    assert d["fps"] is None and d["timings_ms"] == {"capture": 1.5, "infer": 8.25}
    assert d["seq"] == 9 and d["t"] == 3.5 and d["extra"] == {"x": 1}
    minimal = wire.decode_status(wire.encode_status({}, 1, 0.0, "s"))
    assert minimal["state"] is None and minimal["flags"] == [] and minimal["timings_ms"] == {}
    with pytest.raises(wire.WireError, match="missing field 'timings_ms'"):
        wire.decode_status(json.dumps({"schema": "tensortouch.status.v1", "sensor_id": "s",
                                       "seq": 1, "t": 0, "state": "x", "flags": []}))


def test_info_round_trip():
    info = {"model": {"name": "hiera-s", "hash": "sha256:1"}, "calibration_version": 2,
            "bounds": {"disp_x": [-1.0, 1.0]}}
    d = wire.decode_info(wire.encode_info(info, "dome01", "0.1.0"), wire.ENCODINGS["info"])
    assert d["model"]["hash"] == "sha256:1" and d["bounds"]["disp_x"] == [-1.0, 1.0]
    assert d["channels"] == list(CHANNELS) and d["units"] == list(CHANNEL_UNITS)
    assert d["keys"]["fields"] == "tensortouch/dome01/fields" and d["wire_version"] == 1
    assert d["runtime_version"] == "0.1.0"


# ---------------------------------------------------------------------------- non-finite numbers received

def _forged_fields(value):
    """A fields message a hostile or broken sender built by hand, with `value` at one pixel."""
    data = np.zeros((15, 4, 4), np.float16)
    data[7, 1, 2] = value
    head = {"schema": "tensortouch.fields.v1", "sensor_id": "s", "seq": 1, "t": 0.5, "shape": [15, 4, 4],
            "dtype": "<f2", "channels": list(CHANNELS), "units": list(CHANNEL_UNITS), "clipped": []}
    return data.tobytes(), json.dumps(head).encode()


@pytest.mark.parametrize("value", [np.nan, np.inf, -np.inf])
def test_fields_with_a_non_finite_value_are_refused_by_the_decoder(value):
    with pytest.raises(wire.NonFiniteError, match="1 non-finite"):
        wire.decode_fields(*_forged_fields(value))
    assert np.isfinite(wire.decode_fields(*_forged_fields(65504.0)).data).all()


CONTACT = make_contact(1).to_dict()
TEXT_CONTACT = json.dumps({"schema": "tensortouch.contacts.v1", "sensor_id": "s", "seq": 3, "t": 1.0,
                           "contacts": [CONTACT]})
TEXT_WRENCH = ('{"schema":"tensortouch.wrench.v1","sensor_id":"s","seq":3,"t":1.0,"frame":"gel",'
               '"force_n":[0.1,0.2,-0.3],"torque_nmm":[1.0,2.0,3.0]}')


@pytest.mark.parametrize("token", ["NaN", "Infinity", "-Infinity", "1e999", "-1e400", "1" + "0" * 400])
@pytest.mark.parametrize("where", ["force_n", "t", "area_mm2"])
def test_contacts_and_wrench_with_a_non_finite_number_are_refused(token, where):
    """Python's json reads NaN, Infinity and 1e999 as floats; the decoders refuse each of them, wherever
    it stands, with NonFiniteError (the subscriber drops and counts such a message)."""
    num = json.dumps(CONTACT["force_n"][0])
    if where == "force_n":
        contacts = TEXT_CONTACT.replace(f'"force_n": [{num}', f'"force_n": [{token}')
        wrench = TEXT_WRENCH.replace('"force_n":[0.1', f'"force_n":[{token}')
    elif where == "t":
        contacts = TEXT_CONTACT.replace('"t": 1.0', f'"t": {token}')
        wrench = TEXT_WRENCH.replace('"t":1.0', f'"t":{token}')
    else:
        contacts = TEXT_CONTACT.replace(f'"area_mm2": {json.dumps(CONTACT["area_mm2"])}', f'"area_mm2": {token}')
        wrench = TEXT_WRENCH.replace('"torque_nmm":[1.0', f'"torque_nmm":[{token}')
    assert contacts != TEXT_CONTACT and wrench != TEXT_WRENCH
    with pytest.raises(wire.NonFiniteError):
        wire.decode_contacts(contacts)
    with pytest.raises(wire.NonFiniteError):
        wire.decode_wrench(wrench)
    assert wire.decode_contacts(TEXT_CONTACT).contacts[0].force_n == pytest.approx(CONTACT["force_n"])


def test_status_and_info_with_a_non_finite_number_are_refused():
    status = wire.encode_status({"state": "idle", "fps": 30.0}, 1, 0.0, "s").decode()
    with pytest.raises(wire.NonFiniteError):
        wire.decode_status(status.replace("30.0", "NaN"))
    info = wire.encode_info({"bounds": {"disp_x": [-1.0, 1.0]}}, "s", "0").decode()
    with pytest.raises(wire.NonFiniteError):
        wire.decode_info(info.replace("-1.0", "-Infinity"))


@pytest.mark.parametrize("field, value", [("force_n", ["1", 2, 3]), ("force_n", [True, 2, 3]),
                                          ("area_mm2", "nan"), ("id", 1.5), ("id", -1), ("age_frames", "7"),
                                          ("force_mag_n", None)])
def test_contact_numbers_must_be_json_numbers(field, value):
    """float("nan") and float("1") accept strings; the decoder wants JSON numbers of the right kind."""
    with pytest.raises(wire.WireError, match=field):
        wire.Contact.from_dict({**CONTACT, field: value})


def test_fields_beyond_a_receivers_limit_or_of_zero_size_are_refused():
    payload, att, _ = wire.encode_fields(np.zeros((15, 64, 32), np.float32), 1, 0.0, "s")
    assert wire.decode_fields(payload, att, max_shape=(15, 64, 64)).data.shape == (15, 64, 32)
    with pytest.raises(wire.WireError, match=r"exceeds this receiver's limit \(15, 32, 32\)"):
        wire.decode_fields(payload, att, max_shape=(15, 32, 32))
    head = {**json.loads(att), "shape": [15, 0, 0]}
    with pytest.raises(wire.WireError, match="every size >= 1"):
        wire.decode_fields(b"", json.dumps(head).encode())
