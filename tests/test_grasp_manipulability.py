"""Yoshikawa's manipulability (tools/grasp/manipulability.py) on hand-worked Jacobians."""
import numpy as np
import pytest
from tensortouch.tools.grasp.manipulability import manipulability


def test_diagonal_jacobian_gives_the_product_of_its_gains():
    J = np.array([[1.0, 0, 0, 0], [0, 2.0, 0, 0], [0, 0, 3.0, 0]])   # J Jᵀ = diag(1, 4, 9), det 36
    assert manipulability(J) == pytest.approx(6.0)


def test_a_rotated_jacobian_keeps_its_volume_and_batches_keep_their_shape():
    c, s = np.cos(0.3), np.sin(0.3)
    R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
    J = np.array([[1.0, 0, 0, 0], [0, 2.0, 0, 0], [0, 0, 3.0, 0]])
    w = manipulability(np.stack([J, R @ J, 0.5 * J]))
    assert w.shape == (3,)
    np.testing.assert_allclose(w, [6.0, 6.0, 6.0 * 0.5 ** 3], rtol=1e-12)


def test_a_singular_jacobian_is_zero_not_nan():
    J = np.array([[1.0, 0, 0, 0], [2.0, 0, 0, 0], [0, 0, 3.0, 0]])   # two rows parallel: rank 2
    w = manipulability(J)
    assert np.isfinite(w) and w == pytest.approx(0.0, abs=1e-6)
    with pytest.raises(ValueError):
        manipulability(np.ones(3))            # not a matrix
