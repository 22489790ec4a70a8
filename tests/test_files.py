"""contracts/files.py: the one atomic-write helper."""
import json
import os

import pytest
from tensortouch.contracts.files import atomic_write, atomic_write_json, finish_partial, partial_path


def test_writes_bytes_callables_and_json(tmp_path):
    p = atomic_write(tmp_path / "sub" / "a.bin", b"abc")
    assert p.read_bytes() == b"abc"
    atomic_write(p, lambda fh: fh.write(b"xyz"))
    assert p.read_bytes() == b"xyz"
    atomic_write_json(tmp_path / "b.json", {"k": [1, 2]}, indent=None)
    assert json.loads((tmp_path / "b.json").read_text()) == {"k": [1, 2]}
    assert sorted(os.listdir(tmp_path)) == ["b.json", "sub"] and os.listdir(tmp_path / "sub") == ["a.bin"]


def test_a_failed_write_keeps_the_old_file_and_leaves_no_temp(tmp_path):
    p = atomic_write(tmp_path / "a.bin", b"old")

    def boom(fh):
        fh.write(b"half")
        raise OSError("disk full")
    with pytest.raises(OSError, match="disk full"):
        atomic_write(p, boom)
    assert p.read_bytes() == b"old" and os.listdir(tmp_path) == ["a.bin"]


def test_file_and_folder_are_fsynced(tmp_path, monkeypatch):
    synced = []
    real = os.fsync
    monkeypatch.setattr(os, "fsync", lambda fd: (synced.append(os.readlink(f"/proc/self/fd/{fd}")), real(fd)))
    atomic_write(tmp_path / "a.bin", b"x")
    assert str(tmp_path) in synced and any(s.startswith(str(tmp_path / ".a.bin.")) for s in synced)


def test_a_finished_partial_file_replaces_the_old_one_fsynced(tmp_path, monkeypatch):
    synced = []
    real = os.fsync
    monkeypatch.setattr(os, "fsync", lambda fd: (synced.append(os.readlink(f"/proc/self/fd/{fd}")), real(fd)))
    final = tmp_path / "rec.mcap"
    final.write_bytes(b"old")
    partial = partial_path(final)
    assert partial == tmp_path / "rec.mcap.partial"
    partial.write_bytes(b"new recording")
    assert finish_partial(partial, final) == final
    assert final.read_bytes() == b"new recording" and os.listdir(tmp_path) == ["rec.mcap"]
    assert synced == [str(partial), str(tmp_path)]
