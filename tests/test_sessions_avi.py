"""The MJPG AVI writer (tools/sessions/avi.py): quality is honoured and the frame count is readable."""
import cv2
import numpy as np
from tensortouch.contracts.session import avi_frame_count


def _frames(rng, n=6):
    base = cv2.GaussianBlur(rng.integers(0, 255, (48, 64, 3), dtype=np.uint8), (9, 9), 0)
    return [np.roll(base, i, axis=1) for i in range(n)]


def test_mjpg_quality_is_honoured(tmp_path):
    from tensortouch.tools.sessions.avi import write_mjpg_avi

    frames = _frames(np.random.default_rng(2), 8)
    err, size = {}, {}
    for q in (40, 95):
        size[q] = write_mjpg_avi(tmp_path / f"q{q}.avi", frames, 30.0, q)
        cap = cv2.VideoCapture(str(tmp_path / f"q{q}.avi"))
        got = [cap.read()[1] for _ in frames]
        assert cap.read()[0] is False and avi_frame_count(tmp_path / f"q{q}.avi") == len(frames)
        err[q] = np.mean([np.abs(g.astype(int) - f).mean() for g, f in zip(got, frames)])
    assert size[95] > 1.5 * size[40] and err[95] < 0.7 * err[40]
