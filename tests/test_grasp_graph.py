"""Contact graph (tools/grasp/graph.py): k-NN edges, Dijkstra, npz round trip."""
import numpy as np
import pytest
from tensortouch.tools.grasp import graph


def _line_graph(n=6):
    q = np.stack([np.arange(n, dtype=float), np.zeros(n)], 1)
    edges, w = graph.knn_edges(q, 1)
    z = np.zeros((n, 3))
    T = np.tile(np.eye(4), (n, 1, 1))
    return graph.ContactGraph(q, z, z, z, z, z, z, T, T, edges, w, np.array([4.3, 0.0]))


def test_knn_edges_are_undirected_and_weighted_by_joint_distance():
    q = np.array([[0, 0], [1, 0], [0, 2], [5, 5]], float)
    edges, w = graph.knn_edges(q, 1)
    got = {tuple(e): x for e, x in zip(edges.tolist(), w)}
    assert got == {(0, 1): 1.0, (0, 2): 2.0, (2, 3): pytest.approx(np.hypot(5, 3))}


def test_dijkstra_path_on_a_chain_and_a_shortcut():
    g = _line_graph(6)
    assert g.path(0, 5) == [0, 1, 2, 3, 4, 5]
    assert g.path(3, 3) == [3]
    g.edges = np.concatenate([g.edges, [[0, 5]]])
    g.weights = np.concatenate([g.weights, [2.5]])
    assert g.path(0, 5) == [0, 5]
    assert g.reachable_costs(0)[4] == pytest.approx(3.5)  # 0→5→4
    assert g.nearest([3.2, 0.1]) == 3


def test_unreachable_goal_gives_empty_path():
    g = _line_graph(4)
    g.edges, g.weights = g.edges[:1], g.weights[:1]   # only 0–1
    assert g.path(0, 3) == []


def test_save_load_round_trip_without_pickle(tmp_path):
    g = _line_graph(5)
    p = graph.save(g, tmp_path / "g.npz")
    g2 = graph.load(p)
    for f in graph._FIELDS:
        np.testing.assert_array_equal(getattr(g, f), getattr(g2, f))


def test_load_rejects_a_foreign_npz(tmp_path):
    p = tmp_path / "x.npz"
    np.savez(p, q=np.zeros(3))
    with pytest.raises(graph.GraphError, match="schema"):
        graph.load(p)
    g = _line_graph(3)
    g.edges = np.array([[0, 7]])
    g.weights = np.array([1.0])
    graph.save(g, tmp_path / "bad.npz")
    with pytest.raises(graph.GraphError, match="edges"):
        graph.load(tmp_path / "bad.npz")


def test_allegro_graph_contact_nodes_paths_and_sensor_positions():
    pytest.importorskip("pinocchio")
    pytest.importorskip("coal")
    from tensortouch.tools.grasp import hand_model

    spec = hand_model.HandSpec()
    model = hand_model.load(None, spec)
    hand_model.apply_variant(model, spec, hand_model.nominal_placement(model, spec), 0.043, 0.0)
    g = graph.build(model, spec, (4.3, 0.0), graph.GraphConfig(nodes=300, refine_nodes=60))
    assert len(g) == 360
    # the refined nodes lie around one pinch: within 2 × refine_radius of each other
    ref = g.point[300:]
    assert np.linalg.norm(ref[:, None] - ref[None], axis=2).max() <= 2 * 0.014 + 1e-9
    # every node is a contact: fingertip centres 2 × 10.2 mm apart within the contact band
    d = np.linalg.norm(g.tip_thumb[:, :3, 3] - g.tip_index[:, :3, 3], axis=1)
    assert np.all(d <= 0.0204 + 0.001) and np.all(d >= 0.0204 - 0.003)
    np.testing.assert_allclose(np.linalg.norm(g.dir_thumb, axis=1), 1.0)
    # every contact lands on both gels: pad angle inside the mount's cone, gel point on the dome
    from tensortouch.tools.grasp.sensor_mount import SensorMount

    m = SensorMount()
    assert np.all(g.dir_thumb @ np.array(m.axis_tip) >= m.cone_cos() - 1e-9)
    np.testing.assert_allclose(m.gel_to_direction(g.sensor_index_mm), g.dir_index, atol=1e-9)
    costs = g.reachable_costs(0)
    far = int(np.argmax(np.where(np.isfinite(costs), costs, -1)))
    path = g.path(0, far)
    assert path[0] == 0 and path[-1] == far and len(path) > 2
    steps = np.linalg.norm(np.diff(g.q[path], axis=0), axis=1)
    assert steps.sum() == pytest.approx(costs[far])


def _pinch_row(xs_mm, tilt_deg=0.0):
    """Pinches along world x at xs_mm (normal +z, or tilted about y by tilt_deg), chained by
    joint steps of 0.1 rad; the index tip's long axis (tip z) along +x."""
    n = len(xs_mm)
    q = np.stack([np.arange(n) * 0.1, np.zeros(n)], 1)
    point = np.stack([np.asarray(xs_mm, float) / 1000, np.zeros(n), np.zeros(n)], 1)
    t = np.radians(tilt_deg)
    normal = np.tile([np.sin(t), 0.0, np.cos(t)], (n, 1))
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, :3] = [[0, 0, 1], [0, 1, 0], [-1, 0, 0]]          # tip z along world +x
    z = np.zeros((n, 3))
    edges, w = graph.knn_edges(q, 1)
    return graph.ContactGraph(q, point, normal, z, z, z, z, T, T, edges, w, np.array([5.5, 0.0]))


def test_room_counts_pinches_on_either_side_across():
    g = _pinch_row([-10, -8, -7, -2, 0, 3, 6.5, 9, 12])
    # node 4 (x = 0): across = +x; band 6.5–10.5 mm → −10, −8, −7 on the − side, 6.5, 9 on the + side
    assert graph.room(g, 4) == (3, 2)
    assert graph.room(g, 4, band_mm=(2.5, 7.0)) == (1, 2)      # −7 | 3, 6.5
    g.normal[0] = [1.0, 0, 0]                                   # 90° off: not a compatible pinch
    assert graph.room(g, 4) == (2, 2)
