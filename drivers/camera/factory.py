"""Build a camera from a config dataclass or from a `--source` string.

Source strings (options after `?`, separated by `&`, set config fields):

    v4l2:/dev/video0   v4l2:0          live camera by node or index (OpenCVCameraConfig)
    usb:SERIAL                         live camera found by USB serial number
    replay:PATH                        session directory or video file, real-time pacing
    file:video.avi                     plain video file (same as replay:)
    PATH                               a directory -> replay, a file -> file, /dev/videoN -> v4l2

    e.g. "replay:runtime/demo?loop=1&realtime=0", "v4l2:0?width=1280&height=720&fps=60"
"""
from __future__ import annotations

import dataclasses
import logging
import os
import typing

from ...contracts.errors import CaptureError
from .camera import Camera, CameraConfig
from .opencv import OpenCVCamera, OpenCVCameraConfig
from .replay import ReplayCamera, ReplayCameraConfig

log = logging.getLogger(__name__)

SOURCE_FORMS = "v4l2:/dev/videoN | v4l2:N | usb:SERIAL | replay:PATH | file:VIDEO | PATH"
_TRUE, _FALSE = {"1", "true", "yes", "on"}, {"0", "false", "no", "off"}


def make_camera(config: CameraConfig) -> Camera:
    """The camera for a config dataclass."""
    if isinstance(config, OpenCVCameraConfig):
        return OpenCVCamera(config)
    if isinstance(config, ReplayCameraConfig):
        return ReplayCamera(config)
    raise CaptureError(f"no camera backend for {type(config).__name__}")


def _convert(cls, key: str, text: str, uri: str):
    fields = {f.name: f for f in dataclasses.fields(cls)}
    if key not in fields or key in ("device", "serial", "path"):
        known = sorted(k for k in fields if k not in ("device", "serial", "path"))
        raise CaptureError(f"source {uri!r}: unknown option {key!r} (known: {', '.join(known)})")
    hint = typing.get_type_hints(cls)[key]
    kinds = typing.get_args(hint) or (hint,)
    if text.lower() in ("none", "") and type(None) in kinds:
        return None
    if bool in kinds:
        if text.lower() in _TRUE | _FALSE:
            return text.lower() in _TRUE
        raise CaptureError(f"source {uri!r}: option {key}={text!r}, expected 1/0/true/false")
    for kind in (int, float, str):
        if kind in kinds:
            try:
                return kind(text)
            except ValueError:
                continue
    raise CaptureError(f"source {uri!r}: option {key}={text!r} is not a valid {hint}")


def config_from_uri(uri: str, **overrides) -> CameraConfig:
    """Parse a source string into a config; keyword overrides win over `?options`."""
    text, _, query = uri.partition("?")
    scheme, sep, rest = text.partition(":")
    if not sep or len(scheme) == 1 or scheme not in ("v4l2", "usb", "replay", "file"):
        scheme, rest = "", text  # a bare path (or a Windows drive letter)
    if not rest:
        raise CaptureError(f"source {uri!r}: nothing after '{scheme}:' (forms: {SOURCE_FORMS})")
    if scheme == "":
        if rest.isdigit() or rest.startswith("/dev/video"):
            scheme = "v4l2"
        elif os.path.exists(rest):
            scheme = "replay"
        else:
            raise CaptureError(f"source {uri!r}: no such file or directory (forms: {SOURCE_FORMS})")
    cls = OpenCVCameraConfig if scheme in ("v4l2", "usb") else ReplayCameraConfig
    options = {}
    for item in filter(None, query.split("&")):
        key, eq, value = item.partition("=")
        if not eq:
            raise CaptureError(f"source {uri!r}: option {item!r} needs key=value")
        options[key] = _convert(cls, key, value, uri)
    options.update(overrides)
    if scheme == "v4l2":
        return cls(device=int(rest) if rest.isdigit() else rest, **options)
    if scheme == "usb":
        return cls(serial=rest, **options)
    return cls(path=rest, **options)


def camera_from_uri(uri: str, **overrides) -> Camera:
    """`make_camera(config_from_uri(uri, **overrides))`: what the CLI's --source uses."""
    return make_camera(config_from_uri(uri, **overrides))
