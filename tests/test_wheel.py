"""A built wheel lives beside other distributions: everything installs under `tensortouch.*`, and the
installed copy (no checkout anywhere on its path) runs the shipped demo, with the model, demo and
calibration found as package data, while `listen` in a second process receives it.

Real wheel build (setuptools, no build isolation), a fresh venv, real processes, real Zenoh on a free
loopback port. The fresh venv borrows the third-party packages of the test's own environment through
a plain path line (not its .pth files, so the editable checkout stays invisible).
"""
import os
import shutil
import subprocess
import sys
import sysconfig
import zipfile

import pytest
from tensortouch.contracts.paths import ROOT

from tests.test_e2e_runtime import free_port, stop
from tests.test_meeting_point import _wait_for_line

pytestmark = pytest.mark.skipif(not (ROOT / "exported_models" / "hiera-qup-128" / "manifest.json").is_file(),
                                reason="no shipped model in this checkout")


@pytest.fixture(scope="module")
def installed(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("wheel")
    # build from a copy of the sources, so no stale build/ folder of the checkout can leak into the wheel
    src = tmp / "src"
    shutil.copytree(ROOT, src, ignore=shutil.ignore_patterns("cache", ".git", ".venv*", "build", "dist", "*.egg-info",
                                                            "__pycache__", ".pytest_cache", ".ci-hand"))
    subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q",
                    "-w", str(tmp / "dist"), str(src)], check=True, cwd=tmp, capture_output=True)
    wheel = next((tmp / "dist").glob("tensortouch-*.whl"))
    venv = tmp / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True)
    py = venv / "bin" / "python"
    site = subprocess.run([str(py), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                          check=True, capture_output=True, text=True).stdout.strip()
    deps = {sysconfig.get_paths()["purelib"], sysconfig.get_paths()["platlib"]}
    with open(os.path.join(site, "_borrowed_deps.pth"), "w") as f:
        f.write("\n".join(sorted(deps)) + "\n")
    subprocess.run([sys.executable, "-m", "pip", "--python", str(py), "install", "--no-deps", "--no-index", "-q",
                    str(wheel)], check=True, capture_output=True)
    return wheel, venv, tmp


def test_the_wheel_holds_one_top_level_package_and_the_data(installed):
    wheel, _, _ = installed
    names = zipfile.ZipFile(wheel).namelist()
    tops = {n.split("/")[0] for n in names if not n.split("/")[0].endswith((".dist-info", ".data"))}
    assert tops == {"tensortouch"}, tops
    for need in ("tensortouch/runtime/pipeline.py", "tensortouch/contracts/wire.py", "tensortouch/drivers/usb.py",
                 "tensortouch/runtime/demo/session.json", "tensortouch/exported_models/hiera-qup-128/manifest.json",
                 "tensortouch/exported_models/hiera-qup-128/model.int8.onnx",
                 "tensortouch/calibration_store/TWIN-DEMO/CURRENT", "tensortouch/tools/train/recipes/hiera-qup-128.toml"):
        assert need in names, need


def test_the_installed_wheel_runs_the_demo_and_listen_receives_it(installed):
    _, venv, tmp = installed
    env = {k: v for k, v in os.environ.items() if not k.startswith("TENSORTOUCH_") and k != "PYTHONPATH"}
    env.update(PYTHONUNBUFFERED="1", TENSORTOUCH_ENDPOINT=f"tcp/127.0.0.1:{free_port()}", HOME=str(tmp))
    where = subprocess.run([str(venv / "bin" / "python"), "-c",
                            ("import tensortouch.runtime, tensortouch.contracts.paths as p; "
                            "print(tensortouch.runtime.__file__); print(p.models_dir()); print(p.cache_dir())")],
                           env=env, cwd=tmp, check=True, capture_output=True, text=True).stdout.split()
    assert all(str(venv) in w or str(tmp) in w for w in where), where
    assert not any(str(ROOT) in w for w in where), where
    tt = str(venv / "bin" / "tensortouch")
    run = subprocess.Popen([tt, "run"], env=env, cwd=tmp, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    listen = None
    try:
        _wait_for_line(run, run.stderr, "Ctrl-C to stop", 120)
        listen = subprocess.Popen([tt, "listen", "TWIN-DEMO"], env=env, cwd=tmp, stdout=subprocess.PIPE,
                                  stderr=subprocess.PIPE, text=True)
        text, _ = _wait_for_line(listen, listen.stdout, "tensortouch/TWIN-DEMO/wrench", 30.0)
        assert "tensortouch/TWIN-DEMO/" in text
    finally:
        if listen is not None:
            listen.kill()
            listen.wait(10)
        stop(run)


def test_the_installed_wheel_writes_calibrations_to_the_users_data_folder(installed):
    """From a wheel, `calib init` and `effects add` on the shipped TWIN-DEMO write into
    $XDG_DATA_HOME/tensortouch/calibration_store (default ~/.local/share/...), never into site-packages;
    the shipped TWIN-DEMO stays readable and untouched; rollback leaves no file in the package."""
    _, venv, tmp = installed
    py = str(venv / "bin" / "python")
    site = subprocess.run([py, "-c", "import tensortouch, pathlib; print(pathlib.Path(tensortouch.__file__).parent)"],
                          check=True, capture_output=True, text=True, cwd=tmp).stdout.strip()
    shipped = os.path.join(site, "calibration_store")
    before = sorted(os.path.relpath(os.path.join(d, f), shipped) for d, _, fs in os.walk(shipped) for f in fs)
    home = tmp / "home"
    env = {k: v for k, v in os.environ.items()
           if not k.startswith(("TENSORTOUCH_", "XDG_")) and k != "PYTHONPATH"}
    env.update(HOME=str(home))
    tt = str(venv / "bin" / "tensortouch")

    def cli(*argv, extra=None):
        proc = subprocess.run([tt, *argv], env={**env, **(extra or {})}, cwd=tmp, capture_output=True, text=True,
                              timeout=300)
        assert proc.returncode == 0, proc.stderr[-2000:]
        return proc.stdout

    demo = os.path.join(site, "runtime", "demo")
    out = cli("calib", "init", "--source", f"replay:{demo}?realtime=0", "--sensor", "WHEEL-1")
    data = home / ".local" / "share" / "tensortouch" / "calibration_store"
    assert str(data) in out and (data / "WHEEL-1" / "versions" / "v0001" / "calibration.json").is_file()
    out = cli("effects", "add", "strain_stiffening", "--param", "k=5", "--sensor", "TWIN-DEMO")
    assert "calibration v0002" in out                      # numbered after the shipped v0001
    assert (data / "TWIN-DEMO" / "CURRENT").read_text().strip() == "v0002"
    assert '"strain_stiffening"' in cli("calib", "show", "TWIN-DEMO")
    cli("calib", "rollback", "TWIN-DEMO")                  # back to the shipped v0001, read from the package
    assert '"strain_stiffening"' not in cli("calib", "show", "TWIN-DEMO")
    listed = cli("calib", "list")
    assert "* TWIN-DEMO v0001" in listed and "* WHEEL-1 v0001" in listed
    xdg = tmp / "xdg-data"
    cli("calib", "init", "--source", f"replay:{demo}?realtime=0", "--sensor", "WHEEL-2", extra={"XDG_DATA_HOME": str(xdg)})
    assert (xdg / "tensortouch" / "calibration_store" / "WHEEL-2" / "CURRENT").is_file()
    after = sorted(os.path.relpath(os.path.join(d, f), shipped) for d, _, fs in os.walk(shipped) for f in fs)
    assert after == before, sorted(set(after) ^ set(before))        # nothing written inside the package
