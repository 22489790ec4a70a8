"""`twin show`: a contact sheet of a session -- frames, image motion against the rest frame
(optical flow: in-plane sliding and the radial flow of a press both show up), and the F/T force
trace -- drawn with OpenCV only."""
from __future__ import annotations

import logging
from pathlib import Path

import cv2
import numpy as np

from ...contracts.files import atomic_write
from ...contracts.session import load_session
from ..sessions.writer import read_frames

log = logging.getLogger(__name__)
COLORS = [(40, 40, 230), (230, 120, 30), (40, 170, 40), (160, 40, 160)]


def pick_frames(session, n: int = 5) -> list[int]:
    """Frame 0 (rest) and the frames nearest the force peak of the first n-1 contact episodes."""
    ft = session.table("frames")[:, 0]
    picks = [0]
    if session.has("wrench"):
        w = session.table("wrench")
        t = np.unique(w[:, 0])
        mag = np.zeros(len(t))
        for k in np.unique(w[:, 1]):
            rows = w[w[:, 1] == k]
            mag += np.interp(t, rows[:, 0], np.linalg.norm(rows[:, 2:5], axis=1))
        mag = np.convolve(mag, np.ones(15) / 15, "same")  # smooth the F/T noise before thresholding
        on = mag > max(0.15, 0.05 * mag.max())
        padded = np.concatenate([[0], on.astype(np.int8), [0]])
        starts, ends = np.flatnonzero(np.diff(padded) == 1), np.flatnonzero(np.diff(padded) == -1)
        for s0, e0 in zip(starts, ends):
            peak = s0 + int(np.argmax(mag[s0:e0]))
            picks.append(int(np.argmin(np.abs(ft - t[peak]))))
            if len(picks) >= n:
                break
    while len(picks) < n:
        picks.append(int(len(ft) * len(picks) / n))
    return picks


def flow_panel(rest: np.ndarray, frame: np.ndarray, full_px: float = 3.0) -> np.ndarray:
    """Image motion rest -> frame (Farneback optical flow): hue = direction, brightness = magnitude
    (full at `full_px`), so in-plane sliding and the radial flow of a press both show."""
    a, b = (cv2.cvtColor(x, cv2.COLOR_BGR2GRAY) for x in (rest, frame))
    flow = cv2.calcOpticalFlowFarneback(a, b, None, 0.5, 3, 15, 3, 5, 1.2, 0)
    mag, ang = cv2.cartToPolar(flow[..., 0], flow[..., 1])
    hsv = np.zeros(rest.shape, np.uint8)
    hsv[..., 0] = (ang * 90 / np.pi).astype(np.uint8)
    hsv[..., 1] = 255
    hsv[..., 2] = np.clip(mag / full_px * 255, 0, 255).astype(np.uint8)
    out = cv2.cvtColor(hsv, cv2.COLOR_HSV2BGR)
    _label(out, f"image motion, max {mag.max():.1f} px")
    return out


def _label(img, text, y=14):
    cv2.putText(img, text, (4, y), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 255), 1, cv2.LINE_AA)


def force_plot(session, width: int, height: int, marks: list[float]) -> np.ndarray:
    img = np.full((height, width, 3), 255, np.uint8)
    if not session.has("wrench"):
        _label(img, "no wrench stream")
        return img
    w = session.table("wrench")
    t0, t1 = session.table("frames")[[0, -1], 0]
    mags = {int(k): (w[w[:, 1] == k][:, 0], np.linalg.norm(w[w[:, 1] == k][:, 2:5], axis=1)) for k in np.unique(w[:, 1])}
    top = max(0.5, max(m.max() for _, m in mags.values()) * 1.1)
    L, R, T, B = 50, 10, 20, 25
    X = lambda t: (L + (np.asarray(t) - t0) / max(t1 - t0, 1e-9) * (width - L - R)).astype(np.int32)  # noqa: E731
    Y = lambda f: (height - B - np.asarray(f) / top * (height - T - B)).astype(np.int32)  # noqa: E731
    cv2.rectangle(img, (L, T), (width - R, height - B), (0, 0, 0), 1)
    for f in np.linspace(0, top, 5):
        cv2.putText(img, f"{f:.1f}", (5, int(Y(f)) + 4), cv2.FONT_HERSHEY_SIMPLEX, 0.35, (0, 0, 0), 1)
    for s in range(int(np.ceil(t0)), int(t1) + 1, max(1, int((t1 - t0) / 10))):
        cv2.putText(img, f"{s}s", (int(X(s)) - 6, height - 8), cv2.FONT_HERSHEY_SIMPLEX, 0.35, (0, 0, 0), 1)
    for m in marks:
        cv2.line(img, (int(X(m)), T), (int(X(m)), height - B), (180, 180, 180), 1)
    for k, (t, m) in mags.items():
        pts = np.stack([X(t), Y(m)], 1).reshape(-1, 1, 2)
        cv2.polylines(img, [pts], False, COLORS[k % len(COLORS)], 1, cv2.LINE_AA)
        cv2.putText(img, f"|F| indenter {k} (N, F/T)", (L + 10 + 170 * k, T + 14), cv2.FONT_HERSHEY_SIMPLEX, 0.4,
                    COLORS[k % len(COLORS)], 1, cv2.LINE_AA)
    return img


def contact_sheet(session_path, out_png, n: int = 5, scale: int = 1) -> Path:
    s = load_session(session_path)
    picks = sorted(set(pick_frames(s, n)))
    frames = dict(read_frames(s, sorted(set(picks))))
    times = s.table("frames")[:, 0]
    top, mid = [], []
    for i in picks:
        f = frames[i].copy()
        _label(f, f"t={times[i]:.2f}s #{i}")
        top.append(f)
        mid.append(flow_panel(frames[0], frames[i]))
    row1, row2 = np.hstack(top), np.hstack(mid)
    plot = force_plot(s, row1.shape[1], 170, [times[i] for i in picks])
    sheet = np.vstack([row1, row2, plot])
    if scale != 1:
        sheet = cv2.resize(sheet, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
    ok, buf = cv2.imencode(".png", sheet)
    return atomic_write(out_png, buf.tobytes())
