"""The recalibration's replay cache (tools/recalib/replay.py) is keyed by the package's pipeline
configuration too: re-measuring a package's contact threshold / support / merging invalidates it.
The network run itself is replaced by a counter (the test is about the key, not the model)."""
from types import SimpleNamespace

import numpy as np

from runtime.contacts import Cluster
from tools.recalib import replay


def _cal():
    z = np.zeros((4, 4))
    return SimpleNamespace(theta=z, phi=z, surface_xyz=np.zeros((4, 4, 3)), pixel_area=z + 0.04,
                           mask=np.ones((4, 4), bool), gel_center_px=(2.0, 2.0), gel_radius_px=2.0)


def test_cache_key_follows_the_packages_measured_pipeline_config(tmp_path, monkeypatch):
    runs = []

    def fake_run(session_dir, cal, package, precision):       # stands in for the network pass
        runs.append(package.manifest["runtime"].get("contact_support_radius_px"))
        c = Cluster(id=0, centroid_px=(1.0, 1.0), centroid_mm=(0.0, 0.0, 0.0), normal=(0.0, 0.0, 1.0), area_mm2=1.0,
                    force_n=(0.0, 0.0, -1.0), force_mag_n=1.0, pixels=3, perimeter_px=6.0, circularity=1.0)
        return [(0.0, [c]), (0.1, [])]

    monkeypatch.setattr(replay, "_run_pipeline", fake_run)
    pkg = SimpleNamespace(sha256=lambda precision: "abc", manifest={"runtime": {"contact_threshold_n": 0.002}})
    session = tmp_path / "session-x"
    first = replay.collect_frames(session, _cal(), pkg, "int8", cache=tmp_path / "cache")
    again = replay.collect_frames(session, _cal(), pkg, "int8", cache=tmp_path / "cache")
    assert len(runs) == 1 and len(again) == 2 and again[0][1][0].force_mag_n == first[0][1][0].force_mag_n
    pkg.manifest["runtime"]["contact_support_radius_px"] = 30.0          # re-measured package
    replay.collect_frames(session, _cal(), pkg, "int8", cache=tmp_path / "cache")
    assert runs == [None, 30.0]
