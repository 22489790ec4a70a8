"""Distributed FE batch (issue 26 item 5): a real local Dask.distributed cluster (scheduler + 2
worker processes on loopback) runs a small FE batch through the same code a remote cluster uses
(`run_batch(cluster=address)`); results are identical to the local process pool's, and cache,
failures and resume work the same."""
import json

import numpy as np
import pytest

pytest.importorskip("felupe")
pytest.importorskip("gmsh")
trimesh = pytest.importorskip("trimesh")
distributed = pytest.importorskip("distributed")

from tensortouch.tools.fe import load_result, save_scenario  # noqa: E402
from tensortouch.tools.fe.batch import run_batch  # noqa: E402
from tensortouch.tools.fe.scenario import GelGeometry, Indenter, Keypoint, MeshSettings, Scenario  # noqa: E402

PAD = GelGeometry(kind="flat_pad", size_x=10.0, size_y=10.0, thickness=4.0)
MESH = MeshSettings(size_top=1.0, size_inside=1.5, refine_depth=0.5)


def _scenario(depth, z0=4.0, shape="sphere", params=None, mesh_path=""):
    ind = Indenter(name="i", shape=shape, params=params or {"radius": 3.0}, mesh_path=mesh_path,
                   position=[0.0, 0.0, z0], keypoints=[Keypoint([0.0, 0.0, -depth]), Keypoint([0.3, 0.0, -depth])])
    return Scenario(gel=PAD, mesh=MESH, indenters=[ind], friction=2.2, name="small")


def _scenarios(folder):
    ball = trimesh.creation.icosphere(2, radius=2.5)
    ball.apply_translation([0, 0, 2.5])
    folder.mkdir(parents=True)
    ball.export(folder / "ball.stl")
    save_scenario(_scenario(0.4), folder / "a.json")
    save_scenario(_scenario(0.3, shape="mesh", params={}, mesh_path="ball.stl"), folder / "m.json")
    save_scenario(_scenario(0.5, z0=3.5), folder / "bad.json")  # starts inside the gel
    return folder


def _same(a, b):
    for name in ("U", "S", "RF", "RM", "CNORMF", "CSHEAR", "contact_owner", "CAREA", "base_reaction"):
        assert np.array_equal(getattr(a, name), getattr(b, name)), name
    assert a.scenario_json == b.scenario_json and a.scenario_hash == b.scenario_hash


def test_dask_cluster_batch_equals_local_pool(tmp_path):
    scen = _scenarios(tmp_path / "scen")
    local = run_batch([scen], out_dir=tmp_path / "local", workers=2)
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                                  dashboard_address=None) as cluster:
        address = cluster.scheduler_address
        assert address.startswith("tcp://127.0.0.1:")
        remote = run_batch([scen], out_dir=tmp_path / "dask", cluster=address)
        again = run_batch([scen], out_dir=tmp_path / "dask", cluster=address)  # resume: nothing to solve
    assert local["solved"] == remote["solved"] == 2 and local["failed"] == remote["failed"] == 1
    assert again["solved"] == 0 and again["cached"] == 2 and again["failed"] == 1
    idx_l = json.loads((tmp_path / "local" / "index.json").read_text())
    idx_d = json.loads((tmp_path / "dask" / "index.json").read_text())
    assert "penetrates" in idx_d[str(scen / "bad.json")]["error"]
    for name in ("a.json", "m.json"):
        h = idx_l[str(scen / name)]["hash"]
        assert idx_d[str(scen / name)]["hash"] == h
        _same(load_result(tmp_path / "local" / f"{h}.npz"), load_result(tmp_path / "dask" / f"{h}.npz"))


def test_unreachable_cluster_is_one_clear_error(tmp_path, monkeypatch):
    import tensortouch.tools.fe.batch as fb
    from tensortouch.tools.fe.errors import FEError

    monkeypatch.setattr(fb, "CONNECT_TIMEOUT", "2s")
    scen = tmp_path / "scen"
    save_scenario(_scenario(0.4), scen / "a.json")
    with pytest.raises(FEError, match="cannot connect"):
        run_batch([scen], out_dir=tmp_path / "c", cluster="tcp://127.0.0.1:9")
