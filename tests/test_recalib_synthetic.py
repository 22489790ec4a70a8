"""Synthetic recalibration units (tools/recalib/synthetic.py): the hidden gain by hand, and observations
whose model forces carry exactly that gain while the gauge reads the true force."""
import numpy as np
import pytest
from tensortouch.tools.recalib.synthetic import SyntheticUnit


def test_true_gain_by_hand():
    u = SyntheticUnit(stiffness_ratio=1.2, center_shift=(0.1, 0.0), radial_bias=0.25, magnitude_exp=0.05)
    # at the true centre (0.6, 0.5) and 2 N only the stiffness ratio is left
    assert u.true_gain(np.array([[0.6, 0.5]]), np.array([2.0]))[0] == pytest.approx(1.2)
    # 0.5 from the centre: r² = 0.25 / 0.25 = 1 → 1.2 · 1.25; at 4 N the magnitude term is 2^0.05
    g = u.true_gain(np.array([[0.1, 0.5], [0.6, 0.5]]), np.array([2.0, 4.0]))
    np.testing.assert_allclose(g, [1.2 * 1.25, 1.2 * 2 ** 0.05])


def test_observations_carry_the_hidden_gain_and_a_noiseless_gauge_reads_the_truth():
    u = SyntheticUnit(gauge_rel_noise=0.0, gauge_abs_noise_n=0.0)
    t = u.tables()
    uv_px = np.array([[16.0, 16.0], [10.0, 20.0]])
    f = np.array([1.5, 3.0])
    obs = u.observe(np.random.default_rng(0), uv_px, f, t)
    np.testing.assert_allclose(obs.ref_force, f)
    pred_mag = np.linalg.norm(obs.pred_force, axis=1)
    np.testing.assert_allclose(pred_mag * u.true_gain(uv_px / u.size, f), f)
    assert np.all(np.einsum("ij,ij->i", obs.pred_force, t["normals"][[16, 20], [16, 10]]) < 0)   # into the gel


def test_guided_pokes_are_reproducible_with_a_seed():
    u = SyntheticUnit()
    a, b = u.guided_pokes(np.random.default_rng(5), 6), u.guided_pokes(np.random.default_rng(5), 6)
    np.testing.assert_array_equal(a.pred_force, b.pred_force)
    np.testing.assert_array_equal(a.uv, b.uv)
    assert len(a.pred_force) == 6 and np.all((a.uv > 0) & (a.uv < 1))
