"""Procedural indenters (tools/fe/procedural.py): a deterministic, standardized set."""
import json

import numpy as np
import pytest

pytest.importorskip("felupe")
pytest.importorskip("gmsh")
trimesh = pytest.importorskip("trimesh")



def test_procedural_set_is_deterministic_and_standardized(tmp_path):
    from tensortouch.tools.fe.procedural import OBJECT_KINDS, TOP_HEIGHT, generate_set

    assert len(OBJECT_KINDS) >= 12
    a = generate_set(tmp_path / "a", seed=3, count=len(OBJECT_KINDS))
    b = generate_set(tmp_path / "b", seed=3, count=2)
    assert a[0].read_bytes() == b[0].read_bytes() and a[1].read_bytes() == b[1].read_bytes()
    manifest = json.loads((tmp_path / "a" / "manifest.json").read_text())["indenters"]
    assert {m["kind"] for m in manifest} == set(OBJECT_KINDS)
    for p in a:
        m = trimesh.load(p)
        assert m.is_watertight and len(m.split()) == 1
        assert m.bounds[0, 2] == pytest.approx(0, abs=1e-6) and m.bounds[1, 2] == pytest.approx(TOP_HEIGHT, abs=1e-3)
        low = m.vertices[m.vertices[:, 2] < 1e-6]
        assert np.linalg.norm(low, axis=1).min() < 1e-6  # a lowest point (the tip) at the origin
