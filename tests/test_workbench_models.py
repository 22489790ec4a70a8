"""The workbench's nominal contact law (tools/workbench/models.py): a hand-made law predicted by hand
(interpolated, extended, capped by friction, zero out of contact), a fit recovering a known curve, and
storage with a schema."""
import numpy as np
import pytest
from tensortouch.contracts.errors import TensorTouchError
from tensortouch.tools.workbench.models import ContactLaw, LawConfig
from tensortouch.tools.workbench.table import SampleTable


def _table(depth, slip, theta=None, meas=None):
    n = len(depth)
    cols = {"t": np.arange(n) * 0.01, "series": np.zeros(n), "time": np.arange(n) * 0.01,
            "depth": np.asarray(depth, float), "theta": np.zeros(n) if theta is None else np.asarray(theta, float)}
    vec = {"normal": np.tile([0.0, 0.0, 1.0], (n, 1)), "slip_vec": np.asarray(slip, float)}
    meas = np.zeros((n, 3)) if meas is None else meas
    return SampleTable(cols, meas, np.zeros((n, 3)), vec, {"indenters": {"0": "sphere5"}})


def test_a_hand_made_law_predicted_by_hand():
    law = ContactLaw({"sphere5": {"knots": [0.0, 1.0, 2.0], "w": [0.0, 1.0, 3.0], "ct": 0.5}}, mu=0.5)
    t = _table([0.5, 1.5, 3.0, 0.0, 1.0], [[0, 0, 0], [0, 0, 0], [0, 0, 0], [1, 0, 0], [4.0, 0, 0]])
    f = law.predict(t)
    np.testing.assert_allclose(f[:3, 2], [0.5, 2.0, 5.0])     # interpolated; beyond 2 mm the last slope (2 N/mm)
    np.testing.assert_allclose(f[3], 0.0)                       # no depth: no force, slip or not
    np.testing.assert_allclose(f[4], [0.5, 0, 1.0])             # ct·√1·4 = 2 N capped at mu·Fn = 0.5 N
    with pytest.raises(TensorTouchError, match=r"presses with indenter 'sphere5', which none of its calibration sessions used \(it knows \['other'\]\)"):
        ContactLaw({"other": law.laws["sphere5"]}).predict(t)


def test_fit_recovers_a_known_curve_and_round_trips(tmp_path):
    rng = np.random.default_rng(0)
    d = rng.uniform(0.0, 2.0, 400)
    slip = np.column_stack([rng.normal(0, 0.1, 400), rng.normal(0, 0.1, 400), np.zeros(400)])
    truth = ContactLaw({"sphere5": {"knots": [0.0, 2.0], "w": [0.0, 4.0], "ct": 0.3}}, mu=2.2)
    meas = truth.predict(_table(d, slip))
    law = ContactLaw.fit(_table(d, slip, theta=rng.uniform(0, 1, 400), meas=meas), LawConfig(knots=6, theta_knots=1))
    np.testing.assert_allclose(law.predict(_table(d, slip)), meas, atol=0.02)
    law.save(tmp_path / "law.json")
    back = ContactLaw.load(tmp_path / "law.json")
    assert back.fingerprint() == law.fingerprint() and back.mu == 2.2
    (tmp_path / "bad.json").write_text('{"schema": "other", "laws": {}, "mu": 1}')
    with pytest.raises(TensorTouchError, match="expected 'tensortouch.contact_law'"):
        ContactLaw.load(tmp_path / "bad.json")
    with pytest.raises(TensorTouchError, match="no indenter has enough contact samples"):
        ContactLaw.fit(_table(d[:5], slip[:5], meas=meas[:5]))
