"""Shared pieces of the workbench commands (tools/workbench/cli_common.py): the sensor id from --sensor or
the session, checked because it names files; where the cached model and diagnosis live; a missing model
says how to fit one."""
import argparse
import json

import pytest
from tensortouch.contracts.errors import TensorTouchError
from tensortouch.tools.workbench.cli_common import (
    contact_law,
    default_model_path,
    last_diagnosis_path,
    sensor_of,
    session_args,
)


def _args(*argv):
    p = argparse.ArgumentParser()
    session_args(p)
    return p.parse_args(list(argv))


def test_the_sensor_comes_from_the_flag_or_the_session(tmp_path):
    (tmp_path / "s").mkdir()
    (tmp_path / "s" / "session.json").write_text(json.dumps({"sensor_id": "TT-0042"}))
    assert sensor_of(_args(str(tmp_path / "s"))) == "TT-0042"
    assert sensor_of(_args(str(tmp_path / "s"), "--sensor", "TT-7")) == "TT-7"
    with pytest.raises(TensorTouchError, match=r"--sensor '\.\./x': expected"):
        sensor_of(_args(str(tmp_path / "s"), "--sensor", "../x"))
    (tmp_path / "s" / "session.json").write_text(json.dumps({"sensor_id": "a b"}))
    with pytest.raises(TensorTouchError, match=r"session\.json: sensor_id 'a b': expected"):
        sensor_of(_args(str(tmp_path / "s")))


def test_cached_model_and_diagnosis_paths(tmp_path, monkeypatch):
    monkeypatch.setenv("TENSORTOUCH_CACHE", str(tmp_path / "cache"))
    assert default_model_path("TT-1") == tmp_path / "cache" / "workbench" / "models" / "TT-1.json"
    assert last_diagnosis_path("TT-1") == tmp_path / "cache" / "workbench" / "diagnosis-TT-1.json"
    with pytest.raises(TensorTouchError, match="sensor id '../TT'"):
        default_model_path("../TT")
    with pytest.raises(TensorTouchError, match=r"no model for sensor TT-1 .*--model-from CALIB_SESSION"):
        contact_law(argparse.Namespace(model_from=None), "TT-1", store=None)
