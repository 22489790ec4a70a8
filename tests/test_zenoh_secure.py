"""The secure deployment of docs/wire.md#security, for real: `tensortouch run` and `tensortouch listen`
with the documented Zenoh configs (docs/zenoh/*.json5: TLS with mutual certificates + access control),
certificates made here with the `openssl` CLI, Zenoh on loopback.

- a subscriber holding its own certificate receives the sensor's data;
- a peer without a certificate, or with one from another CA (even naming the sensor), cannot connect;
- a peer holding a valid certificate that is not the sensor's connects but cannot publish into
  `tensortouch/TWIN-DEMO/**`: the fake-contact attack gets 0 of N through, while the same attack
  against the same config with access control switched off gets through (so the test can fail).
"""
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest
import zenoh
from tensortouch.contracts import wire
from tensortouch.contracts.paths import ROOT
from tensortouch.runtime.apps.subscriber import Subscriber

from tests.test_e2e_runtime import free_port, stop

DOCS = ROOT / "docs" / "zenoh"
MODEL = ROOT / "exported_models" / "hiera-qup-128"
DEMO = ROOT / "runtime" / "demo"
CLI = [sys.executable, "-m", "tensortouch.runtime.shells.cli"]
SENSOR = "TWIN-DEMO"
N_FAKE = 50

pytestmark = [
    pytest.mark.skipif(shutil.which("openssl") is None, reason="needs the openssl CLI"),
    pytest.mark.skipif(not (MODEL / "manifest.json").is_file() or not (DEMO / "session.json").is_file(),
                       reason="no shipped model or demo in this checkout"),
]


def _ssl(folder: Path, *args: str) -> None:
    subprocess.run(["openssl", *args], cwd=folder, check=True, capture_output=True)


def make_pki(folder: Path, leaves: dict[str, str], ca: str = "ca") -> None:
    """A CA `<ca>.pem` and, for each stem -> common name, `<stem>.pem`/`<stem>.key` signed by it."""
    folder.mkdir(parents=True, exist_ok=True)
    ec = ["-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes"]
    _ssl(folder, "req", "-x509", *ec, "-keyout", f"{ca}.key", "-out", f"{ca}.pem", "-days", "2",
         "-subj", f"/CN=tensortouch-test-{ca}-{folder.name}", "-addext", "basicConstraints=critical,CA:TRUE",
         "-addext", "keyUsage=critical,keyCertSign,cRLSign")
    for stem, cn in leaves.items():
        (folder / f"{stem}.ext").write_text(
            "basicConstraints=critical,CA:FALSE\nkeyUsage=critical,digitalSignature\n"
            "extendedKeyUsage=serverAuth,clientAuth\nsubjectAltName=DNS:localhost,IP:127.0.0.1\n")
        _ssl(folder, "req", *ec, "-keyout", f"{stem}.key", "-out", f"{stem}.csr", "-subj", f"/CN={cn}")
        _ssl(folder, "x509", "-req", "-in", f"{stem}.csr", "-CA", f"{ca}.pem", "-CAkey", f"{ca}.key",
             "-CAcreateserial", "-out", f"{stem}.pem", "-days", "2", "-extfile", f"{stem}.ext")


@pytest.fixture(scope="module")
def deployment(tmp_path_factory):
    """A folder laid out as docs/wire.md#security says: the two configs and certs/."""
    root = tmp_path_factory.mktemp("secure")
    make_pki(root / "certs", {"sensor": "tensortouch-sensor-TWIN-DEMO", "subscriber": "tensortouch-subscriber",
                              "viewer2": "tensortouch-subscriber"})
    make_pki(root / "elsewhere", {"forged": "tensortouch-sensor-TWIN-DEMO"})
    for name in ("sensor.json5", "subscriber.json5"):
        shutil.copy(DOCS / name, root / name)
    no_acl = (DOCS / "sensor.json5").read_text().replace("enabled: true", "enabled: false")
    assert no_acl != (DOCS / "sensor.json5").read_text()
    (root / "sensor-no-acl.json5").write_text(no_acl)
    return root


def test_documented_configs_are_the_ones_in_wire_md():
    text = (ROOT / "docs" / "wire.md").read_text()
    for name in ("sensor.json5", "subscriber.json5"):
        body = (DOCS / name).read_text()
        assert body.strip() in text, f"docs/wire.md does not show docs/zenoh/{name} as it is"


def _attacker(endpoint: str, tls: dict) -> zenoh.Config:
    cfg = zenoh.Config()
    cfg.insert_json5("mode", '"client"')
    cfg.insert_json5("scouting/multicast/enabled", "false")
    cfg.insert_json5("connect/endpoints", json.dumps([endpoint]))
    for key, value in tls.items():
        cfg.insert_json5(f"transport/link/tls/{key}", json.dumps(value))
    return cfg


def _attack(session: zenoh.Session) -> None:
    """N fake contacts for the sensor: a 9 N press, seq from 10**6."""
    fake = [{"id": 1, "position_mm": [0.0, 0.0, 16.0], "force_n": [0.0, 0.0, -9.0], "force_mag_n": 9.0,
             "area_mm2": 4.0, "uv_px": [64.0, 64.0], "normal": [0.0, 0.0, 1.0], "perimeter_px": 12.0,
             "circularity": 1.0, "priority": 1.0, "age_frames": 1}]
    for i in range(N_FAKE):
        payload = wire.encode_contacts(fake, 10**6 + i, 0.0, SENSOR)
        session.put(wire.key(SENSOR, "contacts"), payload, encoding=zenoh.Encoding(wire.ENCODINGS["contacts"]))
        time.sleep(0.01)


def _run_sensor(deployment: Path, config: str, endpoint: str) -> subprocess.Popen:
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    for name in ("TENSORTOUCH_MODELS", "TENSORTOUCH_CALIBRATION", "TENSORTOUCH_DEMO", "TENSORTOUCH_ENDPOINT"):
        env.pop(name, None)
    proc = subprocess.Popen(CLI + ["run", "--zenoh-config", config, "--listen", endpoint, "--no-fields"],
                            cwd=deployment, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    text, t0 = "", time.monotonic()
    while "Ctrl-C to stop" not in text:
        line = proc.stderr.readline()
        if not line or time.monotonic() - t0 > 120:
            raise AssertionError(f"run did not start (rc={proc.poll()}):\n{text}{stop(proc)}")
        text += line
    return proc


def _fakes(frames: list) -> int:
    return sum(1 for f in frames if f.seq >= 10**6)


def _attack_through(deployment: Path, sensor_config: str, monkeypatch) -> dict:
    """Start the sensor with `sensor_config`, subscribe with the documented subscriber config, try
    every attacker; returns what arrived and which attackers could connect."""
    monkeypatch.chdir(deployment)                        # the configs name certs/ relative to here
    endpoint = f"tls/localhost:{free_port()}"
    run = _run_sensor(deployment, sensor_config, endpoint)
    frames: list = []
    out = {"connected": {}}
    try:
        with Subscriber(SENSOR, zenoh_config="subscriber.json5", connect=[endpoint],
                        on_contacts=frames.append) as sub:
            sub.wait_for("contacts", timeout=20)
            attackers = {
                "no certificate": {"root_ca_certificate": "certs/ca.pem"},
                "certificate of another CA naming the sensor": {
                    "root_ca_certificate": "certs/ca.pem", "enable_mtls": True,
                    "connect_certificate": "elsewhere/forged.pem", "connect_private_key": "elsewhere/forged.key"},
                "valid subscriber certificate": {
                    "root_ca_certificate": "certs/ca.pem", "enable_mtls": True,
                    "connect_certificate": "certs/viewer2.pem", "connect_private_key": "certs/viewer2.key"},
            }
            for name, tls in attackers.items():
                try:
                    session = zenoh.open(_attacker(endpoint, tls))
                except zenoh.ZError:
                    out["connected"][name] = False
                    continue
                out["connected"][name] = True
                try:
                    time.sleep(0.5)
                    _attack(session)
                finally:
                    session.close()
            try:                                         # plain TCP to the TLS port does not get in either
                session = zenoh.open(_attacker(endpoint.replace("tls/", "tcp/"), {}))
                out["connected"]["plain tcp"] = True
                session.close()
            except zenoh.ZError:
                out["connected"]["plain tcp"] = False
            n_before = len(frames)
            time.sleep(1.0)
            out["genuine_after_attack"] = len(frames) - n_before - _fakes(frames[n_before:])
            out["fake"] = _fakes(frames)
            out["genuine"] = len(frames) - out["fake"]
    finally:
        stop(run)
    return out


def test_secure_config_keeps_strangers_out_and_delivers_to_subscribers(deployment, monkeypatch):
    got = _attack_through(deployment, "sensor.json5", monkeypatch)
    assert got["connected"] == {"no certificate": False, "certificate of another CA naming the sensor": False,
                                "valid subscriber certificate": True, "plain tcp": False}, got
    assert got["fake"] == 0, f"{got['fake']} of {N_FAKE} fake contacts got through"
    assert got["genuine"] > 10 and got["genuine_after_attack"] > 0, got


def test_same_attack_without_access_control_gets_through(deployment, monkeypatch):
    """The control: TLS alone lets any certificate holder publish as the sensor."""
    got = _attack_through(deployment, "sensor-no-acl.json5", monkeypatch)
    assert got["fake"] == N_FAKE, got


def test_listen_command_with_the_subscriber_config(deployment, monkeypatch):
    monkeypatch.chdir(deployment)
    endpoint = f"tls/localhost:{free_port()}"
    run = _run_sensor(deployment, "sensor.json5", endpoint)
    try:
        r = subprocess.run(CLI + ["listen", SENSOR, "--zenoh-config", "subscriber.json5", "--connect", endpoint,
                                  "--kinds", "contacts,status", "--count", "5", "--json", "--timeout", "30"],
                           cwd=deployment, capture_output=True, text=True, timeout=60, check=False)
    finally:
        stop(run)
    lines = [json.loads(x) for x in r.stdout.splitlines() if x.startswith("{")]
    assert r.returncode == 0 and len(lines) == 5, r.stderr[-2000:]
    assert {m["sensor_id"] for m in lines} == {SENSOR}
