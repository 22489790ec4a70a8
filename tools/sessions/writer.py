"""Session writer: the one way tools/ (twin recorder, bag readers) produce a session directory.

Streams go through contracts.session.write_table (atomic CSV); frames go to a PNG folder (lossless)
or a video file. OpenCV 5 headless, measured on this machine (docs/session.md): FFV1, HFYU and
MPNG in .avi are lossless (max |error| 0 on random frames); MJPG, XVID, mp4v are lossy. Default:
lossless FFV1 .avi for recordings, MJPG .avi for the small shipped demo. The manifest is written
last, so a directory without session.json is an unfinished recording.
"""
from __future__ import annotations

import logging
import os
import shutil
from pathlib import Path

import cv2
import numpy as np

from ...contracts.errors import SessionError
from ...contracts.files import atomic_write, finish_partial
from ...contracts.names import check_name
from ...contracts.session import STREAM_COLUMNS, STREAM_FILES, new_manifest, write_manifest, write_table

log = logging.getLogger(__name__)

FRAME_FORMATS = {  # name -> (fourcc or None for PNG folder, file/folder name, lossless)
    "png": (None, "frames", True),
    "ffv1": ("FFV1", "frames.avi", True),
    "mjpg": ("MJPG", "frames.avi", False),
}


def write_png(path: Path, image: np.ndarray, compression: int = 1) -> None:
    """Write a PNG atomically (zlib level `compression`: 1 = fast, lossless like every level)."""
    ok, buf = cv2.imencode(".png", image, [cv2.IMWRITE_PNG_COMPRESSION, int(compression)])
    if not ok:
        raise SessionError(f"{path}: PNG encoding failed")
    atomic_write(path, buf.tobytes(), fsync=False, mkdir=False)   # one of many frames: the session's finish commits


def encode_video(staging: Path, out: Path, fourcc: str, fps: float, count: int, quality: int = 90) -> int:
    """Encode staged frames 000000.npy.. into a video file (atomically); returns its size."""
    def load(i):
        try:
            return np.load(staging / f"{i:06d}.npy", allow_pickle=False)
        except (OSError, ValueError):
            raise SessionError(f"{staging / f'{i:06d}.npy'}: staged frame missing or unreadable") from None

    if fourcc == "MJPG":  # OpenCV ignores the quality setting for MJPG: own writer (tools/sessions/avi.py)
        from .avi import write_mjpg_avi

        return write_mjpg_avi(out, (load(i) for i in range(count)), fps, quality)
    first = load(0)
    h, w = first.shape[:2]
    tmp = out.with_name(".tmp-" + out.name)
    writer = cv2.VideoWriter(str(tmp), cv2.VideoWriter_fourcc(*fourcc), float(fps), (w, h))
    if not writer.isOpened():
        raise SessionError(f"{out}: OpenCV cannot open a {fourcc} video writer")
    for i in range(count):
        writer.write(first if i == 0 else load(i))
    writer.release()
    finish_partial(tmp, out)                   # the name keeps the extension OpenCV picks the container by
    return out.stat().st_size


def read_frames(session, indices=None):
    """Yield (index, BGR uint8 frame) of a loaded session (video or PNG folder)."""
    kind, src = session.image_source()
    n = len(session.table("frames"))
    wanted = set(range(n)) if indices is None else set(int(i) for i in indices)
    if kind == "images":
        for i in sorted(wanted):
            img = cv2.imread(str(src / f"{i:06d}.png"), cv2.IMREAD_COLOR)
            if img is None:
                raise SessionError(f"{src / f'{i:06d}.png'}: frame missing or unreadable")
            yield i, img
        return
    cap = cv2.VideoCapture(str(src))
    try:
        i = 0
        last = max(wanted) if wanted else -1
        while i <= last:
            ok, img = cap.read()
            if not ok:
                raise SessionError(f"{src}: video ends at frame {i}, frames.csv lists {n} (truncated frames)")
            if i in wanted:
                yield i, img
            i += 1
    finally:
        cap.release()


class SessionWriter:
    """Build a session directory stream by stream; `finish()` writes the manifest."""

    def __init__(self, out: str | Path, sensor_id: str, frame_format: str = "ffv1"):
        if frame_format not in FRAME_FORMATS:
            raise SessionError(f"frame format {frame_format!r}: expected one of {sorted(FRAME_FORMATS)}")
        check_name(sensor_id, "sensor id", SessionError)     # before anything is recorded
        self.out = Path(out)
        self.out.mkdir(parents=True, exist_ok=True)
        self.sensor_id = sensor_id
        self.frame_format = frame_format
        self.streams: dict = {}
        self.extra: dict = {}
        self.staging = self.out / ".partial" / "frames" if frame_format != "png" else self.out / "frames"
        self.staging.mkdir(parents=True, exist_ok=True)

    # -- tables ---------------------------------------------------------------------------
    def table(self, stream: str, data: np.ndarray, **info) -> None:
        data = np.asarray(data, dtype=np.float64)
        if data.ndim != 2 or data.shape[1] != len(STREAM_COLUMNS[stream]):
            raise SessionError(f"stream {stream}: expected (n, {len(STREAM_COLUMNS[stream])}) rows "
                               f"{STREAM_COLUMNS[stream]}, got {data.shape}")
        write_table(self.out / STREAM_FILES[stream], STREAM_COLUMNS[stream], data)
        self.streams[stream] = {"file": STREAM_FILES[stream], "rows": int(len(data)), **info}

    # -- frames ---------------------------------------------------------------------------
    def frame_path(self, index: int) -> Path:
        """PNG in the final folder (png format) or a raw .npy staged for video encoding (fast)."""
        return self.staging / f"{index:06d}.{'png' if self.frame_format == 'png' else 'npy'}"

    def has_frame(self, index: int) -> bool:
        return self.frame_path(index).is_file()

    def frame(self, index: int, image: np.ndarray) -> None:
        path = self.frame_path(index)
        if self.frame_format == "png":
            write_png(path, image)
            return
        atomic_write(path, lambda fh: np.save(fh, np.ascontiguousarray(image, dtype=np.uint8), allow_pickle=False),
                     fsync=False, mkdir=False)

    def finish_frames(self, t: np.ndarray, fps: float, quality: int = 90, **info) -> None:
        t = np.asarray(t, dtype=np.float64)
        n = len(t)
        missing = [i for i in range(n) if not self.has_frame(i)]
        if missing:
            raise SessionError(f"{self.staging}: frames {missing[:5]}... not rendered")
        write_table(self.out / STREAM_FILES["frames"], STREAM_COLUMNS["frames"], np.stack([t, np.arange(n)], 1))
        fourcc, name, lossless = FRAME_FORMATS[self.frame_format]
        first = cv2.imread(str(self.frame_path(0))) if self.frame_format == "png" else \
            np.load(self.frame_path(0), allow_pickle=False)
        h, w = first.shape[:2]
        entry = {"file": STREAM_FILES["frames"], "rows": n, "count": n, "fps": float(fps), "width": w,
                 "height": h, "color": "bgr8 as stored by OpenCV (a normal color image)",
                 "lossless": lossless, **info}
        if fourcc is None:
            entry.update(images=name, codec="png")
        else:
            size = encode_video(self.staging, self.out / name, fourcc, fps, n, quality)
            entry.update(video=name, codec=fourcc, bytes=int(size))
            if not lossless:
                entry["quality"] = int(quality)
        self.streams["frames"] = entry

    # -- manifest -------------------------------------------------------------------------
    def finish(self, provenance: dict | None = None, clock: dict | None = None, **extra) -> Path:
        if "frames" not in self.streams:
            raise SessionError(f"{self.out}: no frames written (finish_frames first)")
        manifest = new_manifest(self.sensor_id, self.streams, provenance, clock)
        manifest.update(extra)
        write_manifest(self.out, manifest)
        if self.frame_format != "png":
            shutil.rmtree(self.out / ".partial" / "frames", ignore_errors=True)
        partial = self.out / ".partial"
        if partial.is_dir() and not any(partial.iterdir()):
            os.rmdir(partial)
        return self.out / "session.json"
