"""Session contract: write -> validate -> read back equal; bad sessions rejected with the problem named."""
import json
import shutil

import cv2
import numpy as np
import pytest
from tensortouch.contracts.errors import SessionError
from tensortouch.contracts.session import STREAM_COLUMNS, avi_frame_count, load_session, rewrite_in_units
from tensortouch.tools.sessions.writer import SessionWriter, read_frames
from tensortouch.tools.twin.record import RecordConfig, record

FT = {"rotation_wxyz": [1.0, 0.0, 0.0, 0.0], "translation_mm": [0.0, 0.0, 44.0]}


def _tables(rng):
    t = np.round(np.arange(50) / 120, 6)
    poses = np.column_stack([np.repeat(t, 2), np.tile([0, 1], 50), rng.normal(0, 5, (100, 3)).round(6),
                             np.tile([1.0, 0, 0, 0], (100, 1))])
    tw = np.round(np.arange(80) / 200, 6)
    wrench = np.column_stack([tw, np.zeros(80), rng.normal(0, 1, (80, 6)).round(6)])
    temp = np.column_stack([np.arange(5) * 0.5, 24 + rng.normal(0, 0.1, 5).round(4)])
    return {"poses": poses, "wrench": wrench, "temperature": temp}


def _frames(rng, n=6):
    base = cv2.GaussianBlur(rng.integers(0, 255, (48, 64, 3), dtype=np.uint8), (9, 9), 0)
    return [np.roll(base, i, axis=1) for i in range(n)]


def _write(out, fmt, rng):
    tables, frames = _tables(rng), _frames(rng)
    w = SessionWriter(out, "TEST-1", fmt)
    w.table("poses", tables["poses"], rate_hz=120)
    w.table("wrench", tables["wrench"], rate_hz=200, ft_to_indenter=FT)
    w.table("temperature", tables["temperature"])
    for i, f in enumerate(frames):
        w.frame(i, f)
    w.finish_frames(np.arange(len(frames)) / 30, 30)
    w.finish({"source": "test"})
    return tables, frames


@pytest.fixture(scope="module")
def twin_session(tmp_path_factory):
    out = tmp_path_factory.mktemp("twin") / "s"
    cfg = RecordConfig(serial="TWIN-T1", pokes=1, seed=3, physics="hertz-fallback", frame_format="ffv1")
    cfg.rig.camera_fps = 15.0
    return record(cfg, out)


def test_twin_session_round_trip(twin_session, tmp_path):
    """A twin session read back and rewritten through the writer is equal to the original."""
    s = load_session(twin_session)
    assert s.manifest["provenance"]["source"] == "twin"
    assert "effects" not in json.dumps(s.manifest)  # truth stays in truth/
    frames = dict(read_frames(s))
    assert len(frames) == len(s.table("frames")) == avi_frame_count(twin_session / "frames.avi")
    w = SessionWriter(tmp_path / "copy", s.sensor_id, "png")
    for name in ("poses", "wrench", "temperature"):
        w.table(name, s.table(name), **{k: v for k, v in s.streams[name].items() if k not in ("file", "rows")})
    for i, f in frames.items():
        w.frame(i, f)
    w.finish_frames(s.table("frames")[:, 0], s.streams["frames"]["fps"])
    w.finish(s.manifest["provenance"])
    c = load_session(tmp_path / "copy")
    for name in ("poses", "wrench", "temperature", "frames"):
        np.testing.assert_allclose(c.table(name), s.table(name), rtol=1e-8)
    for i, f in read_frames(c):
        np.testing.assert_array_equal(f, frames[i])


def _copy(src, dst):
    shutil.copytree(src, dst)
    return dst


def _edit_manifest(path, fn):
    m = json.loads((path / "session.json").read_text())
    fn(m)
    (path / "session.json").write_text(json.dumps(m))


def test_missing_stream_rejected(twin_session, tmp_path):
    s = _copy(twin_session, tmp_path / "s")
    (s / "wrench.csv").unlink()
    with pytest.raises(SessionError, match=r"wrench.csv: stream file missing"):
        load_session(s)


def test_missing_frames_stream_rejected(twin_session, tmp_path):
    s = _copy(twin_session, tmp_path / "s")
    _edit_manifest(s, lambda m: m["streams"].pop("frames"))
    with pytest.raises(SessionError, match=r"at least 'frames'"):
        load_session(s)


def test_non_monotonic_clock_rejected(twin_session, tmp_path):
    s = _copy(twin_session, tmp_path / "s")
    lines = (s / "poses.csv").read_text().splitlines()
    # swap two rows of indenter 0 (rows 1 and 3 hold indenter 0 at consecutive times)
    lines[1], lines[3] = lines[3], lines[1]
    (s / "poses.csv").write_text("\n".join(lines) + "\n")
    with pytest.raises(SessionError, match=r"stream 'poses' clock not strictly increasing"):
        load_session(s)


FOREIGN = {"length": "m", "force": "mN", "torque": "N*m", "time": "ms", "temperature": "K"}


def test_session_in_other_units_reads_in_house_units(twin_session, tmp_path):
    """m, mN, N*m, ms and K in the manifest: every stream is read back in mm, N, N*mm, s, degC."""
    s = _copy(twin_session, tmp_path / "s")
    assert rewrite_in_units(s, FOREIGN).manifest["units"]["force"] == "mN"
    raw = np.loadtxt(s / "wrench.csv", delimiter=",", skiprows=1)
    ref, got = load_session(twin_session), load_session(s)
    np.testing.assert_allclose(raw[:, 2:5], 1e3 * ref.table("wrench")[:, 2:5], rtol=1e-6, atol=1e-6)  # mN in the file
    np.testing.assert_allclose(raw[:, 0], 1e3 * ref.table("wrench")[:, 0], rtol=1e-6)                 # ms
    for name in ref.streams:
        np.testing.assert_allclose(got.table(name), ref.table(name), rtol=1e-6, atol=1e-6, err_msg=name)
    house = rewrite_in_units(s)                 # files converted in place, manifest says so
    assert house.manifest["units"]["force"] == "N" and house.manifest["units"]["time"] == "s"
    for name in ref.streams:
        np.testing.assert_allclose(house.table(name), ref.table(name), rtol=1e-6, atol=1e-6, err_msg=name)
    np.testing.assert_allclose(np.loadtxt(s / "wrench.csv", delimiter=",", skiprows=1), ref.table("wrench"),
                               rtol=1e-6, atol=1e-6)


def test_unknown_unit_rejected(twin_session, tmp_path):
    s = _copy(twin_session, tmp_path / "s")
    _edit_manifest(s, lambda m: m["units"].update(length="furlong"))
    with pytest.raises(SessionError, match=r"units.length is 'furlong', expected one of \['mm', .*'m'"):
        load_session(s)
    _edit_manifest(s, lambda m: m.update(units="SI"))
    with pytest.raises(SessionError, match=r"units must be an object"):
        load_session(s)


def test_truncated_video_rejected(twin_session, tmp_path):
    s = _copy(twin_session, tmp_path / "s")
    data = (s / "frames.avi").read_bytes()
    (s / "frames.avi").write_bytes(data[: len(data) // 2])
    with pytest.raises(SessionError, match=r"truncated frames"):
        load_session(s)
    _edit_manifest(s, lambda m: m["streams"]["frames"].pop("bytes"))  # the RIFF count still catches it
    with pytest.raises(SessionError, match=r"complete frames but frames.csv lists .* \(truncated frames\)"):
        load_session(s)


def test_truncated_png_folder_rejected(tmp_path):
    _write(tmp_path / "s", "png", np.random.default_rng(1))
    f = tmp_path / "s" / "frames" / "000005.png"
    f.write_bytes(f.read_bytes()[:-40])
    with pytest.raises(SessionError, match=r"000005.png: PNG is cut short \(truncated frames\)"):
        load_session(tmp_path / "s")
    f.unlink()
    with pytest.raises(SessionError, match=r"5 images but frames.csv lists 6 \(truncated frames\)"):
        load_session(tmp_path / "s")


def test_truncated_csv_and_missing_transform_rejected(twin_session, tmp_path):
    s = _copy(twin_session, tmp_path / "s")
    text = (s / "wrench.csv").read_text()
    (s / "wrench.csv").write_text(text[: len(text) - 60])  # last row cut mid-line
    with pytest.raises(SessionError, match=r"wrench.csv:\d+: \d values, expected 8"):
        load_session(s)
    lines = text.splitlines()
    (s / "wrench.csv").write_text("\n".join(lines[:-4]) + "\n")  # whole rows lost
    with pytest.raises(SessionError, match=r"wrench.csv: \d+ rows but the manifest recorded \d+ \(truncated stream\)"):
        load_session(s)
    s2 = _copy(twin_session, tmp_path / "s2")
    _edit_manifest(s2, lambda m: m["streams"]["wrench"].pop("ft_to_indenter"))
    with pytest.raises(SessionError, match=r"ft_to_indenter"):
        load_session(s2)


def test_avi_frame_count_matches_opencv(twin_session):
    cap = cv2.VideoCapture(str(twin_session / "frames.avi"))
    n = 0
    while cap.read()[0]:
        n += 1
    assert n == avi_frame_count(twin_session / "frames.avi") > 0


def test_stream_columns_are_the_documented_ones():
    assert STREAM_COLUMNS["wrench"] == ["t", "indenter", "fx", "fy", "fz", "tx", "ty", "tz"]
