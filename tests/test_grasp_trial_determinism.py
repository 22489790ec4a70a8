"""A selective-grasp trial is step-locked: the same seed gives the same frames, contacts, joint
trajectory and outcome, whatever the machine's timing (MuJoCo + twin render + the real runtime on
two threads + a real Zenoh loopback session between the sensors and the controller)."""
import numpy as np
import pytest


@pytest.fixture(scope="module")
def small_hand(tmp_path_factory):
    pytest.importorskip("pinocchio")
    pytest.importorskip("coal")
    pytest.importorskip("mujoco")
    from tensortouch.tools.grasp import graph, hand_model

    out = tmp_path_factory.mktemp("hand")
    spec = hand_model.HandSpec()
    model = hand_model.load(None, spec)
    hand_model.apply_variant(model, spec, hand_model.nominal_placement(model, spec), 0.055, 0.0)
    g = graph.build(model, spec, (5.5, 0.0), graph.GraphConfig(nodes=400, refine_nodes=200))
    graph.save(g, out / "contact_graph.npz")
    hand_model.write_urdf(hand_model.default_urdf(), out / "hand_mounted.urdf", spec, 0.055, 0.0)
    return out


@pytest.mark.slow
def test_same_seed_same_trial_twice(small_hand):
    from tensortouch.tools.grasp.trial import Bench, TrialConfig

    cfg = TrialConfig(startup_frames=24, close_s=0.2, settle_s=0.12, decide_timeout_s=0.32, hold_s=0.08,
                      frame_timeout_s=20.0)
    bench = Bench(small_hand / "contact_graph.npz", small_hand / "hand_mounted.urdf", cfg)
    try:
        runs = []
        for _ in range(2):
            log: list = []
            r = bench.trial("A+B", 3, log_out=log)
            runs.append((r, log))
    finally:
        bench.close()
    (r1, log1), (r2, log2) = runs
    assert len(log1) == len(log2) > cfg.startup_frames
    assert any(f["contacts"]["thumb"] for f in log1)          # the pinch is felt and published
    for a, b in zip(log1, log2):
        assert a == b                                          # bit-exact: time, joints, contacts
    assert (r1.pulled, r1.judged, r1.outcome, r1.touching, r1.path_len, r1.scores) == \
        (r2.pulled, r2.judged, r2.outcome, r2.touching, r2.path_len, r2.scores)
    assert np.isfinite([f["q"] for f in log1]).all()


@pytest.mark.slow
def test_a_randomized_trial_runs_its_draw(small_hand):
    """One short `--randomize` trial: the world is built from the seed's draw (diameters, friction,
    contact setting, layout), the draw is recorded, and the outcome is one of the table's classes."""
    from tensortouch.tools.grasp.task import TaskDistribution, draw
    from tensortouch.tools.grasp.trial import FAILURES, Bench, TrialConfig, failure_class

    cfg = TrialConfig(startup_frames=24, close_s=0.2, settle_s=0.12, decide_timeout_s=0.32, hold_s=0.08,
                      frame_timeout_s=20.0, randomize=True)
    bench = Bench(small_hand / "contact_graph.npz", small_hand / "hand_mounted.urdf", cfg)
    seed = next(s for s in range(100) if draw(TaskDistribution(), ("A", "pen"), s).contact == "stiff")
    try:
        log: list = []
        r = bench.trial("cable+rigid", seed, log_out=log)
    finally:
        bench.close()
    d = draw(TaskDistribution(), ("A", "pen"), seed)
    assert r.randomized and r.task["diameters_mm"] == list(d.diameters_mm) and r.task["contact"] == "stiff"
    assert r.pulled == d.pulled and r.task["start"] >= 0
    assert r.outcome == "success" or failure_class(r) in FAILURES
    assert any(f["felt"]["thumb"] or f["felt"]["index"] for f in log)     # the drawn layout is pinched


@pytest.mark.slow
def test_a_randomized_trial_with_the_arm_starts_at_the_hands_own_pinch(small_hand):
    """`TrialConfig.arm`: the arm, not another graph node, brings the start pinch to where the objects
    are seen (the layout's shift across, to ± layout_error_mm), and the draw records where."""
    from tensortouch.tools.grasp.task import TaskDistribution, draw
    from tensortouch.tools.grasp.trial import FAILURES, Bench, TrialConfig, failure_class

    cfg = TrialConfig(startup_frames=24, close_s=0.2, settle_s=0.12, decide_timeout_s=0.32, hold_s=0.08,
                      frame_timeout_s=20.0, randomize=True, arm=True)
    bench = Bench(small_hand / "contact_graph.npz", small_hand / "hand_mounted.urdf", cfg)
    seed = next(s for s in range(100) if abs(draw(TaskDistribution(), ("pen", "pen"), s).shift_mm[0]) > 3)
    try:
        r = bench.trial("rigid+rigid", seed)
    finally:
        bench.close()
    shift = draw(TaskDistribution(), ("pen", "pen"), seed).shift_mm[0]
    assert r.task["start"] == bench.start
    assert abs(np.linalg.norm(r.task["arm_start_mm"]) - abs(shift)) <= cfg.layout_error_mm + 1e-6
    assert r.outcome == "success" or failure_class(r) in FAILURES
