"""The fast wire encoders against the rule written the plain way: the same bytes.

encode_fields builds its JSON header from cached pieces and converts through OpenCV; encode_wrench
dumps its plain members directly. Each is compared here with numpy's float16 cast and json.dumps of
the whole header / body (wire_keys.dumps for the wrench), on varied values."""
import json
import math

import numpy as np
import pytest
from tensortouch.contracts import wire, wire_keys
from tensortouch.contracts.fields import CHANNEL_UNITS, CHANNELS


def plain_encode_fields(fields, seq, t, sensor_id, channels=CHANNELS, units=CHANNEL_UNITS):
    """encode_fields the plain way: numpy's cast, ±inf clipped to ±65504, the header as one json.dumps."""
    arr = np.asarray(fields)
    with np.errstate(over="ignore", invalid="ignore"):
        half = arr.astype(np.float16)
    bits = half.view(np.uint16)
    if np.isnan(half).any():
        raise wire.WireError("NaN")
    over = np.isinf(half)
    clipped = tuple(n for n, b in zip(channels, over.reshape(len(channels), -1).any(axis=1)) if b)
    bits[over] = (bits[over] & 0x8000) | 0x7BFF
    header = {"schema": wire.SCHEMAS["fields"], "sensor_id": sensor_id, "seq": int(seq), "t": float(t),
              "shape": list(arr.shape), "dtype": "<f2", "channels": list(channels), "units": list(units),
              "clipped": list(clipped)}
    return half.tobytes(), json.dumps(header, separators=(",", ":")).encode(), clipped


def _fields(rng, shape=(15, 12, 10)):
    scale = 10.0 ** rng.integers(-9, 6, shape[0])[:, None, None]
    return (rng.standard_normal(shape) * scale).astype(np.float32)


@pytest.mark.parametrize("seed", range(6))
def test_encode_fields_same_bytes_as_the_plain_rule(seed):
    rng = np.random.default_rng(seed)
    f = _fields(rng)
    f[0, 0, :4] = [0.0, -0.0, 65519.0, -65520.0]          # signed zeros, the last value kept, the first clipped
    if seed % 2:
        f[3, 1, 1] = np.inf
        f[7, 2, 2] = -1e9
    seqs = [0, 1, 2**63 - 1, np.int64(17), np.uint32(5)]
    ts = [0.0, -0.0, 0.1, 1e-300, 1e16, 123456.789012345, np.float32(0.3), np.float64(2.5), 3]
    for seq in seqs:
        for t in ts:
            assert wire.encode_fields(f, seq, t, "s-1") == plain_encode_fields(f, seq, t, "s-1")


def test_encode_fields_header_with_other_channels_shape_and_sensor():
    rng = np.random.default_rng(9)
    f = _fields(rng, (2, 3, 5))
    chans, units = ("a\"b", "ü"), ("µm", "N/mm²")                 # escaping as json.dumps does it
    for sid in ("A", "finger.2", "x_y-z"):
        got = wire.encode_fields(f, 3, 1.25, sid, chans, units)
        assert got == plain_encode_fields(f, 3, 1.25, sid, chans, units)
    f[1, 0, 0] = -np.inf
    assert wire.encode_fields(f, 3, 1.25, "A", chans, units)[1:] == plain_encode_fields(f, 3, 1.25, "A", chans, units)[1:]


def test_encode_fields_header_hand_worked():
    f = np.zeros((1, 1, 2), np.float32)
    f[0, 0, 1] = 7e4                                               # beyond 65504: clipped
    payload, header, clipped = wire.encode_fields(f, 42, 0.5, "s", ("u_x",), ("mm",))
    assert payload == bytes([0x00, 0x00, 0xFF, 0x7B]) and clipped == ("u_x",)
    assert header == (b'{"schema":"tensortouch.fields.v1","sensor_id":"s","seq":42,"t":0.5,"shape":[1,1,2],'
                      b'"dtype":"<f2","channels":["u_x"],"units":["mm"],"clipped":["u_x"]}')


def test_encode_fields_refusals_unchanged():
    f = np.zeros((15, 2, 2), np.float32)
    with pytest.raises(wire.WireError, match="non-finite number inf"):
        wire.encode_fields(f, 1, math.inf, "s")
    with pytest.raises(wire.WireError, match="sensor id"):
        wire.encode_fields(f, 1, math.nan, "bad/id")           # the id is judged first, as before
    f[4, 1, 0] = np.nan
    with pytest.raises(wire.WireError, match="NaN in channel"):
        wire.encode_fields(f, 1, 0.0, "s")


def test_to_float16_same_bits_as_numpy_at_every_rounding_boundary():
    """Every float32 exponent and sign, with mantissas around float16's rounding points (the 13 dropped
    bits at 0, 1, half - 1, half, half + 1, all ones) and the kept bits at every other value, against numpy."""
    high = np.arange(0, 2**32, 2**13, dtype=np.uint64)
    low = np.array([0, 1, 0x0FFF, 0x1000, 0x1001, 0x1FFF], dtype=np.uint64)
    x = (high[:, None] | low[None, :]).astype(np.uint32).view(np.float32).reshape(-1, 64)
    with np.errstate(over="ignore", invalid="ignore"):
        ref = x.astype(np.float16).view(np.uint16)
    got = wire.to_float16(x).view(np.uint16)
    nan = np.isnan(x)
    assert np.array_equal(got[~nan], ref[~nan])
    assert ((got[nan] & 0x7FFF) > 0x7C00).all()                   # NaN stays NaN (payload bits aside)


def test_to_float16_keeps_shape_and_layout():
    x = np.arange(24, dtype=np.float32).reshape(2, 3, 4)[:, ::-1]  # not contiguous
    got = wire.to_float16(x)
    assert got.shape == (2, 3, 4) and got.dtype == np.float16
    assert np.array_equal(got, x.astype(np.float16))
    assert np.array_equal(wire.to_float16(np.float32([1.5, -2.0])), np.float16([1.5, -2.0]))


@pytest.mark.parametrize("force,torque,seq,t", [
    ((0.0, -0.0, 1.0), (1e-300, 2.5, -3.25), 1, 0.1),
    (np.array([0.1, 0.2, 0.3]), np.array([1e6, -1e-6, 7.0], np.float32), np.int64(9), np.float32(0.7)),
    ([1, 2, 3], (np.float64(4), np.int32(5), 6.0), 2**63 - 1, 12),
])
def test_encode_wrench_same_bytes_as_the_plain_rule(force, torque, seq, t):
    ref = wire_keys.dumps({"schema": wire.SCHEMAS["wrench"], "sensor_id": "s-1", "seq": int(seq), "t": float(t),
                           "frame": "gel", "force_n": [float(v) for v in force],
                           "torque_nmm": [float(v) for v in torque]})
    assert wire.encode_wrench(force, torque, seq, t, "s-1") == ref


@pytest.mark.parametrize("force,torque,t,bad", [
    ((0, 0, 0), (0, 0, 0), math.nan, "nan"),
    ((math.inf, 0, 0), (0, 0, 0), math.nan, "nan"),                # t comes before the force
    ((0, math.inf, 0), (0, math.nan, 0), 1.0, "inf"),           # the first non-finite, in member order
    ((0, 0, 0), (0, 0, -math.inf), 1.0, "-inf"),
])
def test_encode_wrench_refuses_the_first_non_finite_number_as_before(force, torque, t, bad):
    with pytest.raises(wire.WireError) as new:
        wire.encode_wrench(force, torque, 1, t, "s")
    with pytest.raises(wire.WireError) as old:
        wire_keys.dumps({"t": float(t), "force_n": list(map(float, force)), "torque_nmm": list(map(float, torque))})
    assert str(new.value) == str(old.value) == f"non-finite number {bad} cannot be sent as JSON"
