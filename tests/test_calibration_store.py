"""The calibration store under pressure: concurrent writer processes, fsync of every file and folder the
docs name, folder modes, stale temp folders, paths confined to the store, typed calibration.json,
finite in-range tables."""
import json
import os
import re
import stat
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
import tensortouch.contracts.store as rc
from tensortouch.contracts.errors import CalibrationError
from tensortouch.contracts.store import CalibrationStore

from tests.conftest import dome_calibration

ROOT = Path(__file__).resolve().parents[1]
SENSOR = "TT-STORE"

WRITER = textwrap.dedent("""
    import sys
    from tensortouch.contracts.store import CalibrationStore
    store = CalibrationStore(sys.argv[1])
    cal = store.load("TT-STORE")
    tables = {k: getattr(cal, k) for k in ("theta", "phi", "surface_xyz", "normals", "pixel_area", "mask")}
    meta = {k: cal.meta[k] for k in ("gel_center_px", "gel_radius_px", "model_size", "gel")}
    sys.stdin.readline()                      # start together
    for i in range(int(sys.argv[3])):
        v = store.write("TT-STORE", tables, {**meta, "provenance": {"writer": sys.argv[2], "i": i}})
        print(v, flush=True)
""")


@pytest.fixture
def store(tmp_path):
    dome_calibration(tmp_path / "calib", SENSOR, size=16)
    return CalibrationStore(tmp_path / "calib")


EFFECTS_ADDER = textwrap.dedent("""
    import argparse, io, re, sys
    from contextlib import redirect_stdout
    from tensortouch.tools.workbench import cli
    parser = argparse.ArgumentParser(prog="tensortouch")
    cli.register(parser.add_subparsers(dest="command", required=True))
    store, effect, param = sys.argv[1:4]
    sys.stdin.readline()                      # start together
    for i in range(25):
        value = f"{0.1 + 0.01 * i:.2f}"            # inside both parameters' ranges
        args = parser.parse_args(["effects", "add", effect, "--param", f"{param}={value}",
                                  "--sensor", "TT-STORE", "--store", store])
        out = io.StringIO()
        with redirect_stdout(out):
            assert args.func(args) == 0
        version = re.search(r"-> calibration (v\\d+)", out.getvalue()).group(1)
        print(version, value, flush=True)     # a confirmed change: this value is in this version
""")


def test_two_processes_25_effects_add_each_every_confirmed_change_is_kept(store, tmp_path):
    """Two real processes each run `tensortouch effects add` 25 times on one sensor, each on its own
    effect with a new parameter value every time. Every version must be its predecessor with exactly
    the one confirmed change, so no change is lost and the final version holds each writer's last."""
    script = tmp_path / "adder.py"
    script.write_text(EFFECTS_ADDER)
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    writers = {"strain_stiffening": "k", "friction_mismatch": "mu"}
    procs = {eff: subprocess.Popen([sys.executable, str(script), str(store.root), eff, param], stdin=subprocess.PIPE,
                                   stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
             for eff, param in writers.items()}
    for p in procs.values():
        p.stdin.write("go\n")
        p.stdin.flush()
    outs = {eff: p.communicate(timeout=300) for eff, p in procs.items()}
    assert [p.returncode for p in procs.values()] == [0, 0], [o[1][-2000:] for o in outs.values()]
    confirmed = {}                                          # version -> (effect, value)
    for eff, (out, _) in outs.items():
        for version, value in (line.split() for line in out.splitlines()):
            assert version not in confirmed
            confirmed[version] = (eff, float(value))
    assert len(confirmed) == 50
    assert store.versions(SENSOR) == [f"v{i:04d}" for i in range(1, 52)] and store.current(SENSOR) == "v0051"
    previous = {e["name"]: e["params"] for e in store.load(SENSOR, "v0001").effects}
    for i in range(2, 52):
        version = f"v{i:04d}"
        now = {e["name"]: e["params"] for e in store.load(SENSOR, version).effects}
        eff, value = confirmed[version]
        param = writers[eff]
        assert now[eff][param] == pytest.approx(value), (version, now)
        assert {n: p for n, p in now.items() if n != eff} == {n: p for n, p in previous.items() if n != eff}, \
            f"{version} lost a change of {previous} (has {now})"
        previous = now
    last = {eff: max(v for v, (e, _) in confirmed.items() if e == eff) for eff in writers}
    assert previous == {eff: {**previous[eff], writers[eff]: confirmed[last[eff]][1]} for eff in writers}


def test_a_change_computed_on_an_old_version_is_refused_and_the_lock_is_reentrant(store):
    base = store.current(SENSOR)
    with store.locked(SENSOR):                         # re-entrant: derive takes the same lock inside
        v2 = store.derive(SENSOR, lambda cal: {"effects": cal.effects + [{"name": "a", "params": {}}]})
    with pytest.raises(CalibrationError, match=f"active calibration is {v2}, not {base}.*nothing was stored"):
        store.derive(SENSOR, {"effects": []}, base_version=base)
    cal = store.load(SENSOR)
    with pytest.raises(CalibrationError, match="nothing was stored"):
        store.write(SENSOR, {k: getattr(cal, k) for k in rc.TABLES}, dict(cal.meta), base_version=None)
    assert store.versions(SENSOR) == [base, v2] and store.current(SENSOR) == v2


def test_two_processes_25_writes_each_lose_nothing(store, tmp_path):
    script = tmp_path / "writer.py"
    script.write_text(WRITER)
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    procs = [subprocess.Popen([sys.executable, str(script), str(store.root), name, "25"], stdin=subprocess.PIPE,
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
             for name in ("a", "b")]
    for p in procs:
        p.stdin.write("go\n")
        p.stdin.flush()
    outs = [p.communicate(timeout=120) for p in procs]
    assert [p.returncode for p in procs] == [0, 0], [o[1][-2000:] for o in outs]
    written = [line for o in outs for line in o[0].split()]
    assert len(written) == 50 and len(set(written)) == 50          # every write got its own version
    versions = store.versions(SENSOR)
    assert versions == [f"v{i:04d}" for i in range(1, 52)]          # v0001 + 50 new ones, none lost
    assert store.current(SENSOR) == "v0051"                         # the last write is active
    writers = {}
    for v in versions[1:]:
        prov = store.load(SENSOR, v).meta["provenance"]             # every version complete, hashes verified
        writers.setdefault(prov["writer"], []).append(prov["i"])
    assert {k: sorted(v) for k, v in writers.items()} == {"a": list(range(25)), "b": list(range(25))}
    assert not list((store.root / SENSOR / "versions").glob(".tmp-*"))


def test_every_file_and_folder_the_docs_name_is_fsynced(store, monkeypatch):
    synced = []
    real = os.fsync

    def record(fd):
        synced.append(os.readlink(f"/proc/self/fd/{fd}"))
        return real(fd)

    monkeypatch.setattr(rc.os, "fsync", record)
    v = store.derive(SENSOR, {"correction": {"file": "correction.onnx", "inputs": ["fmag"], "output": "gain"}},
                     files={"correction.onnx": b"onnx bytes"})
    sensor_dir = (store.root / SENSOR).resolve()
    vdir = sensor_dir / "versions" / v
    tmp_names = {re.search(r"/(\.tmp-[^/]+)", p).group(1) for p in synced if "/.tmp-" in p}
    assert len(tmp_names) == 1 and tmp_names.pop().startswith(f".tmp-{v}-")
    # files are synced while still in the temp folder; map them to their final names
    final = {str(p).replace(f"/.tmp-{v}-{os.getpid()}", f"/{v}") for p in synced}
    for name in ("theta.npy", "phi.npy", "surface_xyz.npy", "normals.npy", "pixel_area.npy", "mask.npy",
                 "correction.onnx", "calibration.json"):
        assert str(vdir / name) in final, name
    assert str(vdir) in final                                    # the new version folder (before the rename)
    assert str(sensor_dir / "versions") in synced                # versions/ after the rename
    assert str(sensor_dir) in synced                             # the sensor folder after CURRENT is replaced
    assert synced.index(str(sensor_dir / "versions")) < synced.index(str(sensor_dir))
    assert any(p.startswith(str(sensor_dir / ".CURRENT.")) for p in synced)   # the new pointer's content
    assert store.current(SENSOR) == v


def test_first_write_syncs_the_new_folders_parents(tmp_path, monkeypatch):
    synced = []
    real = os.fsync
    monkeypatch.setattr(rc.os, "fsync", lambda fd: (synced.append(os.readlink(f"/proc/self/fd/{fd}")), real(fd))[1])
    dome_calibration(tmp_path / "new_store", "TT-NEW", size=16)
    root = (tmp_path / "new_store").resolve()
    assert str(tmp_path.resolve()) in synced and str(root) in synced and str(root / "TT-NEW") in synced


def test_version_folders_follow_the_umask(store):
    old = os.umask(0o022)
    try:
        v = store.derive(SENSOR, {})
    finally:
        os.umask(old)
    for folder in (store.root / SENSOR / "versions" / v,):
        assert stat.S_IMODE(folder.stat().st_mode) == 0o755
    for f in (store.root / SENSOR / "versions" / v).iterdir():
        assert stat.S_IMODE(f.stat().st_mode) == 0o644


def test_stale_temp_folders_are_cleaned_by_the_next_write(store):
    vdir = store.root / SENSOR / "versions"
    stale = vdir / ".tmp-v0002-99999"
    stale.mkdir()
    (stale / "theta.npy").write_bytes(b"half")
    (store.root / SENSOR / ".CURRENT.99999.tmp").write_text("v0002")
    keep = vdir / "notes.txt"          # not ours: left alone
    keep.write_text("x")
    v = store.derive(SENSOR, {})
    assert v == "v0002" and not stale.exists() and keep.exists()
    assert not (store.root / SENSOR / ".CURRENT.99999.tmp").exists()


@pytest.mark.parametrize("content", ["../../other/versions/v0001", "/etc", "v0001/../../x", "", "garbage"])
def test_current_must_name_a_version(store, content):
    (store.root / SENSOR / "CURRENT").write_text(content + "\n")
    with pytest.raises(CalibrationError, match="CURRENT: names .*expected a version name"):
        store.load(SENSOR)


def test_version_folder_symlink_out_of_the_store_is_refused(store, tmp_path):
    import shutil

    outside = tmp_path / "outside"
    shutil.copytree(store.root / SENSOR / "versions" / "v0001", outside)
    os.symlink(outside, store.root / SENSOR / "versions" / "v0002")
    with pytest.raises(CalibrationError, match="link out of the store"):
        store.load(SENSOR, "v0002")


def _rewrite_meta(store, change):
    path = store.root / SENSOR / "versions" / "v0001" / "calibration.json"
    meta = json.loads(path.read_text())
    meta = change(meta)
    path.write_text(json.dumps(meta))
    return path


@pytest.mark.parametrize("change,match", [
    (lambda m: [m], "expected a JSON object, got list"),
    (lambda m: {**m, "files": {}}, "files must be a non-empty object"),
    (lambda m: {**m, "files": {k: v for k, v in m["files"].items() if k != "pixel_area.npy"}},
     "tables.pixel_area = 'pixel_area.npy' is not hashed"),
    (lambda m: {**m, "tables": {**m["tables"], "theta": "../../../x.npy"}}, "must be a plain file name"),
    (lambda m: {**m, "tables": {**m["tables"], "theta": "/etc/passwd"}}, "must be a plain file name"),
    (lambda m: {**m, "files": {**m["files"], "../x": "0" * 64}}, "must be a plain file name"),
    (lambda m: {**m, "gel_radius_px": "50"}, "gel_radius_px must be a finite number"),
    (lambda m: {**m, "model_size": [16.5, 16]}, "model_size must be"),
    (lambda m: {**m, "gel_center_px": 3}, "gel_center_px must be"),
    (lambda m: {**m, "tables": []}, "tables must be an object"),
    (lambda m: {**m, "schema_version": "1"}, "schema_version must be an integer"),
    (lambda m: {**m, "correction": {"file": "correction.onnx"}}, "correction.file 'correction.onnx' is not hashed"),
])
def test_calibration_json_is_checked_by_type(store, change, match):
    _rewrite_meta(store, change)
    with pytest.raises(CalibrationError, match=match):
        store.load(SENSOR)


def test_table_symlink_out_of_the_store_is_refused(store, tmp_path):
    vdir = store.root / SENSOR / "versions" / "v0001"
    target = tmp_path / "elsewhere.npy"
    (vdir / "theta.npy").rename(target)
    os.symlink(target, vdir / "theta.npy")
    with pytest.raises(CalibrationError, match="link out of the store"):
        store.load(SENSOR)


@pytest.mark.parametrize("table,value,match", [
    ("pixel_area", np.inf, "pixel_area has 1 non-finite"),
    ("pixel_area", np.nan, "pixel_area has 1 non-finite"),
    ("pixel_area", -1.0, "pixel_area spans"),
    ("theta", 7.0, "theta spans"),
    ("theta", np.nan, r"theta has 1 non-finite value.*on the gel"),
    ("phi", np.inf, "phi has 1 non-finite"),
    ("surface_xyz", np.nan, "surface_xyz has 3 non-finite"),
    ("normals", 3.0, "normals spans"),
])
def test_non_finite_or_out_of_range_tables_are_refused_at_write_and_load(store, table, value, match):
    cal = store.load(SENSOR)
    tables = {k: getattr(cal, k).copy() for k in rc.TABLES}
    assert cal.mask[8, 8]
    tables[table][8, 8] = value                                   # a pixel on the gel
    meta = {k: cal.meta[k] for k in ("gel_center_px", "gel_radius_px", "model_size")}
    with pytest.raises(CalibrationError, match=match):
        store.write(SENSOR, tables, meta)
    assert store.versions(SENSOR) == ["v0001"]
    # the same table written behind the store's back (valid hashes) is refused at load
    vdir = store.root / SENSOR / "versions" / "v0001"
    np.save(vdir / f"{table}.npy", tables[table].astype(np.float32))
    _rewrite_meta(store, lambda m: {**m, "files": {**m["files"], f"{table}.npy": rc.sha256_file(vdir / f"{table}.npy")}})
    with pytest.raises(CalibrationError, match=match):
        store.load(SENSOR)


def test_theta_phi_off_the_gel_may_be_nan(store):
    cal = store.load(SENSOR)
    tables = {k: getattr(cal, k).copy() for k in rc.TABLES}
    tables["theta"][~cal.mask] = np.nan
    tables["phi"][~cal.mask] = np.nan
    v = store.write(SENSOR, tables, {k: cal.meta[k] for k in ("gel_center_px", "gel_radius_px", "model_size")})
    assert np.isnan(store.load(SENSOR, v).theta[~cal.mask]).all()
    tables["pixel_area"][~cal.mask] = np.nan                      # the other tables: finite everywhere
    with pytest.raises(CalibrationError, match="pixel_area has"):
        store.write(SENSOR, tables, {k: cal.meta[k] for k in ("gel_center_px", "gel_radius_px", "model_size")})


def test_write_error_message_says_what_happened(store, monkeypatch):
    def refuse(*a, **k):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(CalibrationStore, "_set_current", refuse)
    with pytest.raises(CalibrationError, match=r"v0002 was stored but could not be activated .*active version is v0001"):
        store.derive(SENSOR, {})
    monkeypatch.undo()
    assert store.versions(SENSOR) == ["v0001", "v0002"] and store.current(SENSOR) == "v0001"
    monkeypatch.setattr(rc.np, "save", refuse)
    with pytest.raises(CalibrationError, match=r"nothing was stored, the active version is still v0001"):
        store.derive(SENSOR, {})
