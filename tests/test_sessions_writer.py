"""The session writer (tools/sessions/writer.py): tables and frames in every format read back as written."""
import numpy as np
import pytest
from tensortouch.contracts.session import load_session
from tensortouch.tools.sessions.writer import read_frames

from tests.test_session_format import _write


@pytest.mark.parametrize("fmt", ["png", "ffv1", "mjpg"])
def test_round_trip_writer(tmp_path, fmt):
    tables, frames = _write(tmp_path / "s", fmt, np.random.default_rng(0))
    s = load_session(tmp_path / "s")
    assert s.sensor_id == "TEST-1" and set(s.streams) == {"poses", "wrench", "temperature", "frames"}
    for name, data in tables.items():
        np.testing.assert_allclose(s.table(name), data, rtol=1e-8, atol=1e-12)
    got = dict(read_frames(s))
    assert len(got) == len(frames)
    for i, f in enumerate(frames):
        if s.streams["frames"]["lossless"]:
            np.testing.assert_array_equal(got[i], f)
        else:
            assert np.abs(got[i].astype(int) - f).mean() < 6.0  # JPEG quality 90, 4:2:0 chroma
    assert not (tmp_path / "s" / ".partial").exists()
