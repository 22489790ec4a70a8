"""Where things live (contracts/paths.py): a checkout, an installed wheel, and the environment variables
that move each location."""
from pathlib import Path

import pytest
from tensortouch.contracts import paths

VARS = ("TENSORTOUCH_MODELS", "TENSORTOUCH_CALIBRATION", "TENSORTOUCH_CACHE", "TENSORTOUCH_DEMO",
        "XDG_DATA_HOME", "XDG_CACHE_HOME")


@pytest.fixture
def clean_env(monkeypatch):
    for name in VARS:
        monkeypatch.delenv(name, raising=False)
    return monkeypatch


def test_a_checkout_keeps_everything_in_the_checkout(clean_env):
    assert not paths.INSTALLED and (paths.ROOT / "pyproject.toml").is_file()
    assert paths.models_dir() == paths.ROOT / "exported_models"
    assert paths.calibration_dir() == paths.ROOT / "calibration_store"
    assert paths.cache_dir() == paths.ROOT / "cache"
    assert paths.demo_dir() == paths.ROOT / "runtime" / "demo"
    assert paths.shipped_models_dir() is None and paths.shipped_calibration_dir() is None


def test_an_installed_wheel_writes_to_the_users_folders(clean_env, tmp_path):
    root = tmp_path / "site-packages" / "tensortouch"
    (root / "calibration_store").mkdir(parents=True)
    clean_env.setattr(paths, "ROOT", root)
    clean_env.setattr(paths, "INSTALLED", True)
    clean_env.setenv("HOME", str(tmp_path / "home"))
    home = tmp_path / "home"
    assert paths.calibration_dir() == home / ".local/share/tensortouch/calibration_store"
    assert paths.models_dir() == home / ".local/share/tensortouch/exported_models"
    assert paths.cache_dir() == home / ".cache/tensortouch"
    assert paths.shipped_calibration_dir() == root / "calibration_store"
    assert paths.shipped_models_dir() is None                  # no exported_models/ in this package
    clean_env.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert paths.cache_dir() == tmp_path / "xdg" / "tensortouch"
    clean_env.setenv("XDG_CACHE_HOME", "relative/cache")        # relative: ignored, as the XDG spec says
    assert paths.cache_dir() == home / ".cache/tensortouch"


def test_environment_variables_move_each_location(clean_env, tmp_path):
    clean_env.setenv("HOME", str(tmp_path))
    clean_env.setenv("TENSORTOUCH_CACHE", "~/c")
    clean_env.setenv("TENSORTOUCH_MODELS", str(tmp_path / "m"))
    clean_env.setenv("TENSORTOUCH_CALIBRATION", str(tmp_path / "s"))
    clean_env.setenv("TENSORTOUCH_DEMO", str(tmp_path / "d"))
    assert paths.cache_dir() == Path(tmp_path) / "c"
    assert (paths.models_dir(), paths.calibration_dir(), paths.demo_dir()) == (
        tmp_path / "m", tmp_path / "s", tmp_path / "d")
    clean_env.setenv("TENSORTOUCH_CACHE", "")                   # empty: the default
    assert paths.cache_dir() == paths.ROOT / "cache"
