"""Stage 7: ONNX export, int8 quantization, parity report and the model package (docs/model_package.md).

Everything is built in temp dirs; nothing is written to exported_models/. Packages ship int8 only
unless `--with-fp32`; the fp32 graph is left beside the checkpoint (<run>/export/<name>/)."""
import argparse
import hashlib
import json

import numpy as np
import pytest

torch = pytest.importorskip("torch")
onnx = pytest.importorskip("onnx")
ort = pytest.importorskip("onnxruntime")

from tensortouch.contracts.errors import ModelPackageError  # noqa: E402
from tensortouch.contracts.fields import CHANNEL_UNITS, CHANNELS, INPUT_CHANNELS  # noqa: E402
from tensortouch.contracts.paths import ROOT  # noqa: E402
from tensortouch.tools.train.cli import register  # noqa: E402
from tensortouch.tools.train.export import FP32, FP32_HALF, INT8, count_quantize_nodes, fp32_cache_path, verify_package  # noqa: E402

SIZE = 64


def _cli(argv):
    parser = argparse.ArgumentParser()
    register(parser.add_subparsers(dest="command"))
    args = parser.parse_args(argv)
    return args.func(args)


@pytest.fixture(scope="module")
def package(tmp_path_factory):
    """synth → fit (1 epoch, tiny) → export, all through the CLI handlers, in a temp models dir."""
    torch.set_num_threads(1)
    shipped = ROOT / "exported_models"
    before = sorted(p.name for p in shipped.iterdir()) if shipped.is_dir() else []
    tmp = tmp_path_factory.mktemp("pkg")
    data, run, models = tmp / "data", tmp / "run", tmp / "models"
    assert _cli(["train", "synth", "--out", str(data), "--n", "24", "--size", str(SIZE), "--seed", "3"]) == 0
    assert _cli(["train", "fit", "--data", str(data), "--out", str(run), "--epochs", "1", "--batch", "8",
                 "--threads", "1"]) == 0
    assert _cli(["train", "export", "--run", str(run), "--data", str(data), "--name", "tiny",
                 "--models-dir", str(models), "--quantization-samples", "8", "--latency-runs", "5"]) == 0
    assert (sorted(p.name for p in shipped.iterdir()) if shipped.is_dir() else []) == before
    return models / "tiny", data, run


def test_manifest_follows_the_contract(package):
    folder, data, run = package
    assert sorted(p.name for p in folder.iterdir()) == sorted(["manifest.json", INT8, FP32_HALF])  # no exact fp32
    man = json.loads((folder / "manifest.json").read_text())
    assert man["schema"] == "tensortouch.model" and man["schema_version"] == 1 and man["name"] == "tiny"
    assert man["input"] == {"name": "input", "layout": "NCHW", "size": [SIZE, SIZE], "dtype": "float32",
                            "channels": list(INPUT_CHANNELS), "range": [0.0, 1.0]}
    out = man["output"]
    assert out["channels"] == list(CHANNELS) and out["units"] == list(CHANNEL_UNITS)
    assert out["normalization"] == "minmax" and out["size"] == [SIZE, SIZE]
    bounds = json.loads((data / "bounds.json").read_text())["bounds"]
    assert out["bounds"] == bounds
    cached = fp32_cache_path(run, "tiny")
    for f, path in ((FP32, cached), (INT8, folder / INT8)):
        assert man["files"][f]["sha256"] == hashlib.sha256(path.read_bytes()).hexdigest()
    assert man["files"][FP32]["optional"] is True and "optional" not in man["files"][INT8]
    assert man["files"][FP32]["cache"] == str(cached.resolve())            # outside the repo: absolute
    assert man["files"][FP32]["regenerate"].endswith("--with-fp32")
    assert man["metrics"]["quantization"]["scheme"] == "hybrid"
    assert man["metrics"]["quantization"]["quantization_pick"] == "spread"
    assert man["metrics"]["quantization"]["quantization_samples"] == 8
    tr = man["training"]
    assert "train export" in tr["command"] and "--name tiny" in tr["command"]
    assert tr["data_hash"] == hashlib.sha256((data / "index.json").read_bytes()).hexdigest()
    assert len(tr["git_commit"]) in (40, 7) or tr["git_commit"] == "unknown"
    place = tr["run_place"]["fit"]                       # where the weights were trained (issue 42)
    assert len(place) == 1 and place[0]["from_step"] == 0
    assert place[0]["device"] == "cpu" and place[0]["precision"] == "float32" and place[0]["threads"] == 1
    assert place[0]["param_dtype"] == "float32" and place[0]["torch"] == torch.__version__
    assert json.loads((run / "train_config.json").read_text())["segments"] == place
    m = man["metrics"]
    for prec in ("fp32", "int8"):
        assert set(m[prec]) >= {"psnr", "ssim", "mse", "auc_rel", "fpr_rel"}
        assert m["latency_ms"][prec] > 0
    assert set(m["int8_vs_fp32_psnr"]) == {"displacement", "normal_stress", "shear_stress",
                                           "contact_normal", "contact_shear"}
    assert verify_package(folder)["name"] == "tiny"


def test_int8_calibration_inputs_are_spread_over_the_whole_train_split(package):
    """The dataset is written session by session: the first samples are one unit's first pokes."""
    from tensortouch.tools.train.model.data import load_sample, load_split, read_index, spread_indices

    assert spread_indices(10, 4) == [0, 3, 6, 9]
    assert spread_indices(3, 8) == [0, 1, 2] and spread_indices(5, None) == list(range(5))
    assert spread_indices(5, 0) == []
    _, data, _ = package
    train = [e for e in read_index(data)["samples"] if e.get("split") == "train"]
    x, _ = load_split(data, "train", limit=3, spread=True)
    want = [load_sample(data, train[i])[0] for i in (0, len(train) - 1)]
    assert len(x) == 3 and np.array_equal(x[0], want[0]) and np.array_equal(x[-1], want[-1])
    first, _ = load_split(data, "train", limit=3)
    assert np.array_equal(first[1], load_sample(data, train[1])[0])


def test_total_force_parity_in_newtons(package):
    """The parity report's int8 - fp32 total force: the runtime's integral of the traction channels."""
    from tensortouch.tools.train.export import parity_report, total_force_n
    from tensortouch.tools.train.model.data import load_split

    bounds = {c: [-1.0, 1.0] for c in CHANNELS}
    y = np.full((2, 15, 4, 4), 0.5, np.float32)                         # 0 MPa everywhere
    y[1, 9, 0, 0], y[1, 14, 1, 1] = 1.0, 0.0                            # fn_x +1 MPa, fs_z -1 MPa
    area = np.full((4, 4), 0.25)
    assert np.allclose(total_force_n(y, bounds, area), [[0, 0, 0], [0.25, 0, -0.25]])
    folder, data, run = package
    bounds = json.loads((data / "bounds.json").read_text())["bounds"]
    x, _ = load_split(data, "val")
    x = x.astype(np.float32) / 255.0
    ones = np.ones((SIZE, SIZE))
    fp32 = fp32_cache_path(run, "tiny")
    same = parity_report(fp32, fp32, x, bounds=bounds, pixel_area=ones)["int8_vs_fp32_force_n"]
    assert same == {"mean": 0.0, "p95": 0.0, "max": 0.0}
    rep = parity_report(fp32, folder / INT8, x, bounds=bounds, pixel_area=ones)["int8_vs_fp32_force_n"]
    assert 0.0 <= rep["mean"] <= rep["p95"] <= rep["max"] and np.isfinite(rep["max"])
    assert "int8_vs_fp32_force_n" not in parity_report(fp32, fp32, x)      # no area: PSNR only


def test_both_models_load_in_onnxruntime_and_agree(package):
    folder, _, run = package
    x = np.random.default_rng(0).random((1, 6, SIZE, SIZE), dtype=np.float32)
    outs = {}
    paths = {FP32: fp32_cache_path(run, "tiny"), INT8: folder / INT8}
    for f in (FP32, INT8):
        s = ort.InferenceSession(str(paths[f]), providers=["CPUExecutionProvider"])
        assert s.get_inputs()[0].name == "input" and s.get_outputs()[0].name == "fields"
        outs[f] = s.run(None, {"input": x})[0]
        assert outs[f].shape == (1, 15, SIZE, SIZE) and np.all(np.isfinite(outs[f]))
    mse = np.mean((outs[FP32] - outs[INT8]) ** 2)
    assert 0 < mse < 1e-2                                   # quantized, but close
    assert count_quantize_nodes(folder / INT8) > 10
    assert count_quantize_nodes(paths[FP32]) == 0


def test_runtime_fp32_on_an_int8_only_package_names_file_and_command(package):
    from tensortouch.runtime.stages.model import FieldModel, load_package

    folder, _, _ = package
    pkg = load_package(folder)                       # the optional fp32 is absent: still a valid package
    assert not pkg.has("fp32") and pkg.has("int8")
    with pytest.raises(ModelPackageError, match=r"model\.fp32\.onnx.*ships int8 only.*--with-fp32"):
        FieldModel(pkg, "fp32")
    assert FieldModel(pkg, "int8")(np.zeros((6, SIZE, SIZE), np.float32)).shape == (15, SIZE, SIZE)


def test_with_fp32_ships_both_and_the_fp32_graph_is_reproducible(package, tmp_path):
    """--with-fp32 re-exports the same run into a package holding both models; the fp32 graph is
    byte-identical to the one the int8-only export left in the build cache (same SHA-256)."""
    from tensortouch.runtime.stages.model import FieldModel, load_package

    folder, data, run = package
    models = tmp_path / "models"
    assert _cli(["train", "export", "--run", str(run), "--data", str(data), "--name", "tiny",
                 "--models-dir", str(models), "--quantization-samples", "8", "--latency-runs", "2", "--with-fp32"]) == 0
    both = models / "tiny"
    assert sorted(p.name for p in both.iterdir()) == sorted(["manifest.json", INT8, FP32])
    man = verify_package(both)
    assert "optional" not in man["files"][FP32] and "--with-fp32" in man["training"]["command"]
    first = json.loads((folder / "manifest.json").read_text())
    assert man["files"][FP32]["sha256"] == first["files"][FP32]["sha256"]
    x = np.random.default_rng(1).random((6, SIZE, SIZE), dtype=np.float32)
    y32, y8 = FieldModel(load_package(both), "fp32")(x), FieldModel(load_package(both), "int8")(x)
    assert y32.shape == y8.shape == (15, SIZE, SIZE) and not np.array_equal(y32, y8)


def test_half_weight_fp32_ships_at_half_size_and_serves_the_bench_from_a_clean_checkout(package, tmp_path):
    """An int8-only package ships the fp32 graph with float16-stored weights: about half the exact fp32
    graph's size, float32 in and out, outputs within the float16 rounding of the exact graph's (the PSNR
    the manifest records), and `bench runtime` runs it as fp32 when neither the build cache nor the
    checkpoint exists (a clean checkout)."""
    import shutil

    from tensortouch.runtime.stages.model import FieldModel, load_package
    from tensortouch.tools.bench.runtime_bench import fp32_package

    folder, _, run = package
    man = verify_package(folder)
    exact = fp32_cache_path(run, "tiny")
    half = folder / FP32_HALF
    assert half.stat().st_size < 0.6 * exact.stat().st_size
    info = man["metrics"]["fp32_half"]
    assert info["converted"] > 0 and info["bytes"] == half.stat().st_size and info["fp32_bytes"] == exact.stat().st_size
    assert info["vs_fp32_psnr_min"] > 60.0
    g = onnx.load(str(half)).graph
    assert g.input[0].type.tensor_type.elem_type == onnx.TensorProto.FLOAT
    assert any(i.data_type == onnx.TensorProto.FLOAT16 for i in g.initializer)
    x = np.random.default_rng(2).random((1, 6, SIZE, SIZE), dtype=np.float32)
    ye = ort.InferenceSession(str(exact), providers=["CPUExecutionProvider"]).run(None, {"input": x})[0]
    yh = ort.InferenceSession(str(half), providers=["CPUExecutionProvider"]).run(None, {"input": x})[0]
    assert yh.dtype == np.float32 and np.abs(yh - ye).max() < 1e-2 and not np.array_equal(yh, ye)

    clean = tmp_path / "clean" / "tiny"                 # the package as a clean checkout sees it
    shutil.copytree(folder, clean)
    m = json.loads((clean / "manifest.json").read_text())
    m["training"]["run"] = str(tmp_path / "no-such-run")
    m["files"][FP32]["cache"] = str(tmp_path / "no-such-cache.onnx")
    (clean / "manifest.json").write_text(json.dumps(m))
    full, source = fp32_package(load_package(clean), tmp_path / "work")
    assert full is not None and "float16-stored weights" in source and f"{info['vs_fp32_psnr_min']:.1f} dB" in source
    assert full.sha256("fp32") == m["files"][FP32_HALF]["sha256"]
    y = FieldModel(full, "fp32")(x[0])
    assert y.shape == (15, SIZE, SIZE) and np.isfinite(y).all()
    (clean / FP32_HALF).unlink()                        # an older package without it: the recipe message stays
    del m["files"][FP32_HALF]
    (clean / "manifest.json").write_text(json.dumps(m))
    none, why = fp32_package(load_package(clean), tmp_path / "work2")
    assert none is None and "no best.pt" in why


def test_optional_fp32_is_still_verified_when_present(package, tmp_path):
    import shutil

    folder, _, run = package
    bad = tmp_path / "bad"
    shutil.copytree(folder, bad)
    data = bytearray(fp32_cache_path(run, "tiny").read_bytes())
    data[-10] ^= 0xFF
    (bad / FP32).write_bytes(bytes(data))                       # a present optional file must match
    with pytest.raises(ModelPackageError, match="model.fp32.onnx"):
        verify_package(bad)
    (bad / FP32).unlink()
    man = json.loads((bad / "manifest.json").read_text())
    man["files"][INT8]["optional"] = True                       # int8 is never optional
    (bad / "manifest.json").write_text(json.dumps(man))
    with pytest.raises(ModelPackageError, match="model.int8.onnx"):
        verify_package(bad)


def test_tampered_package_is_rejected(package, tmp_path):
    import shutil

    folder, _, _ = package
    bad = tmp_path / "bad"
    shutil.copytree(folder, bad)
    data = bytearray((bad / INT8).read_bytes())
    data[-10] ^= 0xFF
    (bad / INT8).write_bytes(bytes(data))
    with pytest.raises(ModelPackageError, match="model.int8.onnx"):
        verify_package(bad)
    shutil.copy(folder / INT8, bad / INT8)
    man = json.loads((bad / "manifest.json").read_text())
    man["output"]["channels"] = man["output"]["channels"][::-1]
    (bad / "manifest.json").write_text(json.dumps(man))
    with pytest.raises(ModelPackageError, match="channels"):
        verify_package(bad)
    (bad / "manifest.json").unlink()
    with pytest.raises(ModelPackageError, match="manifest.json"):
        verify_package(bad)


def test_keypoints_cli_on_a_session(tmp_path):
    from tensortouch.contracts.session import STREAM_COLUMNS, new_manifest, write_manifest, write_table

    t = np.arange(0, 4, 1 / 120)
    z = 10 - 2.0 * np.clip(np.minimum(t - 0.5, 3.5 - t), 0, 1)
    x = np.interp(t, [0, 1.5, 2.0, 2.5, 4], [0, 0, 0.8, 0, 0])
    poses = np.stack([t, 0 * t, x, 0 * t, z, 1 + 0 * t, 0 * t, 0 * t, 0 * t], 1)
    tw = np.arange(0, 4, 1 / 200)
    wrench = np.zeros((tw.size, 8)); wrench[:, 0] = tw
    wrench[:, 4] = 2.0 * np.interp(tw, t, 10 - z)
    frames = np.stack([np.arange(0, 4, 1 / 30), np.arange(120)], 1)
    for name, arr in (("poses", poses), ("wrench", wrench), ("frames", frames)):
        write_table(tmp_path / f"{name}.csv", STREAM_COLUMNS[name], arr)
    write_manifest(tmp_path, new_manifest("TT-TEST", {
        "poses": {}, "frames": {"images": "frames"},
        "wrench": {"ft_to_indenter": {"rotation_wxyz": [1, 0, 0, 0], "translation_mm": [0, 0, 0]}}}))
    out = tmp_path / "kp.json"
    assert _cli(["train", "keypoints", str(tmp_path), "--out", str(out)]) == 0
    doc = json.loads(out.read_text())
    assert doc["schema"] == "tensortouch.keypoints" and len(doc["periods"]) == 1
    p = doc["periods"][0]
    assert p["indenters"] == [0] and min(abs(np.array(p["t"]) - 2.0)) < 0.1
    assert np.array(p["force"]).shape == (len(p["t"]), 1, 3)
    assert doc["config"]["contact_force_n"] == 1.5 and doc["config"]["detach_force_n"] == 1.1


