"""Names are never paths: recipe names, sensor ids and package names match one pattern
(contracts/names.py) and every path made from them stays inside its root; through the CLI a bad name is
one line and exit 2, and nothing is created outside the root."""
import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
from tensortouch.contracts.errors import CalibrationError, ModelPackageError, SessionError, TensorTouchError
from tensortouch.contracts.names import NAME_PATTERN, check_name, confined
from tensortouch.contracts.store import CalibrationStore

ROOT = Path(__file__).resolve().parents[1]
BAD = ["../x", "../../../etc", "/etc/passwd", "a/b", "..", ".", ".hidden", "", "x" * 65, "a\nb", "a b", "-x",
       "C:\\x", "~root"]


@pytest.mark.parametrize("bad", BAD)
def test_the_one_pattern_refuses_paths(bad):
    with pytest.raises(TensorTouchError, match="expected " + re.escape(NAME_PATTERN)):
        check_name(bad, "sensor id")


def test_good_names_and_a_link_out_of_the_root(tmp_path):
    for good in ("TWIN-DEMO", "dome01", "hiera-qup-128", "a.b_c-1", "x" * 64):
        assert check_name(good, "name") == good
    root = tmp_path / "root"
    root.mkdir()
    (root / "out").symlink_to(tmp_path)                   # a matching name whose folder is a link out
    with pytest.raises(CalibrationError, match="resolves outside"):
        confined(root, "out", "sensor id", CalibrationError)
    assert confined(root, "inside", "sensor id") == root / "inside"


@pytest.mark.parametrize("bad", ["../../../etc", "/tmp/x", ".."])
def test_store_package_and_session_refuse_path_names(tmp_path, bad):
    from tensortouch.contracts.session import new_manifest, validate_manifest
    from tensortouch.tools.train.package import write_package

    store = CalibrationStore(tmp_path / "store")
    with pytest.raises(CalibrationError, match="sensor id"):
        store.load(bad)
    with pytest.raises(ModelPackageError, match="package name"):
        write_package(tmp_path / "models", bad, {}, {"files": {}})
    assert not (tmp_path / "models").exists()                        # refused before anything is created
    with pytest.raises(SessionError, match="sensor_id"):
        validate_manifest(new_manifest(bad, {}))


def _cli(*argv, cwd):
    env = {**os.environ, "PYTHONPATH": str(ROOT), "TENSORTOUCH_CACHE": str(cwd / "cache")}
    proc = subprocess.run([sys.executable, "-m", "tensortouch.runtime.shells.cli", *map(str, argv)], cwd=cwd,
                          env=env, capture_output=True, text=True, timeout=180)
    lines = [line for line in proc.stderr.splitlines() if line.strip() and not line.startswith("INFO ")]
    return proc.returncode, lines


@pytest.mark.parametrize("name", ["../escaped", "/tmp/tensortouch-absolute-recipe"])
def test_a_recipe_named_like_a_path_is_refused_before_anything_runs(tmp_path, name):
    recipe = tmp_path / "bad.toml"
    recipe.write_text(f'name = "{name}"\n[build]\n')
    code, err = _cli("train", "all", "--recipe", recipe, cwd=tmp_path)
    assert code == 2 and len(err) == 1 and "'name' (the package name)" in err[0] and NAME_PATTERN in err[0], err
    assert not (tmp_path / "escaped").exists() and not Path(name).exists()
    assert not (tmp_path / "cache").exists() or not any((tmp_path / "cache").rglob("*"))


def test_session_import_with_a_path_as_sensor_id_is_refused(tmp_path):
    from tests.test_bad_inputs import mcap_bytes

    bag = tmp_path / "rec.mcap"
    bag.write_bytes(mcap_bytes(n=3))
    mapping = tmp_path / "map.json"
    mapping.write_text(json.dumps({"sensor_id": "../../../etc", "clock": "log", "frames": {"topic": "/cam"}}))
    code, err = _cli("session", "import", bag, "--map", mapping, "--out", tmp_path / "out", cwd=tmp_path)
    assert code == 2 and len(err) == 1 and "sensor_id must be a sensor id matching" in err[0], err
    assert not (tmp_path / "out").exists()


def test_a_session_json_naming_a_path_fails_session_check(tmp_path):
    from tensortouch.contracts.session import new_manifest

    (tmp_path / "s").mkdir()
    (tmp_path / "s" / "session.json").write_text(json.dumps(new_manifest("../../../etc", {})))
    code, err = _cli("session", "check", tmp_path / "s", cwd=tmp_path)
    assert code == 2 and len(err) == 1 and "sensor_id" in err[0], err


def test_effects_add_with_a_path_as_sensor_is_refused(tmp_path):
    code, err = _cli("effects", "add", "strain_stiffening", "--param", "k=1", "--sensor", "../../x",
                     "--store", tmp_path / "store", cwd=tmp_path)
    assert code == 2 and len(err) == 1 and "--sensor" in err[0], err
    assert not any(tmp_path.rglob("*.lock"))


def test_export_with_a_path_as_package_name_is_refused_before_any_work(tmp_path):
    code, err = _cli("train", "export", "--run", tmp_path / "no-run", "--data", tmp_path / "no-data",
                     "--name", "../../evil", "--models-dir", tmp_path / "models", cwd=tmp_path)
    assert code == 2 and len(err) == 1 and "package name '../../evil'" in err[0], err
    assert not (tmp_path / "models").exists() and not (tmp_path.parent / "evil").exists()
