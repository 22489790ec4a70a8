"""Closed-form hyperelastic materials (tools/fe/materials.py) against felupe's automatic differentiation."""
import numpy as np
import pytest

pytest.importorskip("felupe")

from tensortouch.tools.fe.materials import YeohUmat, felupe_reference_umat  # noqa: E402
from tensortouch.tools.fe.scenario import Material  # noqa: E402

# ---------------------------------------------------------------- scenario contract


# ---------------------------------------------------------------- result contract


# ---------------------------------------------------------------- material: two formulations


def _random_F(seed=1, scale=0.25, shape=(4, 6)):
    rng = np.random.default_rng(seed)
    return np.eye(3)[:, :, None, None] + scale * rng.normal(size=(3, 3, *shape))


@pytest.mark.parametrize("model", ["yeoh", "neo_hookean"])
def test_closed_form_material_matches_felupe_autodiff(model):
    m = Material(model=model)
    F = _random_F()
    sv = np.zeros((0, *F.shape[2:]))
    ours = YeohUmat(m.C10, m.C20 if model == "yeoh" else 0, m.C30 if model == "yeoh" else 0, 3.0)
    ref = felupe_reference_umat(m, 3.0)
    P, Pr = ours.gradient([F, sv])[0], ref.gradient([F, sv])[0]
    A, Ar = ours.hessian([F, sv])[0], ref.hessian([F, sv])[0]
    assert np.abs(P - Pr).max() < 1e-10 * np.abs(Pr).max()
    assert np.abs(A - Ar).max() < 1e-10 * np.abs(Ar).max()
    h = 1e-6  # and the tangent is the derivative of the stress
    i, j = 1, 2
    Fp, Fm = F.copy(), F.copy()
    Fp[i, j] += h
    Fm[i, j] -= h
    dP = (ours.gradient([Fp, sv])[0] - ours.gradient([Fm, sv])[0]) / (2 * h)
    assert np.abs(dP - A[:, :, i, j]).max() < 1e-6 * np.abs(A).max()
