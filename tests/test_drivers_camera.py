"""Camera layer: replay of sessions / video files and OpenCV capture, all on real files via cv2."""
import time

import cv2
import numpy as np
import pytest
from tensortouch.contracts.errors import CaptureError, DeviceNotFoundError, SessionError, TensorTouchError
from tensortouch.contracts.session import new_manifest, write_manifest, write_table
from tensortouch.drivers.camera import (
    EndOfStream,
    OpenCVCamera,
    OpenCVCameraConfig,
    ReplayCamera,
    ReplayCameraConfig,
    camera_from_uri,
)

H, W = 48, 64


def make_image(i):
    """Frame i: red and blue levels encode i (survives MJPG), green differs so RGB/BGR mix-ups show."""
    img = np.empty((H, W, 3), np.uint8)
    img[..., 0] = 20 + 12 * (i % 19)
    img[..., 1] = 5
    img[..., 2] = 20 + 12 * (i // 19)
    return img


def decode_index(rgb):
    lo = int(round((float(rgb[..., 0].mean()) - 20) / 12))
    hi = int(round((float(rgb[..., 2].mean()) - 20) / 12))
    return lo + 19 * hi


def write_video(path, n, fps=30.0):
    fourcc = "mp4v" if str(path).endswith(".mp4") else "MJPG"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*fourcc), fps, (W, H))
    assert writer.isOpened()
    for i in range(n):
        writer.write(cv2.cvtColor(make_image(i), cv2.COLOR_RGB2BGR))
    writer.release()
    return path


def write_session(root, times, kind="video", indices=None, n_images=None, video="frames.avi"):
    root.mkdir(parents=True, exist_ok=True)
    indices = list(range(len(times))) if indices is None else indices
    if kind == "video":
        write_video(root / video, max(indices) + 1)
        frames = {"file": "frames.csv", "video": video}
    else:
        (root / "frames").mkdir()
        for i in range(n_images or max(indices) + 1):
            cv2.imwrite(str(root / "frames" / f"{i:06d}.png"), cv2.cvtColor(make_image(i), cv2.COLOR_RGB2BGR))
        frames = {"file": "frames.csv", "images": "frames"}
    write_table(root / "frames.csv", ["t", "index"], np.column_stack([times, indices]))
    write_manifest(root, new_manifest("TT-TEST", {"frames": frames}))
    return root


def read_all(cam):
    frames = []
    while True:
        try:
            frames.append(cam.read())
        except EndOfStream:
            return frames


# -- replay: sessions -------------------------------------------------------------------------
@pytest.mark.parametrize("kind", ["video", "images"])
def test_replay_session_delivers_every_frame_with_recorded_clock(tmp_path, kind):
    times = 10.0 + np.arange(8) * 0.01
    root = write_session(tmp_path / "s", times, kind)
    with ReplayCamera(ReplayCameraConfig(root, realtime=False)) as cam:
        frames = read_all(cam)
        with pytest.raises(EndOfStream):
            cam.read()
        with pytest.raises(EndOfStream):
            cam.read_latest()
    assert [f.index for f in frames] == list(range(8))
    np.testing.assert_allclose([f.t for f in frames], times)
    assert [decode_index(f.image) for f in frames] == list(range(8))
    for f in frames:
        assert f.image.shape == (H, W, 3) and f.image.dtype == np.uint8
        assert abs(f.image[..., 1].mean() - 5) < 3  # channel order kept
    if kind == "images":  # PNG is lossless: exact pixels
        np.testing.assert_array_equal(frames[3].image, make_image(3))


@pytest.mark.parametrize("kind", ["video", "images"])
def test_replay_session_follows_frames_csv_indices(tmp_path, kind):
    indices = [0, 2, 3, 7]
    root = write_session(tmp_path / "s", np.arange(4) * 0.1, kind, indices=indices)
    with ReplayCamera(ReplayCameraConfig(root, realtime=False)) as cam:
        assert [decode_index(f.image) for f in read_all(cam)] == indices


def test_replay_realtime_paces_by_recorded_clock(tmp_path):
    times = np.arange(6) * 0.05
    root = write_session(tmp_path / "s", times, "images")
    with ReplayCamera(ReplayCameraConfig(root, realtime=True)) as cam:
        t0 = time.monotonic()
        frames = read_all(cam)
        elapsed = time.monotonic() - t0
    assert len(frames) == 6
    assert 0.24 <= elapsed < 0.5
    with ReplayCamera(ReplayCameraConfig(root, realtime=True, speed=2.0)) as cam:
        t0 = time.monotonic()
        read_all(cam)
        assert 0.12 <= time.monotonic() - t0 < 0.24


def test_replay_read_latest_skips_to_newest_due_frame(tmp_path):
    times = np.arange(40) * 0.05
    root = write_session(tmp_path / "s", times, "video")
    with ReplayCamera(ReplayCameraConfig(root, realtime=True)) as cam:
        t0 = time.monotonic()
        first = cam.read_latest()
        assert first.index == 0
        again = cam.read_latest()  # nothing new is due yet: the same frame, no waiting
        assert again.index == 0 or time.monotonic() - t0 >= 0.05
        time.sleep(0.3)
        t1 = time.monotonic()
        late = cam.read_latest()
        t2 = time.monotonic()
        # the newest due frame: skipped the ones in between (bounds from the clock actually seen)
        assert int((t1 - t0) / 0.05) - 1 <= late.index <= int((t2 - t0) / 0.05) + 1
        assert late.index >= 5
        assert decode_index(late.image) == late.index
        nxt = cam.read()  # read() then continues with the next frame
        assert nxt.index == late.index + 1


def test_replay_loop_keeps_clock_increasing(tmp_path):
    times = np.arange(5) * 0.1
    root = write_session(tmp_path / "s", times, "video")
    with ReplayCamera(ReplayCameraConfig(root, realtime=False, loop=True)) as cam:
        frames = [cam.read() for _ in range(12)]
    assert [decode_index(f.image) for f in frames] == [i % 5 for i in range(12)]
    assert np.all(np.diff([f.t for f in frames]) > 0)
    assert frames[5].t == pytest.approx(0.5)  # one pass = 0.4 s + one frame interval


def test_replay_video_shorter_than_frames_csv_is_a_clear_error(tmp_path):
    root = write_session(tmp_path / "s", np.arange(6) * 0.1, "video", video="frames.mp4")
    write_video(root / "frames.mp4", 3)  # the recording lost its last frames
    with ReplayCamera(ReplayCameraConfig(root, realtime=False)) as cam:
        for _ in range(3):
            cam.read()
        with pytest.raises(CaptureError, match="truncated") as err:
            cam.read()
    assert not isinstance(err.value, EndOfStream)
    assert "frames.mp4" in str(err.value) and err.value.__cause__ is None


def test_replay_truncated_avi_is_a_clear_error(tmp_path):
    """Caught when the session is opened (session contract) or at the missing frame (replay)."""
    root = write_session(tmp_path / "s", np.arange(6) * 0.1, "video")
    data = (root / "frames.avi").read_bytes()
    (root / "frames.avi").write_bytes(data[: len(data) // 2])
    with pytest.raises(TensorTouchError, match="truncated"):
        with ReplayCamera(ReplayCameraConfig(root, realtime=False)) as cam:
            read_all(cam)


def test_replay_unreadable_png_is_a_clear_error(tmp_path):
    root = write_session(tmp_path / "s", np.arange(4) * 0.1, "images")
    png_end = b"\x00\x00\x00\x00IEND\xaeB`\x82"  # a complete-looking file with garbage inside
    (root / "frames" / "000002.png").write_bytes(b"\x89PNG garbage" * 10 + png_end)
    with ReplayCamera(ReplayCameraConfig(root, realtime=False)) as cam:
        cam.read(), cam.read()
        with pytest.raises(CaptureError, match="000002.png"):
            cam.read()


def test_replay_frame_size_change_is_a_clear_error(tmp_path):
    root = write_session(tmp_path / "s", np.arange(3) * 0.1, "images")
    cv2.imwrite(str(root / "frames" / "000001.png"), np.zeros((10, 10, 3), np.uint8))
    with ReplayCamera(ReplayCameraConfig(root, realtime=False)) as cam:
        cam.read()
        with pytest.raises(CaptureError, match="10x10"):
            cam.read()


def test_replay_missing_images_is_a_session_error(tmp_path):
    root = write_session(tmp_path / "s", np.arange(5) * 0.1, "images")
    (root / "frames" / "000004.png").unlink()
    with pytest.raises(SessionError, match="truncated"):
        ReplayCamera(ReplayCameraConfig(root)).connect()


# -- replay: plain video files ---------------------------------------------------------------
def test_plain_video_file_clock_from_container_fps(tmp_path):
    video = write_video(tmp_path / "clip.avi", 7, fps=25.0)
    with camera_from_uri(f"file:{video}?realtime=0") as cam:
        frames = read_all(cam)
    assert [decode_index(f.image) for f in frames] == list(range(7))
    np.testing.assert_allclose([f.t for f in frames], np.arange(7) / 25.0)


def test_plain_video_loop(tmp_path):
    video = write_video(tmp_path / "clip.avi", 4)
    with camera_from_uri(str(video), realtime=False, loop=True) as cam:
        idx = [decode_index(cam.read().image) for _ in range(10)]
    assert idx == [i % 4 for i in range(10)]


@pytest.mark.parametrize("content", [b"", b"garbage" * 1000])
def test_unreadable_video_is_a_clear_error(tmp_path, content):
    bad = tmp_path / "broken.avi"
    bad.write_bytes(content)
    cam = camera_from_uri(f"file:{bad}", realtime=False)
    with pytest.raises(CaptureError, match="broken.avi") as err:
        cam.connect()
    assert err.value.__cause__ is None
    assert not cam.is_connected


def test_missing_source_and_unconnected_reads(tmp_path):
    with pytest.raises(CaptureError, match="no such"):
        ReplayCamera(ReplayCameraConfig(tmp_path / "nope")).connect()
    cam = ReplayCamera(ReplayCameraConfig(write_video(tmp_path / "v.avi", 2)))
    with pytest.raises(CaptureError, match="not connected"):
        cam.read()


# -- OpenCV camera (threaded reader) on a real VideoCapture --------------------------------------
def test_opencv_camera_reads_fresh_frames_then_reports_stall(tmp_path, caplog):
    video = write_video(tmp_path / "cam.avi", 30)
    cfg = OpenCVCameraConfig(device=str(video), api="any", width=1280, height=720, fps=None,
                             fourcc=None, read_timeout_s=0.3, auto_reconnect=False)
    cam = OpenCVCamera(cfg)
    with caplog.at_level("WARNING"):
        cam.connect()
    try:
        assert "refused width=1280" in caplog.text  # a file cannot change size: warned, not fatal
        assert cam.info()["width"] == W and cam.info()["height"] == H
        a = cam.read()
        assert a.image.shape == (H, W, 3) and a.image.dtype == np.uint8
        assert decode_index(a.image) == a.index
        latest = cam.read_latest()
        assert latest.index >= a.index
        # the file is exhausted: the camera "stops delivering frames" -> clear error, not a hang
        t0 = time.monotonic()
        with pytest.raises(CaptureError, match="stopped delivering|no new frame"):
            for _ in range(100):
                cam.read()
        assert time.monotonic() - t0 < 2.0
    finally:
        cam.disconnect()
    assert not cam.is_connected


def test_opencv_camera_unplug_and_replug_mocked_hardware(tmp_path):
    """Deleting / re-creating a file stands in for unplugging / replugging a /dev/video node."""
    video = write_video(tmp_path / "cam.avi", 5)
    cam = OpenCVCamera(OpenCVCameraConfig(device=str(video), api="any", width=None, height=None,
                                          fps=None, fourcc=None, read_timeout_s=2.0))
    with cam:
        before = cam.read()
        video.unlink()
        with pytest.raises(CaptureError, match="disappeared") as err:
            for _ in range(20):
                cam.read()
        assert err.value.__cause__ is None
        # still unplugged: each read tries to reopen and says why it could not
        with pytest.raises(CaptureError, match="reconnect failed.*no such device"):
            cam.read()
        write_video(video, 5)  # plugged back in
        after = cam.read()
        assert cam.is_connected and after.index > before.index
        assert after.image.shape == (H, W, 3)
    assert not cam.is_connected
    with pytest.raises(CaptureError, match="not connected"):
        cam.read()


def test_v4l2_missing_device_is_device_not_found():
    for uri in ("v4l2:/dev/video987", "v4l2:987", "/dev/video987"):
        cam = camera_from_uri(uri)
        with pytest.raises(DeviceNotFoundError, match="/dev/video987") as err:
            cam.connect()
        assert err.value.__cause__ is None and not cam.is_connected
