"""Bad inputs to `tensortouch run`: a clear message, exit 2, no traceback."""
import pytest
from tensortouch.runtime.shells import cli
from tensortouch.tools.bench.models import write_difference_package

from tests.conftest import dome_calibration
from tests.test_e2e_runtime import SENSOR, SIZE, H, W, write_poke_session


@pytest.fixture
def env(tmp_path, monkeypatch):
    write_difference_package(tmp_path / "models" / "difference-32", SIZE)
    monkeypatch.setenv("TENSORTOUCH_MODELS", str(tmp_path / "models"))
    monkeypatch.setenv("TENSORTOUCH_CALIBRATION", str(tmp_path / "calib"))
    return tmp_path


def run_cli(args, capsys):
    code = cli.main(args)
    err = capsys.readouterr().err
    assert "Traceback" not in err
    return code, err


def test_missing_calibration(env, capsys):
    session = write_poke_session(env / "s", n=10)
    code, err = run_cli(["run", "--source", f"replay:{session}", "--fast", "--listen", "tcp/127.0.0.1:0"], capsys)
    assert code == 2 and "no calibration for sensor 'TT-E2E'" in err


def test_unreadable_video(env, capsys):
    bad = env / "broken.avi"
    bad.write_bytes(b"\x00garbage" * 100)
    dome_calibration(env / "calib", SENSOR, size=SIZE, image=(W, H))
    code, err = run_cli(["run", "--source", f"file:{bad}", "--sensor", SENSOR, "--fast",
                         "--listen", "tcp/127.0.0.1:0"], capsys)
    assert code == 2 and "broken.avi" in err


def test_missing_source_path(env, capsys):
    code, err = run_cli(["run", "--source", "replay:/nonexistent/session", "--listen", "tcp/127.0.0.1:0"], capsys)
    assert code == 2 and "/nonexistent/session" in err


def test_calibration_model_size_mismatch(env, capsys):
    session = write_poke_session(env / "s", n=10)
    dome_calibration(env / "calib", SENSOR, size=16, image=(W, H))
    code, err = run_cli(["run", "--source", f"replay:{session}", "--fast", "--listen", "tcp/127.0.0.1:0"], capsys)
    assert code == 2 and "does not match model" in err


