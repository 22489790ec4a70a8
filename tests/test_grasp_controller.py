"""The selective grasp controller (tools/grasp/controller.py): its decision on synthetic contacts, its
scores and goals, and the trial verdict."""
import ast
from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from tensortouch.tools.grasp import graph as graph_mod
from tensortouch.tools.grasp.controller import ControllerConfig, SelectiveGraspController
from tensortouch.tools.grasp.sensor_mount import SensorMount


def _line_graph(half_m: float = 0.008):
    """Nine pinches along world x (±`half_m`), fingertips above/below, sensor pads facing the pinch."""
    n = 9
    xs = np.linspace(-half_m, half_m, n)
    q = np.stack([xs * 10, np.zeros(n)], 1)
    point = np.stack([xs, np.zeros(n), np.zeros(n)], 1)
    normal = np.tile([0, 0, 1.0], (n, 1))
    Tt, Ti = np.tile(np.eye(4), (n, 1, 1)), np.tile(np.eye(4), (n, 1, 1))
    # thumb above looking down (pad +x_tip → world −z), index below looking up (pad → +z)
    Tt[:, :3, :3] = np.array([[0, 0, 1], [0, 1, 0], [-1, 0, 0]])
    Ti[:, :3, :3] = np.array([[0, 0, -1], [0, 1, 0], [1, 0, 0]])
    Tt[:, :3, 3] = point + [0, 0, 0.012]
    Ti[:, :3, 3] = point - [0, 0, 0.012]
    edges, w = graph_mod.knn_edges(q, 2)
    z = np.zeros((n, 3))
    return graph_mod.ContactGraph(q, point, normal, z, z, z, z, Tt, Ti, edges, w, np.array([4.3, 0.0]))


def _decide(ctrl, frame, frames: int = 8):
    """Feed both sensors `frames` frames of `frame(sensor, k)` while watching; the controller's decision."""
    ctrl.watch()
    d = None
    for k in range(frames):
        for s in ("thumb", "index"):
            ctrl.on_contacts(s, frame(s, k))
        d = ctrl.update() or d
    assert d is not None
    return d


def _frame(contacts):
    return SimpleNamespace(seq=0, contacts=[SimpleNamespace(position_mm=p, force_n=f, normal=(0, 0, 1.0), area_mm2=10.0)
                                            for p, f in contacts])


def _on_gel(mount, T, world):
    u = T[:3, :3].T @ (world - T[:3, 3])
    return mount.direction_to_gel(u / np.linalg.norm(u))


def _pinch(objs=((-0.0035, 0, 0), (0.0035, 0, 0)), start: int = 4):
    """The line graph pinching objects (world m) at node `start`: (graph, start, mount, objects, where
    each gel sees each object {sensor: [gel mm]})."""
    g, m = _line_graph(), SensorMount()
    objs = [np.array(o, float) for o in objs]
    pos = {"thumb": [_on_gel(m, g.tip_thumb[start], o) for o in objs],
           "index": [_on_gel(m, g.tip_index[start], o) for o in objs]}
    return g, start, m, objs, pos


def test_controller_names_the_sheared_object_and_plans_past_it():
    g, start, m, objs, pos = _pinch()
    ctrl = SelectiveGraspController(g, start, m, ControllerConfig(confirm_frames=2))
    ctrl.watch()

    def send(shear_on):
        for s in ("thumb", "index"):
            # a pull along the objects' length (world y: gel −y on both sensors) shears the gel along it
            fs = [np.array([0, 0, -1.0]) + (np.array([0, -0.4, 0]) if k == shear_on else 0) for k in range(2)]
            ctrl.on_contacts(s, _frame(list(zip(pos[s], fs))))
        return ctrl.update()

    for _ in range(4):
        assert send(None) is None          # the reference
    assert send(1) is None                 # first sighting, not yet confirmed
    d = send(1)
    assert d is not None
    assert np.linalg.norm(d.moving_point - [0.0035, 0, 0]) < 0.0015
    assert d.path[0] == start and g.point[d.goal][0] > 0.0035   # beyond the moving object
    times, qs = ctrl.trajectory()
    assert len(qs) == len(d.path) and np.all(np.diff(times) > 0)


def test_controller_scores_shear_change_per_newton_of_load():
    """A light cable pulled beside a heavily loaded neighbour that picks up more shear by crosstalk:
    per newton of its reference force the pulled one leads; a cluster only one fingertip feels
    (a spurious edge of a contact) does not compete."""
    g, start, m, objs, pos = _pinch(((-0.0035, 0, 0), (0.0035, 0, 0), (0.009, 0, 0)))
    load = [1.0, 3.0, 0.35]
    # shear per sensor once pulled: object 0 (pulled) 0.3 N, object 1 0.45 N (crosstalk), the
    # thumb-only cluster 0.3 N. Summed over both sensors 0.6 N of 2 N load vs 0.9 N of 6 N: per
    # newton 0.3 vs 0.15 (the thumb-only cluster: 0.86); per newton^0.75 0.357 vs 0.235; in newtons
    # 0.6 vs 0.9, where the crosstalk wins
    pulled = [0.3, 0.45, 0.3]

    def frame(s, k):
        cs = [(pos[s][i], np.array([0, 0, -load[i]]) + (np.array([pulled[i], 0, 0]) if k >= 4 else 0))
              for i in range(3) if s == "thumb" or i < 2]
        return _frame(cs)

    summed = {"witness": "sum", "along_only": False, "attribute": "cluster"}
    cases = ((ControllerConfig(load_power=1.0, **summed), 0, [0.15, 0.3]),
             (ControllerConfig(load_power=0.75, **summed), 0, [0.9 / 6 ** 0.75, 0.6 / 2 ** 0.75]),   # 0.2348, 0.3568
             (ControllerConfig(per_load=False, min_change=0.15, **summed), 1, [0.6, 0.9]))
    for cfg, named, scores in cases:
        d = _decide(SelectiveGraspController(g, start, m, cfg), frame)
        assert np.linalg.norm(d.moving_point - objs[named]) < 0.0015
        np.testing.assert_allclose(sorted(d.scores), scores, atol=1e-6)


def test_lateral_distance_from_pinch_axes():
    from tensortouch.tools.grasp.controller import lateral_mm

    pts = np.array([[0, 0, 0], [0.001, 0, 0]])
    nrm = np.array([[0, 0, 1.0], [1.0, 0, 0]])
    # 3-4-5 off the z axis through the origin; off the x axis through (1, 0, 0) mm: √(4² + 10²)
    np.testing.assert_allclose(lateral_mm(pts, nrm, np.array([0.003, 0.004, 0.010])), [5.0, np.hypot(4, 10)])
    np.testing.assert_allclose(lateral_mm(pts, np.array([0, 0, 1.0]), np.array([0.003, 0.004, 0.010])),
                               [5.0, np.hypot(2, 4)])


def _pinches(xs_mm, tilt_deg):
    """Pinch points along x (m), normals tilted about y, fingertip centres 12 mm either side."""
    xs = np.asarray(xs_mm, float) / 1000
    pts = np.stack([xs, np.zeros(len(xs)), np.zeros(len(xs))], 1)
    t = np.radians(np.asarray(tilt_deg, float))
    nrm = np.stack([np.sin(t), np.zeros(len(t)), np.cos(t)], 1)
    tips = np.stack([pts + 0.012 * nrm, pts - 0.012 * nrm], axis=1)
    return pts, nrm, tips


def test_centre_line_crosses_the_objects_plane_where_a_pinch_closes():
    from tensortouch.tools.grasp.graph import centre_line

    t = np.radians(10.0)
    # a pinch touching 2 mm above the plane z = 0, its line of centres tilted 10° about y:
    # it crosses z = 0 at x = 3.8527 − 2·tan 10° = 3.5 mm, and z = 1 mm at 3.8527 − tan 10° = 3.6764 mm
    pt = np.array([[0.0038527, 0.0, 0.002]])
    nrm = np.array([[np.sin(t), 0.0, np.cos(t)]])
    z = np.array([0, 0, 1.0])
    np.testing.assert_allclose(centre_line(pt, nrm, np.zeros(3), z)[0] * 1000, [3.5, 0, 0], atol=1e-4)
    np.testing.assert_allclose(centre_line(pt, nrm, np.array([0.01, 0.02, 0.001]), z)[0] * 1000,
                               [3.6764, 0, 1.0], atol=1e-4)


def test_goal_centres_the_moving_object_on_the_line_of_fingertip_centres_and_clears_the_other():
    from tensortouch.tools.grasp.controller import goal_scores

    pts, nrm, tips = _pinches([-8, -4, 0, 4, 6, 8, 4, 6, 3.8527], [0, 0, 0, 0, 0, 0, 30, 10, 10])
    pts[8, 2] = 0.002                                            # touching 2 mm above the plane
    tips[8] = [pts[8] + 0.012 * nrm[8], pts[8] - 0.012 * nrm[8]]
    costs = np.array([0.4, 0.2, 0.0, 0.2, 0.3, np.inf, 0.2, 0.3, 0.1])
    cfg = ControllerConfig(keep_mm=3.0, lean_mm=1.5, clear_mm=16.0, depth_mm=2.0, max_normal_deg=15.0,
                           cost_weight_mm_per_rad=2.0, keep_weight=10.0, clear_weight=10.0)
    z = np.array([0, 0, 1.0])
    mov, oth = np.array([0.0035, 0, 0]), np.array([-0.0035, 0, 0])
    sc = goal_scores(pts, nrm, tips, costs, z, mov, oth, cfg)
    # ρ_o: the nearer fingertip centre's distance from the other object's axis (x = −3.5, z = 0, along y)
    # untilted pinches in the plane: fingertips at (x, ±12), e = |x − 3.5|, lean 0, h 0, ρ_o = hypot(x + 3.5, 12)
    def short(dx, dz):
        return 16.0 - float(np.hypot(dx, dz))
    # x = 6: e 2.5, ρ_o 15.305 → 10·0.695 + 2.5 + 2·0.3 = 10.05 (the best goal)
    # x = 4: e 0.5, ρ_o 14.151 → 10·1.849 + 0.5 + 0.4;  x = 0: e 3.5 (0.5 over), ρ_o 12.5 → 10·(3.5 + 0.5) + 3.5
    # x = −4: e 7.5 (4.5 over), ρ_o 12.010;  x = −8: e 11.5 (8.5 over), ρ_o 12.816; node 5: unreachable; node 6: 30°
    untilted = [10 * (short(-4.5, 12) + 8.5) + 11.5 + 0.8, 10 * (short(-0.5, 12) + 4.5) + 7.5 + 0.4,
                10 * (short(3.5, 12) + 0.5) + 3.5, 10 * short(7.5, 12) + 0.5 + 0.4, 10 * short(9.5, 12) + 2.5 + 0.6]
    # node 7 (x = 6, tilted 10°): its line crosses at 6 (e 2.5); fingertips at x = 6 ± 12·sin 10° = 8.0838 /
    # 3.9162, z = ±12·cos 10° = ±11.8177: lean 2.0838 (0.5838 over), ρ_o = hypot(7.4162, 11.8177) = 13.952
    # node 8 (2 mm above, tilted 10°): its line crosses at 3.5 (e 0, centred), h 2; fingertips at
    # (5.9365, 13.8177) / (1.7689, −9.8177): lean 2.4365 (0.9365 over), ρ_o = hypot(5.2689, 9.8177) = 11.142
    t7 = 10 * (short(7.4162, 11.8177) + 0.5838) + 2.5 + 2.0838 + 0.6
    t8 = 10 * (short(5.2689, 9.8177) + 0.9365) + 2.4365 + 2.0 + 0.2
    np.testing.assert_allclose(sc, untilted + [np.inf, np.inf, t7, t8], atol=2e-3)
    assert int(np.argmin(sc)) == 4
    # a fingertip pair displaced along the objects (y) scores the same: distances along them do not count
    shift = np.array([0, 0.005, 0])
    np.testing.assert_allclose(goal_scores(pts + shift, nrm, tips + shift, costs, z, mov, oth, cfg), sc, atol=2e-3)
    # a pen-like other 12 mm away is cleared by all: a pinch centred on the moving object wins even
    # though it touches 2 mm off the plane and leans (node 8: 0.9365·10 + 2.4365 + 2 + 0.2 = 14.0,
    # x = 4: e 1 → 1 + 0.4), then the untilted x = 4
    far = np.array([-0.012, 0, 0])
    sc = goal_scores(pts, nrm, tips, costs, z, np.array([0.0035, 0, 0]), far, cfg)
    np.testing.assert_allclose(sc[[3, 4, 8]], [0.5 + 0.4, 2.5 + 0.6, 9.365 + 2.4365 + 2.0 + 0.2], atol=2e-3)
    # a pinch point 2.5 mm off the plane is 0.5 beyond depth_mm
    pts[3, 2] = 0.0025
    tips[3] = [pts[3] + 0.012 * nrm[3], pts[3] - 0.012 * nrm[3]]
    sc = goal_scores(pts, nrm, tips, costs, z, np.array([0.0035, 0, 0]), far, cfg)
    np.testing.assert_allclose(sc[3], 0.5 + 2.5 + 10 * 0.5 + 0.4, atol=2e-3)


def test_goal_aims_beyond_the_moving_object_away_from_the_other():
    from tensortouch.tools.grasp.controller import goal_scores

    pts, nrm, tips = _pinches([2.0, 3.5, 5.0, 6.5], [0, 0, 0, 0])
    costs = np.zeros(4)
    cfg = ControllerConfig(keep_mm=5.0, lean_mm=1.5, clear_mm=0.0, depth_mm=2.0, cost_weight_mm_per_rad=0.0)
    z = np.array([0, 0, 1.0])
    mov = np.array([0.0035, 0, 0])
    # untilted pinches in the plane: lean 0, h 0, nothing to clear; score = e
    np.testing.assert_allclose(goal_scores(pts, nrm, tips, costs, z, mov, np.array([-0.0035, 0, 0]), cfg),
                               [1.5, 0.0, 1.5, 3.0], atol=1e-6)
    # aimed 1.5 mm beyond, away from an other object on −x: e = |x − 5|
    np.testing.assert_allclose(goal_scores(pts, nrm, tips, costs, z, mov, np.array([-0.0035, 0, 0]), cfg, 1.5),
                               [3.0, 1.5, 0.0, 1.5], atol=1e-6)
    # the other object on +x: aimed towards −x, e = |x − 2|
    np.testing.assert_allclose(goal_scores(pts, nrm, tips, costs, z, mov, np.array([0.0105, 0, 0]), cfg, 1.5),
                               [0.0, 1.5, 3.0, 4.5], atol=1e-6)


def test_plan_aims_only_for_an_object_held_firmly_on_both_gels():
    g = _line_graph()                      # pinches at x = −8 … 8 mm, 2 mm apart, joint steps 0.02 rad
    cfg = ControllerConfig(aim_mm=2.5, aim_min_load_n=2.5, aim_beside_load_n=float("inf"), clear_mm=0.0, keep_mm=5.0)
    ctrl = SelectiveGraspController(g, 4, SensorMount(), cfg)
    mov, oth = np.array([0.0035, 0, 0]), np.array([-0.0035, 0, 0])
    # not aimed: e = |x − 3.5| + 2 mm/rad · path → x = 4 mm (0.5 + 0.08) beats x = 2 (1.5 + 0.04)
    assert g.point[ctrl._plan(mov, oth, [], held_n=2.4).goal][0] == pytest.approx(0.004)
    # aimed 2.5 mm beyond: e = |x − 6| → x = 6 mm
    assert g.point[ctrl._plan(mov, oth, [], held_n=2.5).goal][0] == pytest.approx(0.006)
    # a thin object beside a firmly held one: not aimed with aim_beside_load_n off (inf), aimed from it on
    assert g.point[ctrl._plan(mov, oth, [], held_n=0.5, other_held_n=4.0).goal][0] == pytest.approx(0.004)
    beside = SelectiveGraspController(g, 4, SensorMount(), replace(cfg, aim_beside_load_n=ControllerConfig().aim_beside_load_n))
    assert ControllerConfig().aim_beside_load_n == 3.6                    # the default: on
    assert g.point[beside._plan(mov, oth, [], held_n=0.5, other_held_n=3.5).goal][0] == pytest.approx(0.004)
    assert g.point[beside._plan(mov, oth, [], held_n=0.5, other_held_n=3.6).goal][0] == pytest.approx(0.006)


def test_a_contact_merging_two_objects_on_one_gel_is_not_an_object():
    """The thumb resolves two objects 14 mm apart; the index reports one merged cluster between
    them (the sum of both loads). The merged cluster's shear must not name a third, middle object."""
    from tensortouch.tools.grasp.controller import between

    assert between(np.zeros(3), [np.array([-0.007, 0, 0]), np.array([0.007, 0, 0])], 4.0)
    assert not between(np.array([0.004, 0, 0]), [np.array([-0.007, 0, 0]), np.array([0.007, 0, 0])], 4.0)
    assert not between(np.array([0, 0.005, 0]), [np.array([-0.007, 0, 0]), np.array([0.007, 0, 0])], 4.0)
    g = _line_graph()
    start = 4
    m = SensorMount()
    objs = [np.array([-0.007, 0, 0]), np.array([0.007, 0, 0])]
    thumb = [_on_gel(m, g.tip_thumb[start], o) for o in objs]
    merged = _on_gel(m, g.tip_index[start], np.zeros(3))

    def frame(s, k):
        pulled = k >= 4                                   # object 1 pulled along its length (gel y)
        if s == "thumb":
            return _frame([(thumb[0], np.array([0, 0, -2.0])),
                           (thumb[1], np.array([0, 0.4 if pulled else 0.0, -2.0]))])
        return _frame([(merged, np.array([0, 1.0 if pulled else 0.0, -4.0]))])

    d = _decide(SelectiveGraspController(g, start, m, ControllerConfig(attribute="cluster")), frame)
    # (a gel point 12 mm from the fingertip centre stands for an object 12 mm away: 6.05 mm across for 7)
    assert d.moving_point[0] > 0.005 and d.other_point is not None and d.other_point[0] < -0.005
    d = _decide(SelectiveGraspController(g, start, m, ControllerConfig(drop_between=False, attribute="cluster")), frame)
    assert abs(d.moving_point[0]) < 0.0015                  # without the rule: the phantom middle object


def test_controller_stays_put_without_a_clear_change():
    g = _line_graph()
    ctrl = SelectiveGraspController(g, 4, SensorMount())
    ctrl.watch()
    frame = _frame([((0, 0, 8.0), (0, 0, -1.0))])
    for _ in range(10):
        ctrl.on_contacts("thumb", frame)
        ctrl.on_contacts("index", frame)
        assert ctrl.update() is None


def test_controller_module_cannot_see_the_simulator():
    """Structural: the controller imports only numpy, the graph and the sensor mount."""
    src = Path(__file__).resolve().parents[1] / "tools" / "grasp" / "controller.py"
    mods = set()
    for node in ast.walk(ast.parse(src.read_text())):
        if isinstance(node, ast.Import):
            mods |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom):
            mods.add("." * node.level + (node.module or ""))
    assert mods <= {"__future__", "threading", "dataclasses", "numpy", ".graph", ".sensor_mount",
                    "...runtime.apps.subscriber"}, mods


def test_trial_verdict_names_the_failure_cause():
    from tensortouch.tools.grasp.trial import verdict

    t = np.array
    assert verdict(None, 0, t([[1, 1], [1, 1]])) == ("other", "no decision")
    assert verdict(1, 0, t([[1, 0], [1, 0]])) == ("false detection", "other object named")
    assert verdict(0, 0, t([[1, 0], [1, 0]])) == ("success", "")
    assert verdict(1, 1, t([[0, 1], [1, 1]])) == ("other", "final pinch also touches the other object")
    assert verdict(1, 1, t([[1, 1], [1, 0]])) == ("other", "final pinch lost the pulled object, touches the other")
    assert verdict(0, 0, t([[0, 0], [0, 0]])) == ("other", "final pinch lost the pulled object")
    # the other object pressed into a gel (not its core) beyond touch_mm touches it; within, it does not
    gel = np.array([[1.2, 0.0], [1.2, 0.6]])
    assert verdict(0, 0, t([[1, 0], [1, 0]]), gel, 0.1) == ("other", "final pinch's gel touches the other object")
    assert verdict(0, 0, t([[1, 0], [1, 0]]), gel, 0.7) == ("success", "")
    assert verdict(1, 1, t([[0, 1], [0, 1]]), t([[0.05, 1.2], [0.0, 1.2]]), 0.1) == ("success", "")


def test_controller_scores_the_change_along_the_objects_with_the_stronger_witness():
    """The pulled object (1) shears one gel along its length; the network puts shear on its
    neighbour on the other gel, part of it across the objects (a squeeze change). Summed over both
    gels the neighbour leads; along the objects' length, taking each object's stronger gel, the
    pulled one does."""
    g, start, m, objs, pos = _pinch()
    along = np.array([0, 1.0, 0])                  # the objects lie along world y: gel y on both sensors
    across = np.array([1.0, 0, 0])
    load = {"thumb": [1.0, 1.0], "index": [1.0, 1.0]}
    shear = {"thumb": [0.30 * along + 0.30 * across, 0.10 * along],
             "index": [0.20 * along, 0.45 * along]}

    def frame(s, k):
        return _frame([(pos[s][i], np.array([0, 0, -load[s][i]]) + (shear[s][i] if k >= 4 else 0)) for i in range(2)])

    decided = {}
    for name, cfg in (("sum", ControllerConfig(witness="sum", along_only=False, attribute="cluster")),
                      ("new", ControllerConfig(witness="max", drift_weight=0.0, attribute="cluster"))):
        d = _decide(SelectiveGraspController(g, start, m, cfg), frame)
        decided[name] = int(np.argmin([np.linalg.norm(d.moving_point - o) for o in objs]))
    assert decided == {"sum": 0, "new": 1}


def test_controller_needs_both_gels_and_counts_the_pulled_clusters_drift():
    """A light object (0) at the gel rim is pulled: the thumb shows it 0.15 N along its length and
    its neighbour 0.05 N; the index shows it 0.10 N and puts 0.40 N on the neighbour (crosstalk),
    and the pulled object's index cluster slides 1 mm along it. Loads are 1 N, so the changes per
    N^0.75 are those numbers. The stronger witness names the neighbour (0.40 > 0.15); the geometric
    mean of both gels alone too (√(0.05·0.40) = 0.141 > √(0.15·0.10) = 0.122); with 0.15 per mm of
    drift added on each gel the pulled one leads: √(0.15·(0.10 + 0.15)) = 0.194."""
    g, start, m, objs, pos = _pinch()
    along = np.array([0, 1.0, 0])                  # the objects lie along world y: gel y on both sensors
    shear = {"thumb": [0.15, 0.05], "index": [0.10, 0.40]}
    slide = {"thumb": [0.0, 0.0], "index": [1.0, 0.0]}

    def frame(s, k):
        on = k >= 4
        return _frame([(pos[s][i] + (slide[s][i] * along if on else 0), np.array([0, 0, -1.0]) + (shear[s][i] * along if on else 0))
                       for i in range(2)])

    named, scores = {}, {}
    by_cluster = ControllerConfig(attribute="cluster")
    for name, cfg in (("max", replace(by_cluster, witness="max", drift_weight=0.0)),
                      ("both", replace(by_cluster, drift_weight=0.0)), ("both+drift", by_cluster)):
        d = _decide(SelectiveGraspController(g, start, m, cfg), frame)
        named[name] = int(np.argmin([np.linalg.norm(d.moving_point - o) for o in objs]))
        scores[name] = sorted(d.scores)
    assert named == {"max": 1, "both": 1, "both+drift": 0}
    np.testing.assert_allclose(scores["both"], [np.sqrt(0.015), np.sqrt(0.02)], atol=1e-6)
    np.testing.assert_allclose(scores["both+drift"], [np.sqrt(0.02), np.sqrt(0.15 * 0.25)], atol=1e-6)


def test_replay_names_the_pulled_object_of_a_recorded_trial():
    """A recorded trial (4 reference frames, then 4 with object 1 sheared 0.4 N along its length on
    both gels) replayed through the controller names object 1, judged from where the gels felt each
    object; with a threshold above its score (0.4 N per N^0.75 of 1 N) it names none."""
    from tensortouch.tools.grasp import replay

    g, start, m, objs, pos = _pinch()

    def entry(phase, pulled):
        return {"phase": phase,
                "contacts": {s: [(pos[s][k].tolist(), [0.0, 0.4 if pulled and k == 1 else 0.0, -1.0], [0, 0, 1.0], 10.0)
                                 for k in range(2)] for s in pos},
                "felt": {s: [(k, pos[s][k].tolist(), 1.0, [0, 0, 0]) for k in range(2)] for s in pos}}

    rec = {"pair": "A+A", "seed": 0, "pulled": 1, "start": start,
           "log": [entry("settle", False)] + [entry("reference", False)] * 4 + [entry("pull", True)] * 4}
    assert replay.replay(rec, g) == 1
    assert replay.replay(rec, g, ControllerConfig(min_change=0.5)) is None
    other = dict(rec, pulled=0)
    assert replay.tally([rec, other], g) == {"A+A": {"right": 1, "wrong": 1, "none": 0},
                                             "object 1 pulled": {"right": 1, "wrong": 0, "none": 0},
                                             "object 0 pulled": {"right": 0, "wrong": 1, "none": 0}}


def test_split_forces_shares_a_cluster_between_two_objects_by_lever():
    """Objects at gel points a = (0,0,0) and b = (10,0,0) mm. A cluster at (2.5,0,0) with
    F = (0,1,−4) lies a quarter of the way: 3/4 of F to object 0, 1/4 to object 1. A cluster at
    (12,0,0), beyond b, goes to object 1 whole. Weights |F|·share: √17·0.75 = 3.0923 and
    √17·0.25 + 2 = 3.0308; object 1's centroid (1.0308·2.5 + 2·12)/3.0308 = 8.7690 mm."""
    from tensortouch.tools.grasp.controller import along_direction, split_forces

    a, b = np.zeros(3), np.array([10.0, 0, 0])
    out = split_forces([((2.5, 0, 0), (0, 1.0, -4.0), (0, 0, 1.0), 10.0), ((12.0, 0, 0), (0, 0, -2.0))], [a, b])
    np.testing.assert_allclose(out["force"][0], [0, 0.75, -3.0])
    np.testing.assert_allclose(out["force"][1], [0, 0.25, -3.0])
    np.testing.assert_allclose(out["weight"], [3.0923, 3.0308], atol=1e-4)
    np.testing.assert_allclose(out["centroid"][0], [2.5, 0, 0])
    np.testing.assert_allclose(out["centroid"][1], [8.7690, 0, 0], atol=1e-4)
    # two loads merged into one cluster at their force-weighted centroid come apart as they were
    merged = split_forces([((2.5, 0, 0), (0, 0, -4.0))], [a, b])
    np.testing.assert_allclose(merged["force"], [[0, 0, -3.0], [0, 0, -1.0]])
    # no clusters: no force, each centroid at its object
    empty = split_forces([], [a, b])
    np.testing.assert_allclose(empty["force"], np.zeros((2, 3)))
    np.testing.assert_allclose(empty["centroid"], [a, b])
    # along two objects side by side on x, on a gel facing +z: z × x = +y
    np.testing.assert_allclose(along_direction(a, b, (0, 0, 1.0)), [0, 1.0, 0])
    np.testing.assert_allclose(along_direction(b, a, (0, 0, 1.0)), [0, -1.0, 0])


def test_lever_names_a_pulled_cable_whose_gel_merges_it_with_a_pen():
    """A light cable (object 0) beside a pen (object 1). The thumb resolves both (0.5 N and 3 N);
    the index reports one cluster of 3.75 N at their force-weighted centroid (4/5 of the way to the
    pen, 0.75 N of it the cable's). The cable is pulled along its length: the thumb shows it 0.10 N
    along and the pen 0.18 N (crosstalk); the index cluster splits into one at the pen carrying
    0.30 N along (crosstalk) and one at the cable with 0.08 N. By reference cluster the merged
    cluster is the pen's: its change and its ~3 mm jump across name the pen (0.19 against the
    cable's thumb-only 0.10/0.5^0.75 = 0.17). Split by lever the index compares the cable's 0.08 N
    of its share with the pen's 0.30 N of ~3 N, and the thumb 0.10 N of 0.5 N with 0.18 N of 3 N:
    the geometric means are 0.18 for the cable against 0.10 for the pen (the shares come from
    where the objects' reference points project onto the index gel, near 0.75 N and 3 N)."""
    g, start, m, objs, pos = _pinch(((-0.007, 0, 0), (0.007, 0, 0)))
    along = np.array([0, 1.0, 0])
    load = [0.5, 3.0]
    merged = pos["index"][0] + 0.8 * (pos["index"][1] - pos["index"][0])

    def frame(s, k):
        on = k >= 4
        if s == "thumb":
            return _frame([(pos[s][i], np.array([0, 0, -load[i]]) + (x * along if on else 0))
                           for i, x in enumerate((0.10, 0.18))])
        if not on:
            return _frame([(merged, np.array([0, 0, -3.75]))])
        return _frame([(pos[s][0], np.array([0, 0.08, -0.5])), (pos[s][1], np.array([0, 0.30, -3.0]))])

    named, scores = {}, {}
    for rule in ("cluster", "lever"):
        d = _decide(SelectiveGraspController(g, start, m, ControllerConfig(attribute=rule)), frame)
        named[rule] = int(np.argmin([np.linalg.norm(d.moving_point - o) for o in objs]))
        scores[rule] = d.scores
    assert named == {"cluster": 1, "lever": 0}, scores


@pytest.mark.parametrize("field, value", [("attribute", "levers"), ("witness", "mean")])
def test_controller_config_refuses_an_unknown_rule(field, value):
    with pytest.raises(ValueError, match=f"ControllerConfig.{field} = '{value}'; expected one of"):
        ControllerConfig(**{field: value})


def test_repinch_moves_on_while_a_gel_still_feels_the_other_object():
    g, start, m, (oth, mov), _ = _pinch()
    cfg = ControllerConfig(keep_mm=5.0, clear_mm=13.0, clear_weight=30.0, repinches=1, repinch_clear_mm=1.5,
                           touch_n=0.15, aim_beside_load_n=float("inf"))
    ctrl = SelectiveGraspController(g, start, m, cfg)
    ctrl.decision = ctrl._plan(mov, oth, [])
    first = ctrl.decision.goal
    assert g.point[first][0] == pytest.approx(0.004)     # e 0.5, ρ_o = hypot(7.5, 12) = 14.15 clears 13
    held = [(_on_gel(m, T[first], mov), (0, 0, -1.0)) for T in (g.tip_thumb, g.tip_index)]
    # nothing felt where the other object lies: stay
    ctrl.on_contacts("thumb", _frame([held[0]]))
    ctrl.on_contacts("index", _frame([held[1]]))
    assert ctrl.other_felt() == {"thumb": 0.0, "index": 0.0}
    assert ctrl.repinch() is None
    # the index gel feels 0.3 N nearer the other object's place than the held one's: a goal with
    # 14.5 mm clearance, from where the hand is (x = 6: ρ_o 15.3, e 2.5)
    ctrl.on_contacts("index", _frame([held[1], (_on_gel(m, g.tip_index[first], oth), (0, 0, -0.3))]))
    assert ctrl.other_felt()["index"] == pytest.approx(0.3)
    d = ctrl.repinch()
    assert d is not None and g.point[d.goal][0] == pytest.approx(0.006)
    assert d.path[0] == first and d.terms["repinch"] == 1 and d.terms["clear_mm"] == pytest.approx(14.5)
    assert ctrl.repinch() is None                          # at most `repinches`


def test_an_arm_carries_the_goal_beyond_the_graphs_reach():
    """A graph reaching only ±2 mm across, objects at ±3.5 mm, the +3.5 mm one pulled (held lightly:
    not aimed). Without the arm the best pinch crosses 1.5 mm short of it. With the arm, and the
    other object already clear (clear_mm 12 mm: it lies 7 mm across and 12 mm up from the nearer
    fingertip centre, 13.9 mm), every node is slid across until its line of centres crosses the
    object (e = 0); the goal is the node needing the least travel plus path, x = +2 mm with the arm
    at +1.5 mm. Wanting 17 mm of clearance, the arm goes the full `arm_beyond_mm` (1.5 mm) beyond,
    away from the other: ρ = √(8.5² + 12²). Within a 1 mm reach it stops at 1 mm, e = 0.5 mm. The arm's steps
    end at the goal's translation."""
    from tensortouch.tools.grasp.controller import goal_terms

    g, m = _line_graph(0.002), SensorMount()
    moving, other = np.array([0.0035, 0, 0]), np.array([-0.0035, 0, 0])
    tips = np.stack([g.tip_thumb[:, :3, 3], g.tip_index[:, :3, 3]], axis=1)
    base = ControllerConfig(clear_mm=12.0)
    plain = goal_terms(g.point, g.normal, tips, g.normal[4], moving, other, base)
    assert "arm" not in plain and plain["e"].min() == pytest.approx(1.5)
    carried = goal_terms(g.point, g.normal, tips, g.normal[4], moving, other, replace(base, arm_mm=25.0))
    np.testing.assert_allclose(carried["e"], 0.0, atol=1e-9)
    np.testing.assert_allclose(carried["arm"][:, 0], 0.0035 - g.point[:, 0], atol=1e-12)
    np.testing.assert_allclose(carried["arm_travel"], (0.0035 - g.point[:, 0]) * 1000.0, atol=1e-9)
    np.testing.assert_allclose(carried["rho_other"], np.hypot(7.0, 12.0), atol=1e-6)
    room = goal_terms(g.point, g.normal, tips, g.normal[4], moving, other, replace(base, arm_mm=25.0, clear_mm=17.0))
    np.testing.assert_allclose(room["e"], 1.5, atol=1e-9)
    np.testing.assert_allclose(room["rho_other"], np.hypot(8.5, 12.0), atol=1e-6)
    short = goal_terms(g.point, g.normal, tips, g.normal[4], moving, other, replace(base, arm_mm=1.0),
                       arm=np.array([0.0005, 0, 0]))
    assert short["arm"][8, 0] == pytest.approx(0.001) and short["e"][8] == pytest.approx(0.5)
    assert short["arm_travel"][8] == pytest.approx(0.5)

    ctrl = SelectiveGraspController(g, 4, m, replace(base, arm_mm=25.0, arm_step_mm=0.2))
    d = ctrl.decision = ctrl._plan(moving, other, [1.0, 0.0], held_n=1.0)
    assert d.goal == 8 and d.path[0] == 4 and d.path[-1] == 8 and len(d.path) < 8
    np.testing.assert_allclose(d.arm, [0.0015, 0, 0], atol=1e-12)
    assert d.terms["arm_mm"][0] == pytest.approx(1.5) and d.terms["e"] == pytest.approx(0.0)
    arms = ctrl.arm_trajectory()
    times, qs = ctrl.trajectory()
    assert len(arms) == len(qs) == 8                    # 1.5 mm at 0.2 mm per step: 8 steps, more than the path's
    np.testing.assert_allclose(arms[-1], d.arm)
    k = len(d.path)
    np.testing.assert_allclose(qs[k:], np.repeat(g.q[8:9], 8 - k, axis=0))   # the fingers wait at the goal
    assert np.all(np.diff(arms[:, 0]) > 0) and np.all(np.diff(times) > 0)
    ctrl.moved_to_goal()
    np.testing.assert_allclose(ctrl.arm, d.arm)


def test_an_arm_shifts_where_the_controller_places_the_gel_contacts():
    """The same gel contact stands for a world point carried by the arm's translation, and back."""
    g, m = _line_graph(), SensorMount()
    home = SelectiveGraspController(g, 4, m)
    moved = SelectiveGraspController(g, 4, m, arm=np.array([0.004, -0.001, 0.0]))
    p = _on_gel(m, g.tip_thumb[4], np.array([0.0035, 0, 0]))
    np.testing.assert_allclose(moved._world("thumb", p) - home._world("thumb", p), [0.004, -0.001, 0.0], atol=1e-12)
    np.testing.assert_allclose(moved._gel("thumb", moved._world("thumb", p)), p, atol=1e-9)
