"""Where things live: repository root, shipped models, calibration store, cache.

Every location can be overridden by an environment variable so an installed runtime on a
robot hand's computer can keep its models and calibration outside the source tree.
"""
from __future__ import annotations

import os
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
# A source checkout (ROOT holds pyproject.toml) keeps regenerated data under ROOT/cache; an installed
# wheel (ROOT is site-packages/tensortouch) keeps it in the user's cache folder instead.
INSTALLED = not (ROOT / "pyproject.toml").exists()


def _env_path(name: str, default: Path) -> Path:
    value = os.environ.get(name)
    return Path(value).expanduser() if value else default


def models_dir() -> Path:
    """Folder of model packages (`exported_models/<name>/`)."""
    return _env_path("TENSORTOUCH_MODELS", ROOT / "exported_models")


def calibration_dir() -> Path:
    """Calibration store root (`calibration_store/<sensor-id>/`)."""
    return _env_path("TENSORTOUCH_CALIBRATION", ROOT / "calibration_store")


def cache_dir() -> Path:
    """Regenerated data (FE results, datasets, twin sessions); never committed."""
    if INSTALLED:
        default = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "tensortouch"
    else:
        default = ROOT / "cache"
    return _env_path("TENSORTOUCH_CACHE", default)


def demo_dir() -> Path:
    """The short twin recording shipped as the embedded default source."""
    return _env_path("TENSORTOUCH_DEMO", ROOT / "runtime" / "demo")
