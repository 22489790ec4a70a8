"""Where things live: repository root, shipped models, calibration store, cache (docs/calibration_store.md
"Where the store lives").

A source checkout keeps today's layout: calibration_store/ and cache/ in the checkout. An installed wheel
never writes inside its own package: new calibrations go to the user's data folder
($XDG_DATA_HOME/tensortouch/calibration_store, default ~/.local/share/...) and regenerated data to the
user's cache folder ($XDG_CACHE_HOME/tensortouch, default ~/.cache/...), while the calibrations shipped in
the package (TWIN-DEMO) stay readable from there. Every location can be moved by an environment variable.
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


def _xdg(name: str, fallback: str) -> Path:
    """$XDG_<name>_HOME/tensortouch; a relative or empty value is ignored, as the XDG spec says."""
    value = os.environ.get(f"XDG_{name}_HOME", "")
    base = Path(value) if value and os.path.isabs(value) else Path.home() / fallback
    return base / "tensortouch"


def models_dir() -> Path:
    """The writable folder of model packages (`<dir>/<name>/`, where `train export` writes):
    $TENSORTOUCH_MODELS, else exported_models/ of a checkout, else $XDG_DATA_HOME/tensortouch/exported_models
    of a wheel install."""
    default = _xdg("DATA", ".local/share") / "exported_models" if INSTALLED else ROOT / "exported_models"
    return _env_path("TENSORTOUCH_MODELS", default)


def shipped_models_dir() -> Path | None:
    """The read-only model packages inside an installed package; None in a checkout."""
    shipped = ROOT / "exported_models"
    return shipped if INSTALLED and shipped.is_dir() else None


def calibration_dir() -> Path:
    """The writable calibration store root (`<root>/<sensor-id>/`): $TENSORTOUCH_CALIBRATION, else
    calibration_store/ of a checkout, else $XDG_DATA_HOME/tensortouch/calibration_store of a wheel install."""
    default = _xdg("DATA", ".local/share") / "calibration_store" if INSTALLED else ROOT / "calibration_store"
    return _env_path("TENSORTOUCH_CALIBRATION", default)


def shipped_calibration_dir() -> Path | None:
    """The read-only calibrations shipped inside an installed package (TWIN-DEMO), read where the writable
    store has no such sensor; None in a checkout (there the shipped ones are in the writable store)."""
    shipped = ROOT / "calibration_store"
    return shipped if INSTALLED and shipped.is_dir() else None


def cache_dir() -> Path:
    """Regenerated data (FE results, datasets, twin sessions); never committed. $TENSORTOUCH_CACHE, else
    cache/ of a checkout, else $XDG_CACHE_HOME/tensortouch of a wheel install."""
    default = _xdg("CACHE", ".cache") if INSTALLED else ROOT / "cache"
    return _env_path("TENSORTOUCH_CACHE", default)


def demo_dir() -> Path:
    """The short twin recording shipped as the embedded default source."""
    return _env_path("TENSORTOUCH_DEMO", ROOT / "runtime" / "demo")
