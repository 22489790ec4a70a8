"""A minimal Motion-JPEG AVI writer (pure Python + cv2.imencode) with real JPEG quality control.

OpenCV 5's VideoWriter ignores VIDEOWRITER_PROP_QUALITY for MJPG (measured: the same bytes for
quality 50..95, with both the FFMPEG and the built-in MJPEG backends), and twin frames with sensor
noise cost ~22 kB each at its fixed quality. This writer stores JPEGs encoded at the requested
quality in a standard AVI (RIFF 'AVI ', one 'vids'/'MJPG' stream, 'movi' list, 'idx1' index) that
cv2.VideoCapture reads.
"""
from __future__ import annotations

import struct
from pathlib import Path

import cv2
import numpy as np

from ...contracts.errors import SessionError
from ...contracts.files import atomic_write


def _chunk(cid: bytes, data: bytes) -> bytes:
    return cid + struct.pack("<I", len(data)) + data + (b"\0" if len(data) & 1 else b"")


def _list(kind: bytes, body: bytes) -> bytes:
    return b"LIST" + struct.pack("<I", len(body) + 4) + kind + body


def write_mjpg_avi(path: Path, frames, fps: float, quality: int = 80) -> int:
    """Write BGR uint8 frames (an iterable) as an MJPG AVI atomically; returns the file size."""
    path = Path(path)
    jpegs = []
    w = h = None
    for img in frames:
        if w is None:
            h, w = img.shape[:2]
        elif img.shape[:2] != (h, w):
            raise SessionError(f"{path}: frame {len(jpegs)} is {img.shape[1]}x{img.shape[0]}, expected {w}x{h}")
        ok, buf = cv2.imencode(".jpg", np.ascontiguousarray(img), [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
        if not ok:
            raise SessionError(f"{path}: JPEG encoding failed at frame {len(jpegs)}")
        jpegs.append(buf.tobytes())
    if not jpegs:
        raise SessionError(f"{path}: no frames to write")
    n, biggest = len(jpegs), max(len(j) for j in jpegs)
    scale, rate = 1000, int(round(fps * 1000))
    avih = struct.pack("<14I", int(round(1e6 / fps)), int(biggest * fps), 0, 0x10, n, 0, 1, biggest, w, h, 0, 0, 0, 0)
    strh = b"vidsMJPG" + struct.pack("<IHHIIIIIIIi4h", 0, 0, 0, 0, scale, rate, 0, n, biggest, 0xFFFFFFFF, 0,
                                     0, 0, w, h)
    strf = struct.pack("<IiiHH4sIiiII", 40, w, h, 1, 24, b"MJPG", w * h * 3, 0, 0, 0, 0)
    hdrl = _list(b"hdrl", _chunk(b"avih", avih) + _list(b"strl", _chunk(b"strh", strh) + _chunk(b"strf", strf)))
    movi_body, index, offset = [], [], 4  # offsets relative to the 'movi' fourcc
    for j in jpegs:
        c = _chunk(b"00dc", j)
        index.append(struct.pack("<4sIII", b"00dc", 0x10, offset, len(j)))
        movi_body.append(c)
        offset += len(c)
    movi = _list(b"movi", b"".join(movi_body))
    body = b"AVI " + hdrl + movi + _chunk(b"idx1", b"".join(index))
    atomic_write(path, b"RIFF" + struct.pack("<I", len(body)) + body)
    return path.stat().st_size
