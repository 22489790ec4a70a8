"""The independent session alteration (tools/accept/alter.py): the copy drops the truth, and an F/T bias
drift and a temperature softening change wrench.csv by the amounts worked out by hand."""
import json

import numpy as np
import pytest
from tensortouch.contracts.session import load_session
from tensortouch.tools.accept.alter import _quat_matrix, alter_session, copy_without_truth

from tests.test_session_format import _write


@pytest.fixture
def session(tmp_path):
    _write(tmp_path / "s", "png", np.random.default_rng(0))
    (tmp_path / "s" / "truth").mkdir()
    (tmp_path / "s" / "truth" / "reaction.csv").write_text("t,fz\n0,1\n")
    return tmp_path / "s"


def test_the_copy_has_no_truth_and_says_what_it_is(session, tmp_path):
    dst = copy_without_truth(session, tmp_path / "c")
    assert not (dst / "truth").exists()
    m = json.loads((dst / "session.json").read_text())
    assert m["provenance"] == {"source": "altered copy (tools/accept/alter.py)"} and "truth" not in m
    np.testing.assert_allclose(load_session(dst).table("wrench"), load_session(session).table("wrench"))


def test_bias_drift_and_temperature_by_hand(session, tmp_path):
    before = load_session(session).table("wrench")
    w = load_session(alter_session(session, tmp_path / "b", "ft_bias", {"bx": 0.5, "by": 0.0, "bz": -1.0})).table("wrench")
    np.testing.assert_allclose(w[:, 2:5] - before[:, 2:5], np.outer(before[:, 0], [0.5, 0.0, -1.0]), atol=1e-6)
    np.testing.assert_allclose(w[:, 5:], before[:, 5:], atol=1e-9)           # torques untouched
    temp = load_session(session).table("temperature")
    w = load_session(alter_session(session, tmp_path / "t", "temperature", {"alpha": 0.03, "t_ref": 24.0})).table("wrench")
    gain = 1.0 - 0.03 * (np.interp(before[:, 0], temp[:, 0], temp[:, 1]) - 24.0)
    np.testing.assert_allclose(w[:, 2:5], before[:, 2:5] * gain[:, None], rtol=1e-5, atol=1e-6)
    with pytest.raises(ValueError, match="warp"):
        alter_session(session, tmp_path / "x", "warp", {})


def test_quaternion_matrix_by_hand():
    s = np.sqrt(0.5)
    R = _quat_matrix(np.array([[s, 0, 0, s], [2.0, 0, 0, 0]]))                # 90° about z; unnormalized identity
    np.testing.assert_allclose(R[0], [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-12)
    np.testing.assert_allclose(R[1], np.eye(3), atol=1e-12)
