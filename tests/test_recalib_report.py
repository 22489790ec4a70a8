"""`tensortouch recalibrate --report PATH`: a report folder that does not exist is refused before anything
is stored (one line, exit 2); a report that cannot be written after storing says truthfully what was
stored. Real replay camera, onnxruntime pipeline and calibration store."""
import os
import subprocess
import sys
from pathlib import Path

import pytest
from tensortouch.contracts.errors import TensorTouchError
from tensortouch.tools.recalib import cli

from tests.recalib_util import SENSOR, setup_env, write_recording
from tests.test_recalib_cli import parse

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture
def env(tmp_path):
    package, store = setup_env(tmp_path)
    session, _, _ = write_recording(tmp_path / "session", package, store)
    return tmp_path, package, store, session


def _argv(package, store, session, report):
    return ["recalibrate", "--sensor", SENSOR, "--source", f"replay:{session}", "--store", str(store.root),
            "--model", str(package.folder), "--precision", "fp32", "--pokes", "6", "--report", report]


def test_missing_report_folder_fails_before_storing(env):
    tmp, package, store, session = env
    before = store.versions(SENSOR), store.current(SENSOR)
    proc = subprocess.run([sys.executable, "-m", "tensortouch.runtime.shells.cli",
                           *_argv(package, store, session, str(tmp / "missing" / "dir" / "r.json"))],
                          check=False, capture_output=True, text=True, timeout=120, cwd=ROOT,
                          env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert proc.returncode == 2, proc.stderr[-2000:]
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in proc.stderr, proc.stderr
    assert "missing/dir" in lines[0] and "does not exist; nothing was stored" in lines[0]
    assert (store.versions(SENSOR), store.current(SENSOR)) == before


def test_report_write_failing_after_storing_says_what_was_stored(env, monkeypatch):
    tmp, package, store, session = env
    v1 = store.current(SENSOR)

    def fail(path, report):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(cli, "_write_report", fail)
    args = parse(_argv(package, store, session, str(tmp / "r.json")))
    with pytest.raises(TensorTouchError) as info:
        cli.cmd_recalibrate(args, say=lambda m: None)
    v2 = store.current(SENSOR)
    assert v2 != v1
    assert f"{SENSOR}/{v2} was stored and is active (was {v1}" in str(info.value)
    assert "No space left on device" in str(info.value) and "\n" not in str(info.value)
