"""Diagnosis made cheaper without changing its numbers: the memoized correction forest
(tools/workbench/fastpost.py), the per-table series split, contact-free block edges and the
calibration-baseline sign-flip test. Real scikit-learn forest -> real ONNX -> real onnxruntime."""
import numpy as np
import pytest
from tensortouch.runtime.stages.correction import ForceCorrection
from tensortouch.runtime.stages.effects import EffectChain, Registry
from tensortouch.tools.workbench.diagnose import DiagnoseConfig, diagnose, sign_flip_pvalue, time_blocks
from tensortouch.tools.workbench.fastpost import memo_gain
from tensortouch.tools.workbench.fit import Channels

from tests.workbench_synth import synth_table


@pytest.fixture(scope="module")
def correction(tmp_path_factory):
    from tensortouch.tools.recalib.fit import FitConfig, PokeSet, fit_forest, to_onnx

    rng = np.random.default_rng(3)
    n = 600
    f = rng.normal(size=(n, 3)) * rng.uniform(0.1, 3.0, (n, 1))
    uv, tp = rng.uniform(0, 1, (n, 2)), np.column_stack([rng.uniform(0, 1.2, n), rng.uniform(-3, 3, n)])
    mag = np.linalg.norm(f, axis=1)
    ref = mag * (0.6 + 0.2 * tp[:, 0] + 0.1 * np.tanh(mag - 1)) + rng.normal(0, 0.02, n)
    fc = FitConfig(inputs=("fmag", "theta", "u", "v"), n_estimators=20, max_depth=6, min_samples_leaf=5)
    rf = fit_forest(PokeSet(f, ref, uv, tp), fc)
    path = tmp_path_factory.mktemp("corr") / "correction.onnx"
    path.write_bytes(to_onnx(rf, 4, fc))
    spec = {"file": path.name, "inputs": list(fc.inputs), "output": "gain", "kind": "random_forest_gain"}
    return ForceCorrection(path, spec), f, uv, tp


def test_memoized_correction_is_bit_identical_to_the_runtime_correction(correction):
    corr, f, uv, tp = correction
    memo = memo_gain(corr, uv, tp)
    assert memo is not None and len(memo.t) > 10
    rows = np.arange(len(f))
    rng = np.random.default_rng(0)
    for scale in [np.ones((len(f), 1)), 1.05 * np.ones((len(f), 1)), rng.uniform(0.3, 2.0, (len(f), 1)),
                  np.ones((len(f), 1))]:
        x = f * scale
        assert np.array_equal(memo(x, rows), corr(x, uv, tp))
    sub = rows[::3]
    assert np.array_equal(memo(f[sub] * 0.97, sub), corr(f[sub] * 0.97, uv[sub], tp[sub]))
    assert memo.stats["evaluated"] < memo.stats["rows"]          # repeated intervals were not re-run


def test_memo_declines_corrections_it_cannot_describe(correction):
    corr, f, uv, tp = correction
    other = ForceCorrection(corr.path, dict(corr.spec, inputs=["fx", "theta", "u", "v"]))
    assert memo_gain(other, uv, tp) is None


def test_series_split_gives_the_numbers_of_effect_apply():
    reg = Registry.default(entry_points=False)
    table = synth_table(1, n_pokes=8, rate=25.0)
    ch = Channels(table, EffectChain())
    eff = reg.get("viscoelastic_relaxation")
    p = {"g1": 0.3, "tau": 0.7}
    x = table.model.copy()
    series = table.cov()["series"]
    x[series == series[0]] = 0.0          # one all-zero series: skipped, must still be zero
    assert np.array_equal(ch.apply(eff, x, p), eff.apply(x, table.cov(), p))


def test_viscoelastic_declares_zero_in_zero_out_truthfully():
    eff = Registry.default(entry_points=False).get("viscoelastic_relaxation")
    t = np.cumsum(np.random.default_rng(1).uniform(0.01, 0.05, 200))
    out = eff.forward(np.zeros((200, 3)), {"time": t}, {"g1": 0.5, "tau": 0.3})
    assert eff.zero_in_zero_out and np.array_equal(out, np.zeros((200, 3)))


def test_block_edges_move_to_contact_free_moments():
    t = np.arange(0, 100, 0.02)
    contact = (t % 10) < 8.0                        # presses of 8 s, 2 s gaps
    b = time_blocks(t, 10, contact)
    edges = t[1:][np.diff(b) > 0]
    assert len(edges) == 9 and not contact[np.searchsorted(t, edges)].any()


def test_baseline_shifts_the_null_of_the_sign_flip_test():
    rng = np.random.default_rng(2)
    before = rng.uniform(1.0, 2.0, 16)
    after = before * (1 - 0.15) ** 2 * rng.uniform(0.97, 1.03, 16)   # ~15 % rms reduction in every block
    assert sign_flip_pvalue(before - after) < 0.001
    kept = (1 - 0.15) ** 2                              # the calibration session shows the same 15 %
    assert sign_flip_pvalue(before * kept - after) > 0.05


def test_calibration_baseline_makes_an_equal_reduction_not_significant():
    reg = Registry.default(entry_points=False)
    table = synth_table(4, n_pokes=30, rate=25.0, truth=[("rim_stiffening", {"a": 0.4, "w": 3.0})])
    plain = diagnose(table, reg, cfg=DiagnoseConfig(), candidates=["rim_stiffening"])
    assert plain.verdict is not None
    red = plain.ranking[0].reduction
    with_base = diagnose(table, reg, candidates=["rim_stiffening"], baseline={"rim_stiffening": red})
    assert with_base.verdict is None and with_base.ranking[0].p_value > plain.ranking[0].p_value
