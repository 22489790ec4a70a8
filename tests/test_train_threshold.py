"""The package's contact threshold (tools/train/threshold.py) and its use by the runtime."""
import json
from types import SimpleNamespace

import numpy as np
import pytest

from runtime.contacts import ContactConfig
from runtime.pipeline import PipelineConfig
from tools.train.threshold import ThresholdConfig, _has_core, choose, record


def sweep(rest_fp, hit, n_rest=100, n_contact=50, name="S"):
    return {"session": f"/x/{name}", "rest_frames": n_rest, "contact_frames": n_contact,
            "rest_with_core": list(rest_fp), "contact_with_core": list(hit)}


def test_has_core_needs_min_pixels_above_the_threshold():
    mag = np.zeros((16, 16))
    mag[4, 4] = mag[4, 5] = 0.01                     # a 2-pixel speck
    assert not _has_core(mag, 0.002, 3)
    mag[5, 5] = 0.01                                 # 8-connected third pixel
    assert _has_core(mag, 0.002, 3) and not _has_core(mag, 0.01, 3)


def test_choose_takes_the_lowest_clean_grid_value_over_all_sessions():
    cfg = ThresholdConfig(grid=(0.001, 0.0015, 0.002, 0.0025))
    a = sweep([9, 2, 0, 0], [50, 50, 50, 40], name="A")
    b = sweep([4, 0, 0, 0], [50, 49, 45, 30], name="B")
    out = choose([a, b], cfg)
    assert out["contact_threshold_n"] == pytest.approx(0.002 * 4 / 3, abs=1e-5)
    m = out["measured"]
    assert m["rest_frames_with_core"] == [13, 2, 0, 0] and m["sessions"] == ["A", "B"]
    assert m["detected_at_n"] == 0.0025 and m["contact_detected_fraction"] == pytest.approx(70 / 100)
    dirty = choose([sweep([3, 2, 1, 1], [1, 1, 1, 1])], cfg)
    assert dirty["contact_threshold_n"] is None and dirty["measured"]["rest_frames_with_core"] == [3, 2, 1, 1]


def test_the_runtime_takes_the_threshold_from_the_manifest(tmp_path):
    (tmp_path / "manifest.json").write_text(json.dumps({"name": "m", "files": {}}))
    record(tmp_path, {"contact_threshold_n": 0.00275, "measured": {"rule": "test"}})
    man = json.loads((tmp_path / "manifest.json").read_text())
    assert man["files"] == {} and man["runtime"]["contact_threshold_n"] == 0.00275
    assert PipelineConfig.for_package(SimpleNamespace(manifest=man)).contacts.threshold_n == 0.00275
    for old in ({"name": "old"}, {"runtime": {"contact_threshold_n": None}}):
        assert PipelineConfig.for_package(SimpleNamespace(manifest=old)).contacts.threshold_n == ContactConfig().threshold_n


def test_a_fine_tuned_package_names_its_init_checkpoint(tmp_path):
    import hashlib

    from tools.train.stages import _record_init

    run = tmp_path / "runs" / "fit-x"
    run.mkdir(parents=True)
    (run / "best.pt").write_bytes(b"weights")
    (run / "config.json").write_text(json.dumps({"epochs": 30}))
    (tmp_path / "manifest.json").write_text(json.dumps({"training": {"command": "c"}}))
    _record_init(tmp_path, run / "best.pt")
    init = json.loads((tmp_path / "manifest.json").read_text())["training"]["init_from"]
    assert init["sha256"] == hashlib.sha256(b"weights").hexdigest() and init["fit_config"] == {"epochs": 30}
