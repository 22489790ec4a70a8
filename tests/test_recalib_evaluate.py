"""Held-out poke scoring (tools/recalib/evaluate.py): the reference's pokes and their plateaus by hand,
and the sensor's main contact force averaged over each plateau (0 N for a poke it missed)."""
from types import SimpleNamespace

import numpy as np
import pytest
from tensortouch.runtime.stages.contacts import Cluster
from tensortouch.tools.recalib.evaluate import gauge_episodes, gauge_pokes
from tensortouch.tools.recalib.pokes import PokeRules


def _reference():
    """Indenter 0: a 2 N poke (t 1.0-1.5 s, plateau 1.1-1.4 s) and a 0.1 N touch (too light);
    indenter 1: a 25 N poke (out of range). Readings every 0.05 s."""
    t = np.round(np.arange(0, 3.0, 0.05), 3)
    f0 = np.interp(t, [0.0, 0.95, 1.0, 1.1, 1.4, 1.5, 1.55, 2.0, 2.05, 2.2, 2.25, 3.0],
                   [0.0, 0.0, 1.0, 2.0, 2.0, 1.0, 0.0, 0.0, 0.1, 0.1, 0.0, 0.0])
    f1 = np.where((t > 0.5) & (t < 0.8), 25.0, 0.0)
    return SimpleNamespace(t=np.r_[t, t], ind=np.r_[np.zeros_like(t), np.ones_like(t)], mag=np.r_[f0, f1])


def test_episodes_by_hand():
    eps = gauge_episodes(_reference(), PokeRules())
    assert len(eps) == 1                                      # the light touch and the 25 N poke are left out
    t0, t1, ref = eps[0]
    assert (t0, t1) == pytest.approx((1.1, 1.4)) and ref == pytest.approx(2.0)


def test_sensor_force_over_each_plateau_and_zero_when_missed():
    def cl(f, x):
        return Cluster(id=-1, uv_px=(10.0 + x, 10.0), position_mm=(x, 0.0, 10.0), normal=(0, 0, 1), area_mm2=1.0,
                       force_n=(0.0, 0.0, -f), force_mag_n=f, pixels=5, perimeter_px=8.0, circularity=0.9)

    # one contact split in two parts 2 mm apart (summed: 1.5 N), and a far one that is not part of it
    frames = [(t, [cl(1.0, 0.0), cl(0.5, 2.0), cl(0.3, 9.0)] if 1.0 <= t <= 1.5 else [])
              for t in np.round(np.arange(0, 3.0, 1 / 30), 4)]
    out = gauge_pokes(frames, _reference())
    np.testing.assert_allclose(out["ref"], [2.0])
    np.testing.assert_allclose(out["pred"], [1.5])
    missed = gauge_pokes([(t, []) for t, _ in frames], _reference())
    np.testing.assert_allclose(missed["pred"], [0.0])
