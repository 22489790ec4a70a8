import json

import numpy as np
import pytest
from tensortouch.contracts.errors import ModelPackageError
from tensortouch.contracts.fields import CHANNELS
from tensortouch.runtime.stages.model import FieldModel, find_package, load_package
from tensortouch.tools.bench.models import write_package


@pytest.fixture(scope="module")
def package(tmp_path_factory):
    return write_package(tmp_path_factory.mktemp("pkg") / "tiny", size=32, width=4, depth=2)


def test_load_and_run_both_precisions(package):
    pkg = load_package(package)
    x = np.random.default_rng(0).random((6, 32, 32), dtype=np.float32)
    out = {}
    for prec in ("fp32", "int8"):
        m = FieldModel(pkg, prec, threads=1)
        y = m(x)
        assert y.shape == (15, 32, 32) and y.dtype == np.float32
        lo, hi = pkg.bounds()
        assert np.all(y >= lo[:, None, None] - 1e-6) and np.all(y <= hi[:, None, None] + 1e-6)
        out[prec] = y
    # the int8 model approximates the fp32 one (same random network, quantized)
    assert np.corrcoef(out["int8"].ravel(), out["fp32"].ravel())[0, 1] > 0.9


def test_denormalization_uses_bounds(tmp_path):
    bounds = {c: [0.0, 2.0] for c in CHANNELS}
    bounds["disp_z"] = [-3.0, -1.0]
    pkg = load_package(write_package(tmp_path / "p", size=16, width=2, depth=1, bounds=bounds, int8=False))
    m = FieldModel(pkg, "fp32")
    raw = m.run_normalized(np.zeros((6, 16, 16), np.float32))[0]
    y = m.denormalize(raw)
    assert np.allclose(y[2], -3.0 + 2.0 * raw[2], atol=1e-6)
    assert np.allclose(y[0], 2.0 * raw[0], atol=1e-6)


def test_missing_manifest(tmp_path):
    (tmp_path / "empty").mkdir()
    with pytest.raises(ModelPackageError, match="manifest.json: missing"):
        load_package(tmp_path / "empty")


def test_no_model_installed_message(tmp_path):
    with pytest.raises(ModelPackageError, match="no trained model is installed.*tensortouch train all"):
        find_package(root=tmp_path)


def test_corrupt_model_file_detected(package, tmp_path):
    import shutil

    bad = tmp_path / "bad"
    shutil.copytree(package, bad)
    data = bytearray((bad / "model.int8.onnx").read_bytes())
    data[len(data) // 2] ^= 0xFF
    (bad / "model.int8.onnx").write_bytes(data)
    with pytest.raises(ModelPackageError, match="model.int8.onnx: SHA-256 does not match"):
        load_package(bad)
    # even with hashes unchecked, a garbled graph gives a clear error, not a deep traceback
    (bad / "model.int8.onnx").write_bytes(b"not an onnx file")
    with pytest.raises(ModelPackageError, match="onnxruntime cannot load it"):
        FieldModel(load_package(bad, verify_hashes=False), "int8")


def test_shape_mismatch_detected(package, tmp_path):
    import shutil

    bad = tmp_path / "bad"
    shutil.copytree(package, bad)
    m = json.loads((bad / "manifest.json").read_text())
    m["input"]["size"] = [64, 64]
    m["output"]["size"] = [64, 64]
    (bad / "manifest.json").write_text(json.dumps(m))
    with pytest.raises(ModelPackageError, match="input H = 32, manifest says 64"):
        FieldModel(load_package(bad), "fp32")


def test_wrong_channels_and_bounds(package, tmp_path):
    import shutil

    bad = tmp_path / "bad"
    shutil.copytree(package, bad)
    m = json.loads((bad / "manifest.json").read_text())
    m["output"]["bounds"]["fn_z"] = [1.0, 0.0]
    (bad / "manifest.json").write_text(json.dumps(m))
    with pytest.raises(ModelPackageError, match="output.bounds.fn_z"):
        load_package(bad)
    m["output"]["channels"] = m["output"]["channels"][::-1]
    (bad / "manifest.json").write_text(json.dumps(m))
    with pytest.raises(ModelPackageError, match="output.channels"):
        load_package(bad)


def test_call_denormalizes_in_place_to_the_same_values(package):
    m = FieldModel(load_package(package), "int8")
    x = np.random.default_rng(3).random((6, 32, 32), dtype=np.float32)
    ref = m.denormalize(m.run_normalized(x)[0])
    out = m(x)
    assert out.dtype == np.float32 and out.flags.c_contiguous
    assert np.array_equal(out, ref)
