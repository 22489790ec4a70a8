"""Twin recording survives FE non-convergence: a poke the real FE cannot solve (forced here with a
one-iteration Newton cap, no cutbacks, on a coarse mesh) is shortened to the last keypoint reached or
skipped, the session still finishes, truth/provenance say what happened, failures are remembered on
disk (a resume does not re-solve them), and a finished recording's Recorder gives the final plan.
Also: guided plans (recalibration pokes) and explicit unit variation."""
import json

import numpy as np
import pytest
from tensortouch.contracts.session import load_session
from tensortouch.tools.twin.record import RecordConfig, Recorder
from tensortouch.tools.twin.trajectory import GuidedConfig, TrajectoryConfig, apply_replans, plan_guided, shorten
from tensortouch.tools.twin.unit import TwinUnit

APEX = [0.0, 0.0, 8.0]
SIDE = [5.84127513, 0.0, 6.81591491]          # GelSurface().point_at(0.4, 0)


def _guided_cfg(serial="TWIN-RP", depths=(1.0, 1.0), **kw):
    pts = [APEX, SIDE]
    cfg = RecordConfig(serial=serial, physics="fe", frame_format="png",
                       guided=GuidedConfig(pts, list(depths), "sphere5", hold_s=0.2), **kw)
    cfg.rig.camera_fps = 10.0
    return cfg


def _air_then_deep(poke):
    """Keypoints: two tiny steps still above the surface (no contact: converge in one Newton
    iteration), then 1 mm deep in one step (needs several), hold, release."""
    nrm = -poke.translation[0, 1] / np.linalg.norm(poke.translation[0, 1])
    tr = np.array([[0 * n, -0.015 * n, -0.03 * n, -1.0 * n, -1.0 * n, 0.2 * n] for n in [nrm]], dtype=float)
    poke.translation, poke.rotvec = tr, np.zeros_like(tr)
    poke.times = poke.times[0] + np.linspace(0, poke.times[-1] - poke.times[0], tr.shape[1])
    return poke


def test_guided_plan_presses_at_points_along_the_normal():
    from tensortouch.tools.twin.geometry import GelSurface

    gel = GelSurface()
    g = GuidedConfig([APEX, SIDE], [1.2, 0.9], "sphere5", hold_s=1.0)
    plan = plan_guided(g, gel)
    assert [p.kind for p in plan] == ["press", "press"] and all(p.indenters == ["sphere5"] for p in plan)
    for p, depth in zip(plan, g.depths_mm):
        deepest = np.linalg.norm(p.translation[0], axis=1).max()
        assert deepest == pytest.approx(depth)
        hold = np.flatnonzero(np.all(np.isclose(np.diff(p.translation[0], axis=0), 0), axis=1))
        assert len(hold) == 1 and p.times[hold[0] + 1] - p.times[hold[0]] == pytest.approx(1.0)
        assert p.translation[0, -1] @ gel.normals(p.position)[0] > 0          # released above the surface
    assert plan[1].t_approach > plan[0].t_retreat_end


def test_shorten_keeps_times_and_releases_above_surface():
    from tensortouch.tools.twin.geometry import GelSurface

    p = plan_guided(GuidedConfig([APEX], [2.0], "sphere5"), GelSurface())[0]
    s = shorten(p, 2, TrajectoryConfig())
    np.testing.assert_array_equal(s.times[:3], p.times[:3])
    np.testing.assert_array_equal(s.translation[:, :3], p.translation[:, :3])
    assert s.times[-1] <= p.times[-1] and np.all(np.diff(s.times) > 0)
    assert s.translation[0, -1, 2] > 0 and s.extra["replanned"] == "shortened"
    assert shorten(p, 0) is None
    assert [q.extra.get("replanned") for q in apply_replans([p, p], [{"poke": 1, "action": "shortened",
                                                                       "last_keypoint": 2}])] == [None, "shortened"]
    assert len(apply_replans([p, p], [{"poke": 0, "action": "skipped"}])) == 1


def test_unit_override_and_key_compatibility():
    u = TwinUnit("TWIN-0001", override={"stiffness_scale": 1.2, "center_offset_px": [4, -3]})
    ref = TwinUnit("TWIN-0001")
    assert u.params.stiffness_scale == 1.2 and u.params.center_offset_px == (4.0, -3.0)
    assert u.params.focal_scale == ref.params.focal_scale                   # the rest from the serial
    assert u.gel_center_px[0] - ref.gel_center_px[0] == pytest.approx(4 - ref.params.center_offset_px[0])
    with pytest.raises(ValueError, match="override keys"):
        TwinUnit("X", override={"gel": 1})
    d = RecordConfig().to_dict()                  # unset new fields do not change earlier recordings' keys
    assert "unit" not in d and "guided" not in d


def test_fe_non_convergence_shortens_or_skips_and_session_finishes(tmp_path):
    """FE physics with a 1-iteration Newton cap (names the forced failure): poke 0 reaches keypoint 2
    in the air then fails at the deep step -> shortened; poke 1 fails at its first contact step -> skipped."""
    pytest.importorskip("felupe")
    from tensortouch.tools.fe import MeshSettings, SolverSettings
    from tensortouch.tools.twin.fe_physics import FEPhysics

    cache = tmp_path / "fe"

    def physics():
        return FEPhysics(mesh=MeshSettings(size_top=2.5, size_inside=4.0),
                         solver=SolverSettings(max_iterations=1, max_cutbacks=0, max_increment_mm=5.0, threads=1),
                         refine=(), cache=cache)

    cfg = _guided_cfg()
    rec = Recorder(cfg, tmp_path / "s", physics=physics())
    rec.planned[0] = rec.plan[0] = _air_then_deep(rec.plan[0])
    out = rec.run()
    s = load_session(out)
    truth = json.loads((out / "truth" / "truth.json").read_text())
    ev = truth["physics_events"]
    assert [(e["poke"], e["action"]) for e in ev] == [(0, "shortened"), (1, "skipped")], ev
    assert ev[0]["last_keypoint"] == 2 and "did not converge" in ev[1]["reason"]
    assert len(truth["plan"]) == 1 and truth["plan"][0]["replanned"] == "shortened"
    assert len(truth["fe_scenarios"]) == 1
    prov = s.manifest["provenance"]
    assert prov["pokes"] == 1 and prov["planned_pokes"] == 2
    assert [e["action"] for e in prov["replanned"]] == ["shortened", "skipped"]
    assert len(s.table("frames")) > 0 and np.isfinite(s.table("wrench")).all()
    failed = sorted(p.name for p in cache.glob("*.failed.json"))
    assert len(failed) == 2                       # both planned scenarios remembered as not converging
    # a second recording of the same plan re-uses the failure markers: nothing is solved again
    ph = physics()
    rec2 = Recorder(cfg, tmp_path / "s2", physics=ph)
    rec2.planned[0] = rec2.plan[0] = _air_then_deep(rec2.plan[0])
    rec2.run()
    assert ph.stats["solved"] == 0 and ph.stats["cached"] == 1
    assert json.loads((tmp_path / "s2" / "truth" / "truth.json").read_text())["physics_events"] == ev
    # the Recorder of a finished recording re-applies its replans (consumers zip plan with fe_scenarios)
    again = Recorder(cfg, out)
    assert len(again.plan) == 1 and again.plan[0].extra["replanned"] == "shortened" and len(again.planned) == 2
