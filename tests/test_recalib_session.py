"""Guided-session logic on synthetic clusters: prompts, rejections with reasons, typed reference."""
import numpy as np
import pytest
from tensortouch.contracts.store import CalibrationStore
from tensortouch.runtime.stages.contacts import Cluster
from tensortouch.tools.recalib.session import SessionConfig, StreamReference, TypedReference, analyse, run_guided

from tests.conftest import dome_calibration
from tests.recalib_util import poke_positions


def cl(f, uv, xyz):
    return Cluster(id=-1, uv_px=tuple(uv), position_mm=tuple(xyz), normal=(0, 0, 1), area_mm2=1.0,
                   force_n=(0.0, 0.0, -f), force_mag_n=f, pixels=5, perimeter_px=8.0, circularity=0.9)


def episodes(plan, dt=0.03):
    """plan: list of (peak force, [(uv, xyz, share)...]) → (t, clusters) frames with rest between."""
    t = 0.0
    for peak, contacts in plan:
        for f in np.r_[np.linspace(0.2, 1, 6), np.ones(10), np.linspace(1, 0.2, 4)] * peak:
            yield t, [cl(f * share, uv, xyz) for uv, xyz, share in contacts]
            t += dt
        for _ in range(6):
            yield t, []
            t += dt


@pytest.fixture
def cal(tmp_path):
    dome_calibration(tmp_path / "c", "TT-S")
    return CalibrationStore(tmp_path / "c").load("TT-S")


def test_session_rejects_with_reasons_then_accepts(cal):
    uvs, xyz = poke_positions(cal, 7)
    plan = [(2.0, [(uvs[0], xyz[0], 1.0)]),                                  # ok
            (0.15, [(uvs[1], xyz[1], 1.0)]),                                 # too light
            (2.0, [(uvs[0] + 0.3, xyz[0] + 0.5, 1.0)]),                      # too close to poke 1
            (2.0, [(uvs[1], xyz[1], 1.0), (uvs[2], xyz[2], 0.6)])]           # two fingers
    plan += [(1.0 + 0.3 * i, [(uvs[i], xyz[i], 1.0)]) for i in range(1, 7)]
    said = []
    # the reference is typed for every detected poke (rejected ones too), gain 1.25 for the good ones
    answers = iter(["2.5", "0.2", "2.5", "2.5"] + [str(1.25 * (1.0 + 0.3 * i)) for i in range(1, 7)])
    ref = TypedReference(ask=lambda prompt: next(answers), say=said.append)
    out = run_guided(episodes(plan), cal, ref, SessionConfig(pokes=6), say=said.append)
    text = "\n".join(said)
    assert out.complete and len(out.accepted) == 6 and len(out.rejected) == 3
    reasons = [p.verdict for p in out.rejected]
    assert reasons[0].startswith("too light") and reasons[1].startswith("too close to accepted poke 1")
    assert reasons[2].startswith("not a single contact")
    assert "poke 1/6: press on the top of the dome" in text and "o'clock" in text
    an = analyse(out.accepted, cal, SessionConfig(pokes=6))
    assert an.decision.store and an.fit.loo["after"]["mae_n"] < an.fit.loo["before"]["mae_n"]


def test_typed_reference_retries_and_skip():
    said = []
    answers = iter(["abc", "-1", "1,75"])
    ref = TypedReference(ask=lambda p: next(answers), say=said.append)
    from tensortouch.tools.recalib.pokes import Poke

    p = Poke(0, 1, 10, np.array([0, 0, -1.0]), np.zeros(2), np.zeros(3), 0.0)
    assert ref.for_poke(p) == pytest.approx(1.75)
    assert said == ["  'abc' is not a number in N", "  a force magnitude is >= 0 N"]
    assert TypedReference(ask=lambda p: "s").for_poke(p) is None


def test_stream_reference_takes_strongest_indenter():
    t = np.arange(0, 2, 0.01)
    f1 = np.where((t > 0.5) & (t < 1.5), 2.0, 0.0)
    f2 = np.where((t > 0.5) & (t < 1.5), 0.3, 0.0)
    tt = np.r_[t, t]
    force = np.zeros((len(tt), 3))
    force[:, 2] = np.r_[f1, f2]
    ref = StreamReference(tt, force, np.r_[np.zeros(len(t)), np.ones(len(t))])
    from tensortouch.tools.recalib.pokes import Poke

    p = Poke(0.6, 1.4, 20, np.array([0, 0, -1.0]), np.zeros(2), np.zeros(3), 0.0)
    assert ref.for_poke(p) == pytest.approx(2.0)
