"""Rig estimate cores (tools/train/rig_estimate.py): clock lags, contact onsets and the onset fit, hand-worked."""
import numpy as np
from tensortouch.tools.train.rig_estimate import clock_lag, contact_onsets, fit_translation, near_surface
from tensortouch.tools.twin.geometry import GelSurface


def test_clock_lag_contact_onsets_and_the_onset_fit_hand_worked():
    t = np.arange(0.0, 10.0, 0.005)
    bump = np.exp(-0.5 * ((t - 5.0) / 0.2) ** 2)
    assert abs(clock_lag([(t, bump, t + 0.023, [bump])]) - 0.023) < 0.001   # sig stamped 23 ms late
    assert abs(clock_lag([(t, bump, t - 0.041, [bump])]) + 0.041) < 0.001
    force = 2.0 * bump ** 1.5 + 0.1                                       # a curved, monotone relation
    assert abs(clock_lag([(t, force, t + 0.012, [bump])], grid_s=0.0005) - 0.012) < 0.0005
    on = contact_onsets(np.array([0.0, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6]), np.array([0, 0, 0.05, 0.15, 0.0, 0.2, 0.2]),
                        0.1, 0.15)
    np.testing.assert_allclose(on, [0.25])               # the 0.45 s crossing follows only 0.1 s of quiet
    gel = GelSurface()
    c, rho = gel.profile.center_z_mm, gel.profile.radius_mm
    th, ph = np.meshgrid(np.linspace(0.0, 0.6, 4), np.linspace(0, 2 * np.pi, 6, endpoint=False))
    d = np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], -1).reshape(-1, 3)
    pts = np.array([0.0, 0.0, c]) + (rho - 0.05) * d + [0.2, -0.1, 0.0]    # 0.05 mm deep, shifted sideways
    shift, depth, on_bound = fit_translation(pts, c, rho)
    np.testing.assert_allclose(shift, [0.2, -0.1, 0.0], atol=1e-6)
    assert abs(depth - 0.05) < 1e-6 and not on_bound


def test_the_onset_fit_holds_against_an_outlier_and_says_when_it_ends_on_a_bound():
    """Eight onsets on one side of the cap (a 6-poke session's spread) plus one 4 mm above the gel (F/T noise
    crossing the onset level at rest): unbounded least squares had thrown the shift 32 mm sideways with an
    onset depth of -22 mm. The gate leaves the outlier out and the fit keeps the true shift; a fit pushed
    onto a bound says so."""
    gel = GelSurface()
    c, rho = gel.profile.center_z_mm, gel.profile.radius_mm
    rng = np.random.default_rng(3)
    th, ph = rng.uniform(0.1, 0.5, 8), rng.uniform(-0.6, 1.9, 8)
    d = np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], -1)
    pts = np.array([0.0, 0.0, c]) + (rho - 0.1) * d + [0.3, 0.2, 0.0]
    bad = np.vstack([pts, [[-7.27, 5.2, 12.05]]])
    assert np.hypot(*(fit_translation(bad, c, rho)[0][:2] - [0.3, 0.2])) > 0.5   # one outlier moves even a robust fit
    keep = near_surface(bad, c, rho, 1.5)
    assert keep.tolist() == [True] * 8 + [False]
    shift, depth, on_bound = fit_translation(bad[keep], c, rho, 2.0, (-1.0, 1.0))
    np.testing.assert_allclose(shift[:2], [0.3, 0.2], atol=0.01)
    assert abs(depth - 0.1) < 0.01 and not on_bound
    far = pts + [5.0, 0.0, 0.0]                      # 5 mm off: beyond the 2 mm a calibrated rig can be off
    assert fit_translation(far, c, rho, 2.0, (-1.0, 1.0))[2]
