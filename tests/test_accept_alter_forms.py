"""Hidden effects in forms that are not the library's (tools/accept/alter_forms.py), on a small written
session: each form's contribution worked out by hand from the session's own streams."""
import numpy as np
import pytest
from tensortouch.contracts.session import load_session
from tensortouch.tools.accept.alter_forms import FORMS, _lowpass, contribution

from tests.test_session_format import _write

GEL = {"radius": 10.0, "center_z": 5.0, "skirt": 2.0}


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    root = tmp_path_factory.mktemp("forms") / "s"
    _write(root, "png", np.random.default_rng(0))
    return load_session(root, check_frames=False)


def test_zero_amplitude_changes_nothing_and_unknown_forms_are_named(session):
    f = session.table("wrench")[:, 2:5]
    for kind in FORMS:
        np.testing.assert_allclose(contribution(session, kind, 0.0, GEL), f, atol=1e-12, err_msg=kind)
    with pytest.raises(ValueError, match=r"hidden form 'warp': expected one of \('saturating_stiffening'"):
        contribution(session, "warp", 0.1, GEL)


def test_saturating_stiffening_and_temperature_onset_by_hand(session):
    w, p, tt = session.table("wrench"), session.table("poses"), session.table("temperature")
    t = w[:, 0]
    tip = np.column_stack([np.interp(t, p[p[:, 1] == 0][:, 0], p[p[:, 1] == 0][:, 2 + j]) for j in range(3)])
    d = np.clip(10.0 - np.linalg.norm(tip - [0, 0, 5.0], axis=1), 0, None)      # indentation below the cap
    np.testing.assert_allclose(contribution(session, "saturating_stiffening", 0.2, GEL),
                               w[:, 2:5] * (1 + 0.2 * np.tanh(d ** 2))[:, None], rtol=1e-12)
    T = np.interp(t, tt[:, 0], tt[:, 1])
    np.testing.assert_allclose(contribution(session, "temperature_onset", 0.5, GEL),
                               w[:, 2:5] * (1 - 0.5 * (np.clip(T - 24.0, 0, None) / 5.0) ** 2)[:, None], rtol=1e-12)


def test_lowpass_step_response_by_hand():
    t = np.array([0.0, 1.0, 2.0, 3.0])
    y = _lowpass(np.ones((4, 1)), t, tau=1.0)
    np.testing.assert_allclose(y[:, 0], [0.0, 1 - np.exp(-1), 1 - np.exp(-2), 1 - np.exp(-3)])


def test_scoring_forms_by_hand(session):
    w, p, tt = session.table("wrench"), session.table("poses"), session.table("temperature")
    t = w[:, 0]
    tip = np.column_stack([np.interp(t, p[p[:, 1] == 0][:, 0], p[p[:, 1] == 0][:, 2 + j]) for j in range(3)])
    d = np.clip(10.0 - np.linalg.norm(tip - [0, 0, 5.0], axis=1), 0, None)
    np.testing.assert_allclose(contribution(session, "cubic_stiffening", 0.3, GEL),
                               w[:, 2:5] * (1 + 0.3 * d ** 3)[:, None], rtol=1e-12)
    T = np.interp(t, tt[:, 0], tt[:, 1])
    mid = 0.5 * (tt[:, 1].min() + tt[:, 1].max())
    np.testing.assert_allclose(contribution(session, "logistic_temperature", 0.1, GEL),
                               w[:, 2:5] * (1 - 0.1 / (1 + np.exp(-(T - mid) / 0.5)))[:, None], rtol=1e-12)
    ramp = 0.2 * np.sqrt((t - t[0]) / 100.0)[:, None] * np.array([-0.5, 0.6, 0.8])
    np.testing.assert_allclose(contribution(session, "ft_offset_sqrt", 0.2, GEL), w[:, 2:5] + ramp, atol=1e-12)


def test_gain_of_gives_back_each_multiplicative_forms_gain(session):
    """gain_of recovers the per-row gain a multiplicative form put on the force, hand-worked for
    cubic_stiffening; the set of multiplicative forms is the forms whose altered/clean force is a
    scalar multiple row by row; shapes are checked."""
    from tensortouch.tools.accept.alter_forms import MULTIPLICATIVE, gain_of

    w, p = session.table("wrench"), session.table("poses")
    f = w[:, 2:5]
    tip = np.column_stack([np.interp(w[:, 0], p[p[:, 1] == 0][:, 0], p[p[:, 1] == 0][:, 2 + j]) for j in range(3)])
    d = np.clip(10.0 - np.linalg.norm(tip - [0, 0, 5.0], axis=1), 0, None)
    loaded = np.linalg.norm(f, axis=1) > 1e-6
    g = gain_of(contribution(session, "cubic_stiffening", 0.3, GEL), f)
    np.testing.assert_allclose(g[loaded], (1 + 0.3 * d ** 3)[loaded], rtol=1e-9)
    for kind in FORMS:
        alt = contribution(session, kind, 0.2, GEL)
        cross = np.linalg.norm(np.cross(alt, f), axis=1)
        assert (kind in MULTIPLICATIVE) == bool(np.all(cross <= 1e-9 * (1 + np.linalg.norm(f, axis=1) ** 2))), kind
    np.testing.assert_array_equal(gain_of(np.zeros((2, 3)), np.zeros((2, 3))), [1.0, 1.0])
    with pytest.raises(ValueError, match=r"gain_of: expected two \(N, 3\) force arrays"):
        gain_of(np.zeros((2, 3)), np.zeros(3))
