"""The twin planner's contact placement ends for every seed (tools/twin/trajectory.py)."""
from dataclasses import replace

import numpy as np
import pytest
from tensortouch.tools.twin.geometry import GelSurface
from tensortouch.tools.twin.trajectory import TrajectoryConfig, contact_points, plan_session


def _cfg() -> TrajectoryConfig:
    # the workbench scenarios' ranges (tools/workbench/scenarios.py)
    return replace(TrajectoryConfig(), indenters=("sphere5", "flat4"), kinds=("poke", "press", "slide", "twist"))


def test_seed_whose_first_contact_leaves_no_room_for_a_second_is_planned():
    # seed 5341 (unit TWIN-G02's gel = the default 12 mm cap) draws a first contact so near the apex that
    # no second point with θ ≤ 0.6 rad is 9 mm away; the placement redraws the pair instead of looping.
    gel, cfg = GelSurface(), _cfg()
    pokes = plan_session(30, 5341, gel, cfg)
    assert len(pokes) == 30
    two = [p for p in pokes if len(p.slots) == 2]
    assert two
    for p in two:
        assert np.linalg.norm(p.position[0] - p.position[1]) >= cfg.min_separation - 2 * cfg.approach_gap


def test_apex_first_contact_restarts_within_the_draw_bound():
    gel, cfg = GelSurface(), _cfg()

    class ApexFirst:                      # the first point at the apex, later draws uniform
        def __init__(self):
            self.rng, self.n = np.random.default_rng(0), 0

        def random(self):
            self.n += 1
            return 0.0 if self.n == 1 else self.rng.random()

        def uniform(self, a, b):
            return self.rng.uniform(a, b)

    pts = contact_points(ApexFirst(), gel, cfg, 2, restart_after=50, max_draws=2000)
    assert len(pts) == 2 and np.linalg.norm(pts[0] - pts[1]) >= cfg.min_separation
    assert np.linalg.norm(pts[0][:2]) > 1e-6          # the apex point was dropped


def test_separation_the_cap_cannot_hold_is_an_error_not_a_hang():
    gel = GelSurface()
    widest = 2 * gel.profile.radius_mm * np.sin(0.6)
    with pytest.raises(ValueError, match="min_separation"):
        contact_points(np.random.default_rng(1), gel, replace(_cfg(), min_separation=widest + 0.1), 2)
    # feasible in principle, practically never drawn: the draw bound ends it
    with pytest.raises(ValueError, match="not found in 3000 draws"):
        contact_points(np.random.default_rng(1), gel, replace(_cfg(), min_separation=widest - 1e-4), 2,
                       restart_after=100, max_draws=3000)
