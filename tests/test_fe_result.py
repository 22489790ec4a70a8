"""The FE result contract (tools/fe/result.py): round trip without pickle, unconverged and corrupt files
refused."""
import numpy as np
import pytest

pytest.importorskip("felupe")

from tensortouch.tools.fe import (  # noqa: E402
    FEResultError,
    load_result,
    save_result,
    standard_dome,
)

# ---------------------------------------------------------------- scenario contract


# ---------------------------------------------------------------- result contract


def _fake_result(F=2, N=5, K=1, converged=True):
    from tensortouch.tools.fe.result import FEResult

    z = np.zeros
    return FEResult(nodes=np.random.default_rng(0).normal(size=(N, 3)), tets=np.array([[0, 1, 2, 3]]),
                    surface_nodes=np.arange(4), surface_tris=np.array([[0, 1, 2]]), fixed_nodes=np.array([4]),
                    U=z((F, N, 3)), S=z((F, N, 6)), CNORMF=z((F, N, 3)), CSHEAR=z((F, N, 3)),
                    contact_owner=np.full((F, N), -1), CAREA=z((F, K)), RF=np.ones((F, K, 3)), RM=z((F, K, 3)),
                    pose_position=z((F, K, 3)), pose_rotation=z((F, K, 3)),
                    converged=np.full(F, converged), base_reaction=z((F, 3)), seconds=z(F),
                    indenter_names=np.array(["a"] * K), scenario_json=standard_dome().to_json())


def test_result_roundtrip_no_pickle(tmp_path):
    r = _fake_result()
    path = save_result(r, tmp_path / "r.npz")
    assert not list(tmp_path.glob("*.tmp"))
    back = load_result(path)
    assert np.array_equal(back.nodes, r.nodes) and back.scenario().hash() == standard_dome().hash()
    with np.load(path, allow_pickle=False) as data:
        assert "U" in data.files


def test_result_refuses_unconverged_and_corrupt(tmp_path):
    with pytest.raises(FEResultError, match="unconverged"):
        save_result(_fake_result(converged=False), tmp_path / "r.npz")
    assert not (tmp_path / "r.npz").exists()
    bad = _fake_result()
    bad.S = np.zeros((2, 5, 3))
    with pytest.raises(FEResultError, match="S has shape"):
        save_result(bad, tmp_path / "r.npz")
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(FEResultError, match="not a readable"):
        load_result(tmp_path / "junk.npz")
