"""The frame loop's cheaper bookkeeping gives what the plain way gave: the latency summary (one
percentile call for p50 and p99) and the baseline tracker keeping the pipeline's frame without a copy."""
import numpy as np
import pytest
from tensortouch.runtime.apps.loop import LatencyWindow
from tensortouch.runtime.stages.baseline import BaselineConfig, BaselineState, BaselineTracker


@pytest.mark.parametrize("n", [1, 2, 7, 300, 1001])
def test_latency_summary_same_as_one_percentile_call_each(n):
    rng = np.random.default_rng(n)
    w = LatencyWindow(n=500)
    for v in rng.gamma(2.0, 1.5, n):
        w.add({"a": float(v), "b": float(v) * 3 + 1})
    for k, d in w.samples.items():
        a = np.fromiter(d, float)
        s = w.summary()[k]
        assert s["p50"] == float(np.percentile(a, 50)) and s["p99"] == float(np.percentile(a, 99))
        assert s["mean"] == float(a.mean())


def test_latency_summary_hand_worked():
    w = LatencyWindow()
    for v in (1.0, 2.0, 3.0, 4.0):
        w.add({"x": v})
    assert w.summary()["x"] == {"p50": 2.5, "p99": pytest.approx(3.97, abs=1e-12), "mean": 2.5}


def _frames(n=160, seed=0):
    """Images that visit every state: rest, a press, a slow creep back to a new rest, rest again."""
    rng = np.random.default_rng(seed)
    rest = rng.uniform(0.2, 0.8, (3, 16, 16)).astype(np.float32)
    out = []
    for k in range(n):
        img = rest + rng.normal(0, 0.002, rest.shape).astype(np.float32)
        if 40 <= k < 60:
            img[:, 4:12, 4:12] += 0.3                              # pressed
        elif 60 <= k < 120:
            img[:, 4:12, 4:12] += 0.06 * max(0.0, 1 - (k - 60) / 30)  # creeping back
            img[:, 4:12, 4:12] += 0.03                              # and a permanent offset
        elif k >= 120:
            img[:, 4:12, 4:12] += 0.03
        out.append(img)
    return out


def _run(owned, forces):
    cfg = BaselineConfig(startup_frames=10, hold_time_s=0.3)
    tr, got = BaselineTracker(cfg), []
    for k, (img, f) in enumerate(zip(_frames(), forces)):
        u = tr.update(img.copy(), f, k / 30.0, owned=owned)
        got.append((u.state, u.previous_state, u.changed, u.mse_baseline, u.mse_master, u.mse_previous, u.settled_s,
                    None if u.baseline is None else u.baseline.tobytes()))
    return got


@pytest.mark.parametrize("with_force", [False, True])
def test_baseline_owned_frames_same_decisions_as_copied_ones(with_force):
    forces = [(1.0 if 40 <= k < 60 else 0.0) if with_force else None for k in range(160)]
    owned, copied = _run(True, forces), _run(False, forces)
    assert [g[:3] for g in owned] == [g[:3] for g in copied]
    np.testing.assert_equal([g[3:] for g in owned], [g[3:] for g in copied])   # NaN == NaN here
    states = {g[0] for g in owned}
    assert {BaselineState.STARTUP, BaselineState.STABLE, BaselineState.CONTACT} <= states
    if with_force:                                              # without a force the press never ends (by design)
        assert BaselineState.DETACHMENT in states
        assert sum(g[2] for g in owned) >= 2                    # master chosen, then a new rest adopted


def test_baseline_copies_a_frame_it_does_not_own():
    tr = BaselineTracker(BaselineConfig(startup_frames=2))
    buf = np.full((3, 4, 4), 0.5, np.float32)
    tr.update(buf, None, 0.0)
    buf[:] = 0.6                                                  # the caller reuses its buffer
    u = tr.update(buf, None, 0.1)
    assert u.mse_previous == pytest.approx((0.1 * 255) ** 2, rel=1e-5)
    assert u.baseline is not buf and tr._previous is not buf
    mine = np.full((3, 4, 4), 0.7, np.float32)
    tr.update(mine, None, 0.2, owned=True)
    assert tr._previous is mine                                   # handed over: kept as it is


def _plain_wrench(clusters):
    force, torque = np.zeros(3), np.zeros(3)
    for c in clusters:
        force += c.force_n
        torque += np.cross(c.position_mm, c.force_n)
    return force, torque


@pytest.mark.parametrize("seed", range(5))
def test_wrench_sum_same_bits_as_numpy_cross(seed):
    from types import SimpleNamespace

    from tensortouch.runtime.pipeline import wrench_sum

    rng = np.random.default_rng(seed)
    kinds = [float, np.float64, np.float32, int] if seed % 2 else [float]

    def vec():
        kind = kinds[rng.integers(len(kinds))]
        v = rng.standard_normal(3) * 10.0 ** rng.integers(-8, 8, 3)
        v[rng.random(3) < 0.1] = -0.0
        return tuple(kind(round(x)) if kind is int else kind(x) for x in v)

    for n in (0, 1, 2, 7, 40):
        cl = [SimpleNamespace(position_mm=vec(), force_n=vec()) for _ in range(n)]
        got, ref = wrench_sum(cl), _plain_wrench(cl)
        for g, r in zip(got, ref):
            assert g.dtype == r.dtype == np.float64 and g.shape == (3,)
            assert g.tobytes() == r.tobytes()


def test_wrench_sum_hand_worked():
    from types import SimpleNamespace

    from tensortouch.runtime.pipeline import wrench_sum

    cl = [SimpleNamespace(position_mm=(1.0, 0.0, 0.0), force_n=(0.0, 2.0, 0.0)),
          SimpleNamespace(position_mm=(0.0, 0.0, 3.0), force_n=(1.0, 0.0, -1.0))]
    f, t = wrench_sum(cl)
    assert f.tolist() == [1.0, 2.0, -1.0]
    assert t.tolist() == [0.0, 3.0, 2.0]          # (1,0,0)×(0,2,0) = (0,0,2); (0,0,3)×(1,0,-1) = (0,3,0)
