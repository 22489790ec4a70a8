"""How each command's Zenoh session is configured (runtime/apps/zenoh_session.py), read back from the
zenoh.Config itself: the meeting point by role, endpoints given, scouting off, and one-line errors."""
import argparse
import json
import logging

import pytest
from tensortouch.contracts.errors import TensorTouchError
from tensortouch.runtime.apps.zenoh_session import (
    DEFAULT_ENDPOINT,
    add_zenoh_options,
    config_from_args,
    describe,
    load_zenoh_config,
    release,
    session_config,
    zenoh_config,
)


def _get(cfg, key):
    return json.loads(cfg.get_json(key))


def _args(role, *argv):
    p = argparse.ArgumentParser()
    add_zenoh_options(p, role)
    return p.parse_args(list(argv))


def test_the_meeting_point_by_role_and_the_environment(monkeypatch):
    monkeypatch.delenv("TENSORTOUCH_ENDPOINT", raising=False)
    sensor, sub = session_config("sensor"), session_config("subscriber")
    assert _get(sensor, "listen/endpoints") == [DEFAULT_ENDPOINT] and _get(sensor, "connect/endpoints") == []
    assert _get(sub, "connect/endpoints") == [DEFAULT_ENDPOINT] and _get(sub, "listen/endpoints") == []
    assert _get(sensor, "scouting/multicast/enabled") is False and _get(sensor, "scouting/gossip/enabled") is False
    monkeypatch.setenv("TENSORTOUCH_ENDPOINT", "tcp/127.0.0.1:17447")
    assert _get(session_config("sensor"), "listen/endpoints") == ["tcp/127.0.0.1:17447"]
    assert describe(_args("subscriber"), "subscriber") == "connect tcp/127.0.0.1:17447"
    with pytest.raises(ValueError, match="role 'robot'"):
        session_config("robot")


def test_given_endpoints_replace_the_meeting_point():
    a = _args("sensor", "--listen", "tcp/127.0.0.1:7500", "--connect", "tcp/127.0.0.1:7501", "--multicast")
    cfg = config_from_args(a, "sensor")
    assert _get(cfg, "listen/endpoints") == ["tcp/127.0.0.1:7500"]
    assert _get(cfg, "connect/endpoints") == ["tcp/127.0.0.1:7501"]
    assert _get(cfg, "scouting/multicast/enabled") is True
    assert describe(a, "sensor") == "listen tcp/127.0.0.1:7500, connect tcp/127.0.0.1:7501"


def test_config_files_and_bad_settings_are_one_line(tmp_path):
    f = tmp_path / "z.json5"
    f.write_text('{ mode: "peer", listen: { endpoints: ["tcp/127.0.0.1:7600"] } }')
    assert _get(load_zenoh_config(f), "listen/endpoints") == ["tcp/127.0.0.1:7600"]
    assert _get(load_zenoh_config(f, listen=["tcp/127.0.0.1:7601"]), "listen/endpoints") == ["tcp/127.0.0.1:7601"]
    assert describe(_args("sensor", "--zenoh-config", str(f)), "sensor") == f"config {f}"
    with pytest.raises(TensorTouchError, match=r"no such Zenoh config file"):
        load_zenoh_config(tmp_path / "missing.json5")
    (tmp_path / "bad.json5").write_text("{ mode: ")
    with pytest.raises(TensorTouchError, match=r"bad\.json5: not a valid Zenoh config \(") as info:
        load_zenoh_config(tmp_path / "bad.json5")
    assert "\n" not in str(info.value) and ".rs:" not in str(info.value)
    with pytest.raises(TensorTouchError, match="zenoh mode 'server'"):
        zenoh_config("server")


def test_release_logs_what_a_gone_peer_refuses(caplog):
    def refuse():
        raise RuntimeError("session closed")

    with caplog.at_level(logging.DEBUG, logger="t"):
        release(refuse, "undeclare fields", logging.getLogger("t"))
    assert "undeclare fields: session closed" in caplog.text
