"""The project's one atomic-write helper: a file is either the old one or the complete new one.

    atomic_write(path, b"...")                   # bytes
    atomic_write(path, lambda fh: np.save(fh, a)) # or a writer given the open binary file
    atomic_write_json(path, obj)
    finish_partial(partial_path(path), path)     # a file another library wrote in full beside `path`

The data goes to a temp file beside `path` (same filesystem), is flushed and fsynced, then renamed
over `path`; the folder is fsynced after the rename so the rename itself survives a power loss. On any
error the temp file is removed and the old file is untouched.
"""
from __future__ import annotations

import json
import os
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import BinaryIO


def fsync_dir(folder: str | os.PathLike) -> None:
    """fsync a directory (its entries: a rename, a new file); a no-op where the OS cannot."""
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def atomic_write(path: str | os.PathLike, data: bytes | Callable[[BinaryIO], object], *,
                 fsync: bool = True, mkdir: bool = True) -> Path:
    """Write `data` (bytes, or a callable given the open binary file) to `path` atomically."""
    path = Path(path)
    if mkdir:
        path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as fh:
            if callable(data):
                data(fh)
            else:
                fh.write(data)
            fh.flush()
            if fsync:
                os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise
    if fsync:
        fsync_dir(path.parent)
    return path


def atomic_write_text(path: str | os.PathLike, text: str, **kw) -> Path:
    return atomic_write(path, text.encode("utf-8"), **kw)


def atomic_write_json(path: str | os.PathLike, obj, *, indent: int | None = 1, sort_keys: bool = False,
                      default=None, **kw) -> Path:
    return atomic_write_text(path, json.dumps(obj, indent=indent, sort_keys=sort_keys, default=default), **kw)


def partial_path(path: str | os.PathLike) -> Path:
    """Where a file that a library writes itself (a recording) grows until `finish_partial`: `<name>.partial`."""
    path = Path(path)
    return path.with_name(path.name + ".partial")


def finish_partial(partial: str | os.PathLike, path: str | os.PathLike) -> Path:
    """Put a completely written `partial` file in place of `path`: fsynced, renamed, folder fsynced."""
    with open(partial, "rb") as fh:
        os.fsync(fh.fileno())
    os.replace(partial, path)
    fsync_dir(Path(path).parent)
    return Path(path)
