"""`tensortouch train weights`: a model package's ONNX weights back into the training network
(tools/train/from_package.py), so a fine-tune can start from what ships. Tiny packages in temp dirs."""
import json
import shutil

import numpy as np
import pytest

torch = pytest.importorskip("torch")
onnx = pytest.importorskip("onnx")

from tensortouch.contracts.errors import ModelPackageError  # noqa: E402
from tensortouch.tools.train.export import FP32, INT8  # noqa: E402
from tensortouch.tools.train.from_package import assemble, dequantized, id_positions, state_dict_from_package  # noqa: E402

from tests.test_train_export import SIZE, _cli, package  # noqa: E402,F401  (package: the tiny int8 package)


@pytest.fixture(scope="module")
def built(package, tmp_path_factory):  # noqa: F811 (fixture)
    """test_train_export's tiny run re-exported with both graphs (fp32 + int8) into a temp models dir."""
    _, data, run = package
    models = tmp_path_factory.mktemp("frompkg")
    assert _cli(["train", "export", "--run", str(run), "--data", str(data), "--name", "tiny", "--models-dir",
                 str(models), "--quantization-samples", "8", "--latency-runs", "2", "--with-fp32"]) == 0
    return models / "tiny", data, run


def _trained(run):
    return torch.load(run / "best.pt", weights_only=True, map_location="cpu")


def test_fp32_graph_gives_back_the_trained_weights_exactly(built):
    folder, _, run = built
    state, info = state_dict_from_package(folder)              # "best" = the fp32 graph when shipped
    ref = _trained(run)
    assert info["precision"] == "fp32" and info["rewritten_graph"] and sorted(state) == sorted(ref)
    for k in ref:
        assert torch.allclose(state[k], ref[k], atol=1e-6, rtol=0), k


def test_int8_graph_gives_the_weights_within_their_quantization_step(built):
    folder, _, run = built
    state, info = state_dict_from_package(folder, "int8")
    ref = _trained(run)
    assert info["precision"] == "int8" and info["file"] == INT8
    worst = 0.0
    for k, w in ref.items():
        step = float(w.abs().max()) / 127.0 + 1e-6          # per-tensor int8 step bounds the per-channel one
        err = float((state[k] - w).abs().max())
        assert err <= 0.51 * step + 1e-6, (k, err, step)
        worst = max(worst, err)
    assert worst > 0.0                                        # it did read the rounded int8 weights


def test_the_network_from_the_package_computes_what_the_package_computes(built):
    import onnxruntime as ort
    from tensortouch.tools.train.model import build_model

    folder, _, run = built
    info = json.loads((run / "metrics.json").read_text())
    model = build_model(info["arch"], SIZE)
    model.load_state_dict(state_dict_from_package(folder, "fp32")[0], strict=True)
    x = np.random.default_rng(2).random((6, SIZE, SIZE), dtype=np.float32)
    with torch.no_grad():
        y = model.eval()(torch.from_numpy(x[None]))[0].numpy()
    sess = ort.InferenceSession(str(folder / FP32), providers=["CPUExecutionProvider"])
    y32 = sess.run(None, {"input": x[None]})[0][0]            # normalized outputs, as the torch model's
    assert np.abs(y - y32).max() < 1e-4


def test_cli_writes_state_dict_bounds_and_provenance_and_a_fit_starts_from_it(built, tmp_path):
    from tensortouch.tools.train.model.train import FitConfig, fit

    folder, data, run = built
    out = tmp_path / "init"
    assert _cli(["train", "weights", str(folder), "--out", str(out), "--precision", "int8"]) == 0
    assert sorted(p.name for p in out.iterdir()) == ["best.pt", "bounds.json", "from_package.json"]
    prov = json.loads((out / "from_package.json").read_text())
    man = json.loads((folder / "manifest.json").read_text())
    assert prov["sha256"] == man["files"][INT8]["sha256"] and prov["params"] > 0
    assert json.loads((out / "bounds.json").read_text())["bounds"] == man["output"]["bounds"]
    res = fit(data, tmp_path / "ft", FitConfig(epochs=1, batch_size=8, threads=1, init_from=str(out / "best.pt")))
    assert np.isfinite(res["metrics"]["mean"]["psnr"])


def test_a_graph_of_another_architecture_is_refused_with_the_reason(built, tmp_path):
    folder, _, _ = built
    other = tmp_path / "tiny"
    shutil.copytree(folder, other)
    man = json.loads((other / "manifest.json").read_text())
    man["metrics"]["arch"] = "unet"
    (other / "manifest.json").write_text(json.dumps(man))
    with pytest.raises(ModelPackageError, match="not the same architecture|not in the package"):
        state_dict_from_package(other, "fp32")
    with pytest.raises(ModelPackageError, match="no model.fp32.onnx"):
        (other / FP32).unlink()
        man["files"].pop(FP32, None)
        (other / "manifest.json").write_text(json.dumps(man))
        state_dict_from_package(other, "fp32")


def test_core_dequantizes_per_channel_and_maps_ids():
    q = np.array([[2, -4], [10, 0]], np.int8)
    inits = {"w_quantized": q, "w_scale": np.array([0.5, 0.1], np.float32),
             "w_zero_point": np.array([0, 0], np.int8),
             "b_quantized": np.array([30], np.int32), "b_quantized_scale": np.array(0.01, np.float32)}
    v = dequantized(inits)
    assert np.allclose(v["w"], [[1.0, -2.0], [1.0, 0.0]]) and np.allclose(v["b"], [0.3])
    from tensortouch.tools.train.from_package import ID0
    tpl = {"w": np.array([[ID0 + 1, 0.0], [ID0 + 0, ID0 + 2]], np.float32), "const": np.array([1.0, ID0 + 1])}
    pos = id_positions(tpl, 3)
    assert list(pos) == ["w"]                                 # a folded constant is not a weight
    theta = assemble(pos, {"w": np.array([[7.0, 0.0], [6.0, 8.0]])}, 3)
    assert theta.tolist() == [6.0, 7.0, 8.0]
    with pytest.raises(ModelPackageError, match="not in the package's graph"):
        assemble(pos, {"w": np.zeros((2, 2))}, 4)
