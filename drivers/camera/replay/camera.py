"""Replay camera: frames of a recorded session (video or PNG folder, clock from frames.csv) or of a
plain video file, paced by the recorded clock (`realtime=True`) or as fast as they decode.

Synchronous (no thread): `read()` sleeps until the next frame is due (realtime) and returns it;
`read_latest()` returns the newest frame already due, skipping the ones in between, and repeats
the previous frame when no new one is due yet. The clock starts at the first read, not at connect.
A session whose video is shorter than frames.csv says so (CaptureError); the end of a replay
without `loop` raises EndOfStream.
"""
from __future__ import annotations

import logging
import math
import threading
import time
from pathlib import Path

import cv2
import numpy as np

from ....contracts.errors import CaptureError
from ....contracts.session import load_session
from ..camera import Camera, EndOfStream, Frame, to_rgb
from .config import DEFAULT_VIDEO_FPS, ReplayCameraConfig

log = logging.getLogger(__name__)


def _numbered_images(folder: Path) -> dict[int, Path]:
    """PNG files of a frame folder keyed by frame number (numeric stems), else by sorted position."""
    files = sorted(folder.glob("*.png"))
    if files and all(f.stem.isdigit() for f in files):
        return {int(f.stem): f for f in files}
    return dict(enumerate(files))


class ReplayCamera(Camera):
    """Replays a session directory or a video file. See module doc for pacing."""

    def __init__(self, config: ReplayCameraConfig):
        super().__init__(config)
        self.config: ReplayCameraConfig = config
        self._connected = False
        self._cap: cv2.VideoCapture | None = None
        self._video: Path | None = None
        self._images: dict[int, Path] | None = None
        self._times: np.ndarray | None = None     # session: recorded t per row (s)
        self._indices: np.ndarray | None = None   # session: image-stream index per row
        self._count: int | None = None            # rows per pass (None: plain video, not yet known)
        self._fps = DEFAULT_VIDEO_FPS
        self._period = 0.0                        # recorded duration of one pass incl. last frame (s)
        self._pos = 0                             # next frame number the video decoder yields
        self._next = 0                            # next frame position k (counts across loops)
        self._last: Frame | None = None
        self._shape: tuple | None = None
        self._wall0: float | None = None
        self._interrupted = threading.Event()     # set by interrupt(): a paced wait ends at once
        self._first: np.ndarray | None = None     # decoded row 0, checked at connect

    @property
    def name(self) -> str:
        return f"replay:{self.config.path}"

    @property
    def is_connected(self) -> bool:
        return self._connected

    def info(self) -> dict:
        h, w = self._shape[:2] if self._shape else (None, None)
        return {"source": self.name, "width": w, "height": h, "frames": self._count,
                "realtime": self.config.realtime, "loop": self.config.loop}

    # -- lifecycle -------------------------------------------------------------------------
    def connect(self) -> None:
        if self._connected:
            return
        path = self.config.path
        if path.is_dir():
            session = load_session(path)
            frames = session.table("frames")
            if len(frames) == 0:
                raise CaptureError(f"{path / 'frames.csv'}: no frames recorded")
            self._times, self._indices = frames[:, 0].copy(), frames[:, 1].astype(np.int64)
            self._count = len(frames)
            step = float(np.median(np.diff(self._times))) if self._count > 1 else 1.0 / DEFAULT_VIDEO_FPS
            self._period = float(self._times[-1] - self._times[0]) + step
            kind, source = session.image_source()
            if kind == "video":
                self._video = source
            else:
                self._images = _numbered_images(source)
        elif path.is_file():
            self._video = path
        else:
            raise CaptureError(f"{path}: no such session directory or video file")
        if self._video is not None:
            self._open_video()
        self._next, self._last, self._shape, self._wall0 = 0, None, None, None
        self._interrupted.clear()
        self._connected = True
        try:
            self._first = self._decode(0)
        except CaptureError:
            self.disconnect()
            raise
        log.info("replay %s: %s frames, realtime=%s loop=%s", path,
                 self._count if self._count is not None else "?", self.config.realtime, self.config.loop)

    def _open_video(self) -> None:
        if self._cap is not None:
            self._cap.release()
        cap = cv2.VideoCapture(str(self._video))
        if not cap.isOpened():
            cap.release()
            raise CaptureError(f"{self._video}: cannot open video (unreadable, corrupt or not a video; "
                               "readable here: MJPG .avi, mp4v .mp4)")
        self._cap, self._pos = cap, 0
        if self._times is None:  # plain video: its own frame rate is the clock
            declared = cap.get(cv2.CAP_PROP_FRAME_COUNT)
            self._declared = int(declared) if declared and math.isfinite(declared) and declared > 0 else None
            fps = cap.get(cv2.CAP_PROP_FPS)
            self._fps = self.config.fps or (fps if fps and fps > 0 and math.isfinite(fps) else DEFAULT_VIDEO_FPS)

    def disconnect(self) -> None:
        if self._cap is not None:
            self._cap.release()
            self._cap = None
        self._connected = False

    # -- positions and clock ---------------------------------------------------------------
    def _row(self, k: int) -> int:
        return k % self._count if self._count else k

    def recording_time(self, t: float) -> float:
        """A frame time of this replay on the recording's own clock: looping replays shift each pass by
        the recorded duration; this folds `t` back into the first pass (identity otherwise)."""
        if not (self.config.loop and self._times is not None and self._period > 0):
            return float(t)
        return float(t) - math.floor((float(t) - self._times[0]) / self._period) * self._period

    def _time(self, k: int) -> float:
        if self._times is None:
            return k / self._fps
        loops, row = divmod(k, self._count)
        return float(self._times[row]) + loops * self._period

    def _finished(self, k: int) -> bool:
        return not self.config.loop and self._count is not None and k >= self._count

    def _newest_due(self, now: float) -> int:
        """Largest position whose recorded time has come (wall clock scaled by speed)."""
        t = self._time(0) + (now - self._wall0) * self.config.speed
        if self._times is None:
            return int(math.floor(t * self._fps + 1e-9))
        loops = int(math.floor((t - self._times[0]) / self._period)) if self.config.loop else 0
        row = int(np.searchsorted(self._times, t - loops * self._period, side="right")) - 1
        return loops * self._count + max(row, 0)

    # -- decoding --------------------------------------------------------------------------
    def _decode(self, k: int) -> np.ndarray:
        row = self._row(k)
        if self._images is not None:
            idx = int(self._indices[row])
            file = self._images.get(idx)
            if file is None:
                raise CaptureError(f"{self.config.path}: frames.csv row {row + 2} names image {idx}, "
                                   "which is not in the frame folder")
            return self._check(to_rgb(cv2.imread(str(file), cv2.IMREAD_COLOR), str(file)), k)
        idx = int(self._indices[row]) if self._indices is not None else row
        if idx < self._pos:  # looping or seeking back: start the decoder over
            self._open_video()
        while self._pos < idx:
            if not self._cap.grab():
                return self._video_ended(k, idx)
            self._pos += 1
        ok, image = self._cap.read()
        if not ok:
            return self._video_ended(k, idx)
        self._pos += 1
        return self._check(to_rgb(image, f"{self._video} frame {idx}"), k)

    def _video_ended(self, k: int, idx: int) -> np.ndarray:
        if self._indices is not None:
            raise CaptureError(f"{self._video}: video ends or is corrupt at frame {idx}, but frames.csv "
                               f"lists {self._count} frames (truncated recording?)")
        if idx == 0:
            raise CaptureError(f"{self._video}: no frame could be decoded (unreadable or corrupt video)")
        self._count = idx  # plain video: now we know its length
        declared = getattr(self, "_declared", None)
        if declared is not None and idx < declared - 1:
            # the container announces more frames: this is a corrupt frame, not the end. Say so once;
            # the next read goes on as if the video ended here (loops or ends).
            raise CaptureError(f"{self._video}: frame {idx} of {declared} cannot be decoded (garbled or "
                               "truncated video); continuing as if the video ended there")
        if not self.config.loop:
            raise EndOfStream(f"{self.name}: end of video after {idx} frames")
        return self._decode(k)

    def _check(self, image: np.ndarray, k: int) -> np.ndarray:
        if self._shape is None:
            self._shape = image.shape
        elif image.shape != self._shape:
            raise CaptureError(f"{self.name}: frame {self._row(k)} is {image.shape[1]}x{image.shape[0]}, "
                               f"earlier frames are {self._shape[1]}x{self._shape[0]}")
        return image

    def _frame(self, k: int) -> Frame:
        if k == 0 and self._first is not None:
            image, self._first = self._first, None
        else:
            image = self._decode(k)
        self._next = k + 1
        self._last = Frame(image, self._time(k), k)
        return self._last

    # -- frames ----------------------------------------------------------------------------
    def _start_clock(self) -> None:
        if self._wall0 is None:
            self._wall0 = time.monotonic() - (self._time(self._next) - self._time(0)) / self.config.speed

    def read(self, timeout_s: float | None = None) -> Frame:
        """The next frame; in realtime mode sleeps until it is due. `timeout_s` is not used: the
        recording's own clock decides (a long pause in the recording is replayed as such)."""
        self._require_connected()
        k = self._next
        if self._finished(k):
            raise EndOfStream(f"{self.name}: all {self._count} frames delivered")
        if self.config.realtime:
            self._start_clock()
            due = self._wall0 + (self._time(k) - self._time(0)) / self.config.speed
            delay = due - time.monotonic()
            if delay > 0 and self._interrupted.wait(delay):
                raise EndOfStream(f"{self.name}: stopped while waiting {delay:.1f} s for the next recorded frame")
        return self._frame(k)

    def interrupt(self) -> None:
        """End a paced wait now (from another thread or a signal handler): the pending `read()` raises
        EndOfStream. A recorded gap of minutes does not delay a stop. `connect()` re-arms the camera."""
        self._interrupted.set()

    def read_latest(self) -> Frame:
        self._require_connected()
        if not self.config.realtime:
            return self.read()
        self._start_clock()
        k = self._newest_due(time.monotonic())
        if self._count is not None and not self.config.loop:
            if self._next >= self._count:
                raise EndOfStream(f"{self.name}: all {self._count} frames delivered")
            k = min(k, self._count - 1)
        if k < self._next:
            return self._last if self._last is not None else self._frame(self._next)
        return self._frame(k)
