"""Speed work on the deploy path (docs/runtime.md "Speed"): the float16 conversion, publishing fields at
a reduced rate, and the runtime benchmark's fp32 source for int8-only packages."""
import json
import shutil
import time

import numpy as np
import pytest
from tensortouch.contracts import wire
from tensortouch.runtime.stages.model import PRECISION_FILES, load_package
from tensortouch.tools.bench.models import write_package


def test_to_float16_is_bit_identical_to_numpy_including_subnormals_overflow_nan():
    rng = np.random.default_rng(0)
    vals = rng.standard_normal(60_000) * 10.0 ** rng.integers(-10, 7, 60_000)
    special = [65504, 65519, 65520, 7e4, -1e9, np.inf, -np.inf, np.nan, 0.0, -0.0, 5.96e-8, 2.98e-8, 6.1e-5]
    arr = np.concatenate([vals, special]).astype(np.float32).reshape(1, 1, -1)
    with np.errstate(over="ignore"):
        ref = arr.astype(np.float16)
    assert np.array_equal(wire.to_float16(arr).view(np.uint16), ref.view(np.uint16))
    f64 = arr.astype(np.float64)                              # other dtypes: numpy's own cast
    with np.errstate(over="ignore"):
        assert np.array_equal(wire.to_float16(f64).view(np.uint16), f64.astype(np.float16).view(np.uint16))


def test_to_float16_is_fast_on_stress_sized_values():
    """MPa-scale fields are mostly float16 subnormals, where numpy's cast is ~50x slower."""
    fields = (np.random.default_rng(1).standard_normal((15, 128, 128)) * 1e-4).astype(np.float32)
    wire.to_float16(fields)

    def best(fn, n=15):
        out = []
        for _ in range(n):
            t0 = time.thread_time()
            fn()
            out.append(time.thread_time() - t0)
        return min(out)

    fast, slow = best(lambda: wire.to_float16(fields)), best(lambda: fields.astype(np.float16))
    assert fast < slow / 3, (fast, slow)


def test_fields_every_n_keeps_wrench_and_contacts_at_frame_rate():
    from tensortouch.runtime.apps.loop import LoopConfig, SensorLoop

    class Pub:
        def __init__(self):
            self.sent = {"fields": [], "contacts": [], "wrench": []}

        def publish_fields(self, fields, seq, t):
            self.sent["fields"].append(seq)

        def publish_contacts(self, contacts, seq, t):
            self.sent["contacts"].append(seq)

        def publish_wrench(self, f, tq, seq, t):
            self.sent["wrench"].append(seq)

    class R:
        def __init__(self, seq, fields):
            self.seq, self.t, self.fields, self.clusters = seq, 0.0, fields, []
            self.force_n = self.torque_nmm = np.zeros(3)

    pub = Pub()
    loop = SensorLoop(camera=None, pipeline=None, publisher=pub, config=LoopConfig(fields_every=3))
    for seq in range(1, 11):
        loop._publish(R(seq, None if seq <= 2 else np.zeros((15, 4, 4))))   # no fields before the baseline
    assert pub.sent["fields"] == [3, 6, 9]
    assert pub.sent["contacts"] == pub.sent["wrench"] == list(range(1, 11))


def _int8_only(pkg_folder, dest, run=None, cache=None):
    """An int8-only copy of a synthetic package, its manifest recording the fp32 as optional."""
    shutil.copytree(pkg_folder, dest)
    fp32 = dest / PRECISION_FILES["fp32"]
    man = json.loads((dest / "manifest.json").read_text())
    info = man["files"][PRECISION_FILES["fp32"]]
    info.update(optional=True, regenerate="tensortouch train export ... --with-fp32")
    if cache is not None:
        shutil.copyfile(fp32, cache)
        info["cache"] = str(cache)
    if run is not None:
        man.setdefault("training", {})["run"] = str(run)
    fp32.unlink()
    (dest / "manifest.json").write_text(json.dumps(man))
    return load_package(dest)


def test_bench_takes_fp32_from_the_build_cache_and_checks_its_hash(tmp_path):
    from tensortouch.tools.bench.runtime_bench import fp32_package

    src = write_package(tmp_path / "src", size=16, width=2, depth=1)
    pkg = _int8_only(src, tmp_path / "pkg", cache=tmp_path / "cached.onnx")
    assert not pkg.has("fp32")
    full, source = fp32_package(pkg, tmp_path / "work")
    assert "build cache" in source and full.has("fp32") and full.has("int8")
    assert full.sha256("fp32") == pkg.sha256("fp32")
    data = bytearray((tmp_path / "cached.onnx").read_bytes())           # a stale cache is not used
    data[len(data) // 2] ^= 0xFF
    (tmp_path / "cached.onnx").write_bytes(bytes(data))
    none, why = fp32_package(pkg, tmp_path / "work2")
    assert none is None and "names no recipe" in why and "cache" not in why.split(";")[-1]
    man = json.loads((tmp_path / "pkg" / "manifest.json").read_text())   # a package built from a recipe
    man["training"]["recipe"] = {"source": "hiera-qup-128", "hash": "0" * 64}
    (tmp_path / "pkg" / "manifest.json").write_text(json.dumps(man))
    none, why = fp32_package(load_package(tmp_path / "pkg"), tmp_path / "work3")
    assert none is None and f"train all --recipe {tmp_path / 'pkg' / 'manifest.json'}" in why


@pytest.mark.slow
def test_bench_regenerates_fp32_from_the_checkpoint(tmp_path):
    """No cache copy: the bench re-exports the run's best.pt; the deterministic export gives the hash."""
    pytest.importorskip("torch")
    import argparse

    from tensortouch.tools.bench.runtime_bench import fp32_package
    from tensortouch.tools.train.cli import register
    from tensortouch.tools.train.export import FP32

    parser = argparse.ArgumentParser()
    register(parser.add_subparsers(dest="command"))

    def cli(argv):
        a = parser.parse_args(argv)
        return a.func(a)

    data, run, models = tmp_path / "data", tmp_path / "run", tmp_path / "models"
    assert cli(["train", "synth", "--out", str(data), "--n", "12", "--size", "32", "--seed", "1"]) == 0
    assert cli(["train", "fit", "--data", str(data), "--out", str(run), "--epochs", "1", "--batch", "6",
                "--threads", "1"]) == 0
    assert cli(["train", "export", "--run", str(run), "--data", str(data), "--name", "t", "--models-dir",
                str(models), "--quantization-samples", "4", "--latency-runs", "2"]) == 0
    shutil.rmtree(run / "export")                                          # cache gone
    pkg = load_package(models / "t")
    full, source = fp32_package(pkg, tmp_path / "work")
    assert full is not None and "regenerated" in source and "same SHA-256" in source
    assert (full.folder / FP32).is_file()


def test_bench_runtime_runs_configs_interleaved_and_reports_ratios(capsys):
    """`tensortouch bench runtime` end to end on a small synthetic size (real capture, Zenoh loopback)."""
    import argparse

    from tensortouch.tools.bench.runtime_bench import add_arguments, run

    p = argparse.ArgumentParser()
    add_arguments(p)
    args = p.parse_args(["--source", "synthetic", "--sizes", "32", "--frames", "12", "--chunk", "4", "--fields-every", "3",
                         "--json"])
    assert run(args) == 0
    out = capsys.readouterr().out
    summary = json.loads(out.strip().splitlines()[-1])
    res = summary["results"]
    assert set(res) == {"32/fp32", "32/int8", "32/int8/fields÷3"}
    for r in res.values():
        assert r["frames"] == 12 and r["hz"] > 0 and 0 < r["cpu_ms_per_frame"] <= r["process_cpu_ms_per_frame"] + 0.01
        assert r["clusters_per_frame"] >= 0
        assert {"capture", "preprocess", "inference", "contacts", "publish", "end_to_end"} <= set(r["stages"])
    assert "int8 vs fp32 (same run, interleaved)" in out and "fp32 model: shipped in the package" in out
    st = summary["stages_previous_vs_current"]["32"]
    assert st["frames"] == 12                       # every timed int8 frame's fields, both cores timed on them
    for name in ("contacts", "fields_encoding"):
        assert st[name]["previous_ms"] > 0 and st[name]["current_ms"] > 0 and st[name]["ratio"] > 0
    assert "changed stages, previous → current core" in out


def test_bench_runtime_on_the_demo_recording_uses_its_unit_calibration(tmp_path, capsys):
    """`bench runtime` (default `--source demo`): the shipped demo recording through a copy of its unit's
    calibration (a tiny package at the demo's size; real capture, Zenoh loopback); the demo at another size is
    refused, naming the source that times any size."""
    import argparse

    from tensortouch.contracts.errors import CalibrationError
    from tensortouch.tools.bench.runtime_bench import add_arguments, demo_inputs, demo_size, run

    size = demo_size()
    pkg = write_package(tmp_path / "tiny", size=size, width=4, depth=2)
    p = argparse.ArgumentParser()
    add_arguments(p)
    args = p.parse_args(["--package", str(pkg), "--frames", "8", "--chunk", "4", "--json"])
    assert args.sizes is None and args.source == "demo"
    assert run(args) == 0
    out = capsys.readouterr().out
    summary = json.loads(out.strip().splitlines()[-1])
    assert summary["source"] == "demo" and summary["config"] == f"{size}/int8"
    assert set(summary["results"]) == {f"{size}/fp32", f"{size}/int8"}
    assert all(r["frames"] == 8 for r in summary["results"].values())
    assert "the shipped demo recording" in out
    with pytest.raises(CalibrationError, match="expected the package.s 32x32.*--source synthetic"):
        demo_inputs(tmp_path / "store", ["bench-0"], 32)
    from tensortouch.contracts.errors import CommandError

    with pytest.raises(CommandError, match="--source synthetic times any sizes"):
        run(p.parse_args(["--sizes", f"32,{size}", "--frames", "4"]))


def test_demo_inputs_copy_the_demo_tables_under_each_sensor_id(tmp_path):
    from tensortouch.contracts import paths
    from tensortouch.contracts.session import load_session
    from tensortouch.contracts.store import TABLES, CalibrationStore
    from tensortouch.tools.bench.runtime_bench import demo_inputs, demo_size

    video = demo_inputs(tmp_path, ["f0", "f1"], demo_size())
    session = load_session(paths.demo_dir())
    assert video == session.image_source()[1] and video.is_file()
    demo = CalibrationStore().load(session.sensor_id)
    for serial in ("f0", "f1"):
        cal = CalibrationStore(tmp_path).load(serial)
        assert cal.model_size == demo.model_size and cal.gel_center_px == demo.gel_center_px
        for k in TABLES:
            np.testing.assert_array_equal(getattr(cal, k), getattr(demo, k))
