"""CAN summary frames (contracts/can_frame.py): layout round trip, scaling, saturation, id range, decoding."""
import numpy as np
import pytest
from tensortouch.contracts.can_frame import (
    FORCE_SCALE_N,
    POSITION_SCALE_MM,
    STATUS_BITS,
    FingerSummary,
    SummaryDecoder,
    check_id_range,
    decode_frames,
    encode_finger,
    frame_ids,
    summary_from_result,
)


def test_round_trip_within_one_lsb():
    s = FingerSummary(3, (1.234, -5.678, 15.01), (0.1234, -0.5, 2.3456), 2.5, {"alive", "contact"}, 7)
    frames = encode_finger(s, 0x300, 2)
    assert [f[0] for f in frames] == list(frame_ids(0x300, 2)) == [0x304, 0x305]
    assert all(len(d) == 8 for _, d in frames)
    got = decode_frames(frames, 0x300, 4)[2]
    assert got.count == 3 and got.counter == 7
    assert got.status == {"alive", "contact"}
    np.testing.assert_allclose(got.position_mm, s.position_mm, atol=POSITION_SCALE_MM / 2 + 1e-9)
    np.testing.assert_allclose(got.force_n, s.force_n, atol=FORCE_SCALE_N / 2 + 1e-9)
    assert abs(got.total_force_n - 2.5) <= FORCE_SCALE_N / 2


def test_documented_byte_layout():
    s = FingerSummary(2, (1.0, -1.0, 0.5), (0.001, -0.002, 1.0), 1.0, {"alive"}, 5)
    (a, da), (b, db) = encode_finger(s, 0x100, 0)
    assert da[0] == 1 << STATUS_BITS["alive"]
    assert da[1] == (2 << 4) | 5
    assert int.from_bytes(da[2:4], "little", signed=True) == 100
    assert int.from_bytes(da[4:6], "little", signed=True) == -100
    assert int.from_bytes(db[0:2], "little", signed=True) == 1
    assert int.from_bytes(db[2:4], "little", signed=True) == -2
    assert int.from_bytes(db[6:8], "little") == 1000


def test_saturation_sets_bit_and_clips():
    s = FingerSummary(40, (400.0, 0, 0), (50.0, float("nan"), 0), 100.0, {"alive"})
    got = decode_frames(encode_finger(s, 0x300, 0), 0x300, 1)[0]
    assert got.has("saturated")
    assert got.count == 15
    assert got.position_mm[0] == pytest.approx(327.67)
    assert got.force_n[0] == pytest.approx(32.767) and got.force_n[1] == 0
    assert got.total_force_n == pytest.approx(65.535)


def test_id_range_checked():
    check_id_range(0x7F8, 4)
    with pytest.raises(ValueError, match="11-bit"):
        check_id_range(0x7FA, 4)
    check_id_range(0x7FA, 4, extended=True)


def test_decoder_ignores_foreign_ids_and_needs_pairs():
    dec = SummaryDecoder(0x300, 2)
    assert dec.feed(0x123, bytes(8)) is None
    assert dec.feed(0x301, bytes(8)) is None            # force frame without contact frame
    frames = encode_finger(FingerSummary(1, status={"alive"}), 0x300, 1)
    assert dec.feed(*frames[0]) is None
    assert dec.feed(*frames[1]) == 1
    assert dec.updated == {1: 1}


def test_summary_from_pipeline_result_picks_strongest():
    from tensortouch.runtime.pipeline import FrameResult
    from tensortouch.runtime.stages.contacts import Cluster

    def cl(i, f, pos):
        return Cluster(id=i, uv_px=(0.0, 0.0), position_mm=pos, normal=(0, 0, 1), area_mm2=1.0,
                       force_n=tuple(f), force_mag_n=float(np.linalg.norm(f)), pixels=4, perimeter_px=4.0,
                       circularity=1.0)

    r = FrameResult(1, 0.0, np.zeros((15, 4, 4)), [cl(1, (0, 0, 0.2), (1, 2, 3)), cl(2, (0.1, 0, 0.9), (4, 5, 6))],
                    np.array([0.1, 0, 1.1]), np.zeros(3), "CONTACT", ["frame_black"], {})
    s = summary_from_result(r, {"calibration_invalid"})
    assert s.count == 2 and s.position_mm == (4, 5, 6) and s.force_n == (0.1, 0, 0.9)
    assert s.status == {"alive", "contact", "image_bad", "invalid"}
    assert s.total_force_n == pytest.approx(np.hypot(0.1, 1.1))
