"""Synthetic ONNX test networks (tools/bench/models.py) run in onnxruntime: the difference network's
output worked out by hand, its package valid for the runtime, and the synthetic U-Net's shapes."""
import json

import numpy as np
import pytest

ort = pytest.importorskip("onnxruntime")

from tensortouch.contracts.fields import CHANNELS  # noqa: E402
from tensortouch.contracts.manifest_schema import check_manifest  # noqa: E402
from tensortouch.runtime.stages.model import load_package  # noqa: E402
from tensortouch.tools.bench.models import build_difference_model, build_unet, param_count, write_difference_package  # noqa: E402


def _run(model, x):
    sess = ort.InferenceSession(model.SerializeToString(), providers=["CPUExecutionProvider"])
    return sess.run(None, {sess.get_inputs()[0].name: x})[0]


def test_difference_network_by_hand():
    x = np.zeros((1, 6, 8, 8), np.float32)
    x[:, 3:, 2, 3] = 0.1                          # current frame brighter by 0.1 at one pixel
    x[:, 3:, 5, 5] = 0.9                          # ... and by 0.9 at another: 4 × 0.9 clips at 1
    y = _run(build_difference_model(8, gain=4.0), x)
    k = CHANNELS.index("fn_z")
    assert y.shape == (1, 15, 8, 8)
    assert y[0, k, 2, 3] == pytest.approx(1 - 0.4) and y[0, k, 5, 5] == pytest.approx(0.0)
    assert y[0, k, 0, 0] == pytest.approx(1.0)    # unchanged pixel: normalized 1 ↦ 0 MPa for bounds [-t, 0]
    others = np.delete(y[0], k, axis=0)
    assert np.all(others == 0.5)                  # symmetric bounds: 0.5 ↦ 0


def test_difference_package_is_a_valid_package(tmp_path):
    pkg = write_difference_package(tmp_path / "difference-16", size=16, traction_mpa=0.05)
    m = json.loads((pkg / "manifest.json").read_text())
    check_manifest(m, "manifest.json")
    assert m["synthetic"] and m["output"]["bounds"]["fn_z"] == [-0.05, 0.0]
    assert load_package(pkg).manifest["input"]["size"] == [16, 16]


def test_synthetic_unet_shapes():
    model = build_unet(32, width=4, depth=2)
    assert param_count(model) > 0
    assert _run(model, np.random.default_rng(0).random((1, 6, 32, 32), np.float32)).shape == (1, 15, 32, 32)
