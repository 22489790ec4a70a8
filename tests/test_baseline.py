"""Dynamic baseline state machine (seed §III.F): every transition, slow recovery, permanent offset."""
import math

import numpy as np
import pytest
from tensortouch.contracts.errors import TensorTouchError
from tensortouch.runtime.stages.baseline import (
    SEED_FORCE_CONTACT_N,
    SEED_MSE_THRESHOLD,
    BaselineConfig,
    BaselineState,
    BaselineTracker,
)

S = 32
FPS = 120.0
NOISE = 1.0  # camera noise, 0-255 units -> MSE between two noisy frames ~ 2 * NOISE^2


def rest_image(seed=0):
    """A smooth gel-like (3, S, S) image in [0, 1]."""
    yy, xx = np.mgrid[0:S, 0:S] / S
    base = np.stack([0.4 + 0.2 * np.sin(3 * xx + c) * np.cos(2 * yy) for c in range(3)])
    return base.astype(np.float32)


def blob(amplitude, cx=0.5, cy=0.5, sigma=0.2):
    """A deformation pattern; `amplitude` in 0-255 units."""
    yy, xx = np.mgrid[0:S, 0:S] / S
    g = np.exp(-((xx - cx) ** 2 + (yy - cy) ** 2) / (2 * sigma ** 2))
    return np.repeat((amplitude / 255.0 * g)[None], 3, axis=0).astype(np.float32)


def true_mse(a, b):
    """The seed's formula written out: mean of squared 0-255 differences."""
    return float(np.mean((a.astype(np.float64) * 255 - b.astype(np.float64) * 255) ** 2))


class Rig:
    """Drives a tracker with noisy frames at FPS and records every update."""

    def __init__(self, config=None, seed=1):
        self.tracker = BaselineTracker(config or BaselineConfig())
        self.rest = rest_image()
        self.rng = np.random.default_rng(seed)
        self.k = 0
        self.log = []

    def frame(self, deformation=0.0, force=None):
        noise = self.rng.normal(0, NOISE / 255.0, self.rest.shape).astype(np.float32)
        image = np.clip(self.rest + deformation + noise, 0, 1)
        u = self.tracker.update(image, force, self.k / FPS)
        self.k += 1
        self.log.append(u)
        return u, image

    def run(self, seconds, deformation=lambda t: 0.0, force=lambda t: None):
        start = self.k
        n = int(round(seconds * FPS))
        return [self.frame(deformation((self.k - start) / FPS), force((self.k - start) / FPS))[0]
                for _ in range(n)]

    def start(self):
        self.run(self.tracker.config.startup_frames / FPS)
        assert self.tracker.state is BaselineState.STABLE
        return self


def states(updates):
    """Run-length list of states, e.g. ['contact', 'detachment', 'stable']."""
    out = []
    for u in updates:
        if not out or out[-1] != u.state.value:
            out.append(u.state.value)
    return out


# -- STARTUP -> STABLE -------------------------------------------------------------------------
def test_startup_picks_most_stable_frame_as_master():
    cfg = BaselineConfig(startup_frames=10)
    tracker = BaselineTracker(cfg)
    rest = rest_image()
    # the gel moves during startup except between frames 6 and 7: frame 7 is the most stable
    offsets = [0, 30, 60, 90, 60, 30, 5, 5.5, 40, 80]
    frames = [np.clip(rest + blob(a), 0, 1) for a in offsets]
    for k, img in enumerate(frames[:-1]):
        u = tracker.update(img, None, k / FPS)
        assert u.state is BaselineState.STARTUP and u.baseline is None and not u.changed
    u = tracker.update(frames[-1], None, 9 / FPS)
    assert u.state is BaselineState.STABLE and u.previous_state is BaselineState.STARTUP
    assert u.changed and u.state_changed
    np.testing.assert_array_equal(tracker.master, frames[7])
    np.testing.assert_array_equal(u.baseline, frames[7])
    assert u.mse_baseline == pytest.approx(true_mse(frames[-1], frames[7]), rel=1e-4)


def test_startup_warns_when_gel_moves(caplog):
    tracker = BaselineTracker(BaselineConfig(startup_frames=4))
    rest = rest_image()
    with caplog.at_level("WARNING", logger="tensortouch.runtime.stages.baseline"):
        for k, a in enumerate([0, 40, 80, 120]):
            u = tracker.update(np.clip(rest + blob(a), 0, 1), None, k / FPS)
    assert u.state is BaselineState.STABLE
    assert "touched at start" in caplog.text


def test_mse_matches_seed_formula_for_float_and_uint8():
    rng = np.random.default_rng(3)
    a, b = rng.random((3, S, S), dtype=np.float32), rng.random((3, S, S), dtype=np.float32)
    assert BaselineTracker().mse(a, b) == pytest.approx(true_mse(a, b), rel=1e-5)
    a8, b8 = (a * 255).round().astype(np.uint8), (b * 255).round().astype(np.uint8)
    expect = float(np.mean((a8.astype(float) - b8.astype(float)) ** 2))
    assert BaselineTracker(BaselineConfig(pixel_scale=1.0)).mse(a8, b8) == pytest.approx(expect, rel=1e-5)


# -- STABLE -> CONTACT ---------------------------------------------------------------------------
def test_stable_to_contact_by_force_alone():
    rig = Rig().start()
    ups = rig.run(0.2, force=lambda t: 0.0)
    assert states(ups) == ["stable"]
    u, _ = rig.frame(0.0, force=0.5)  # image unchanged (e.g. a stiff, small indenter), force says contact
    assert u.state is BaselineState.CONTACT and u.previous_state is BaselineState.STABLE
    assert u.mse_baseline < SEED_MSE_THRESHOLD


def test_stable_to_contact_by_image_alone_without_force():
    rig = Rig().start()
    u, _ = rig.frame(blob(60), force=None)
    assert true_mse(rig.rest + blob(60), rig.rest) > rig.tracker.config.contact_mse
    assert u.state is BaselineState.CONTACT


def test_noise_alone_stays_stable():
    rig = Rig().start()
    ups = rig.run(1.0, force=lambda t: 0.01)
    assert states(ups) == ["stable"] and not any(u.changed for u in ups)
    assert max(u.mse_previous for u in ups) < SEED_MSE_THRESHOLD


# -- CONTACT -> STABLE / DETACHMENT --------------------------------------------------------------
def test_contact_to_stable_when_released_and_gel_back():
    rig = Rig().start()
    rig.run(0.3, deformation=lambda t: blob(80), force=lambda t: 2.0)
    assert rig.tracker.state is BaselineState.CONTACT
    u, _ = rig.frame(0.0, force=0.0)  # elastic gel: back at rest the moment the force is gone
    assert u.previous_state is BaselineState.CONTACT and u.state is BaselineState.STABLE
    assert not u.changed and rig.tracker.baseline is rig.tracker.master


def test_contact_to_detachment_when_released_but_gel_deformed():
    rig = Rig().start()
    rig.run(0.3, deformation=lambda t: blob(80), force=lambda t: 2.0)
    u, _ = rig.frame(blob(70), force=0.05)
    assert u.previous_state is BaselineState.CONTACT and u.state is BaselineState.DETACHMENT
    assert u.mse_baseline > rig.tracker.config.release_mse


def test_contact_release_without_force_needs_the_image_back():
    rig = Rig().start()
    ups = rig.run(0.5, deformation=lambda t: blob(80), force=lambda t: None)
    assert states(ups) == ["contact"]
    u, _ = rig.frame(0.0, force=None)
    assert u.state is BaselineState.STABLE


# -- DETACHMENT -> CONTACT / STABLE --------------------------------------------------------------
def test_detachment_back_to_contact_when_force_returns():
    rig = Rig().start()
    rig.run(0.3, deformation=lambda t: blob(80), force=lambda t: 2.0)
    ups = rig.run(0.4, deformation=lambda t: blob(50), force=lambda t: 0.0)
    assert states(ups) == ["detachment"] and ups[-1].settled_s > 0
    u, _ = rig.frame(blob(50), force=1.0)
    assert u.previous_state is BaselineState.DETACHMENT and u.state is BaselineState.CONTACT
    assert u.settled_s == 0.0
    # the settling window starts over after the next release
    ups = rig.run(0.1, deformation=lambda t: blob(50), force=lambda t: 0.0)
    assert ups[0].state is BaselineState.DETACHMENT and ups[-1].settled_s < 0.1


def test_slowly_recovering_gel_is_not_taken_as_baseline():
    """Exponential creep back to rest over seconds: consecutive frames differ by far less than
    MSE 8, yet the half-recovered gel must not become the baseline."""
    cfg = BaselineConfig(hold_time_s=1.0)
    rig = Rig(cfg).start()
    rig.run(0.5, deformation=lambda t: blob(80), force=lambda t: 3.0)
    tau = 1.5
    ups = rig.run(6.0, deformation=lambda t: blob(80 * math.exp(-t / tau)), force=lambda t: 0.0)
    detach = [u for u in ups if u.state is BaselineState.DETACHMENT]
    assert detach, "release with a deformed gel must enter DETACHMENT"
    early = [u for u in ups[: int(2.0 * FPS)]]
    # during the first 2 s every consecutive-frame MSE is below the seed threshold ...
    assert max(u.mse_previous for u in early) < SEED_MSE_THRESHOLD
    # ... but the gel is still far from rest, and the baseline must not have moved
    assert not any(u.changed for u in early)
    assert all(u.state is BaselineState.DETACHMENT for u in early)
    # it ends STABLE; if the baseline moved at all, it moved to an (almost) fully recovered gel
    assert ups[-1].state is BaselineState.STABLE
    assert true_mse(rig.tracker.baseline, rig.rest) < SEED_MSE_THRESHOLD
    assert ups[-1].mse_master < SEED_MSE_THRESHOLD


def test_recovered_gel_returns_to_stable_without_update():
    rig = Rig(BaselineConfig(hold_time_s=2.0)).start()
    rig.run(0.3, deformation=lambda t: blob(80), force=lambda t: 2.0)
    ups = rig.run(2.0, deformation=lambda t: blob(80 * math.exp(-t / 0.2)), force=lambda t: 0.0)
    assert states(ups) == ["detachment", "stable"]
    assert not any(u.changed for u in ups) and rig.tracker.baseline is rig.tracker.master


def test_permanent_offset_becomes_new_baseline_and_master_is_kept():
    cfg = BaselineConfig(hold_time_s=0.5)
    rig = Rig(cfg).start()
    master = rig.tracker.master.copy()
    rig.run(0.5, deformation=lambda t: blob(90), force=lambda t: 2.5)
    offset = blob(30, cx=0.45)  # the gel keeps a dent: MSE to the old rest well above release
    assert true_mse(rig.rest + offset, rig.rest) > cfg.contact_mse
    ups = rig.run(3.0, deformation=lambda t: offset + blob(60 * math.exp(-t / 0.2), cx=0.45),
                  force=lambda t: 0.0)
    changed = [i for i, u in enumerate(ups) if u.changed]
    assert len(changed) == 1
    u = ups[changed[0]]
    assert u.previous_state is BaselineState.DETACHMENT and u.state is BaselineState.STABLE
    assert u.settled_s >= cfg.hold_time_s
    assert true_mse(rig.tracker.baseline, rig.rest + offset) < SEED_MSE_THRESHOLD
    np.testing.assert_array_equal(rig.tracker.master, master)
    after = ups[changed[0] + 1:]
    assert after and all(x.state is BaselineState.STABLE for x in after)
    assert max(x.mse_baseline for x in after) < cfg.release_mse
    assert min(x.mse_master for x in after) > cfg.contact_mse
    rig.tracker.reset_to_master()
    assert rig.tracker.baseline is rig.tracker.master


def test_slow_drift_during_contact_does_not_steal_baseline():
    cfg = BaselineConfig(hold_time_s=0.5)
    rig = Rig(cfg).start()
    # a held press that creeps slowly (viscoelastic) for 8 s: image nearly static frame to frame
    ups = rig.run(8.0, deformation=lambda t: blob(70 + 2.0 * t), force=lambda t: 2.0 - 0.05 * t)
    assert states(ups) == ["contact"]
    assert not any(u.changed for u in ups) and rig.tracker.baseline is rig.tracker.master
    assert max(u.mse_previous for u in ups[5:]) < SEED_MSE_THRESHOLD
    # without a force estimate a steady press also keeps the baseline
    ups = rig.run(3.0, deformation=lambda t: blob(74), force=lambda t: None)
    assert states(ups) == ["contact"] and not any(u.changed for u in ups)


def test_force_hysteresis_between_thresholds():
    cfg = BaselineConfig()
    mid = (cfg.force_contact_n + cfg.force_release_n) / 2
    rig = Rig(cfg).start()
    ups = rig.run(0.5, force=lambda t: mid)
    assert states(ups) == ["stable"]
    rig.frame(blob(60), force=cfg.force_contact_n)
    ups = rig.run(0.5, deformation=lambda t: blob(60), force=lambda t: mid)
    assert states(ups) == ["contact"]


def test_movement_restarts_the_settling_window():
    cfg = BaselineConfig(hold_time_s=0.5)
    rig = Rig(cfg).start()
    rig.run(0.3, deformation=lambda t: blob(80), force=lambda t: 2.0)
    ups = rig.run(0.4, deformation=lambda t: blob(50), force=lambda t: 0.0)
    assert ups[-1].settled_s == pytest.approx(0.4 - 1 / FPS, abs=2 / FPS)
    u, _ = rig.frame(blob(50) + blob(40, cx=0.2), force=0.0)  # a jolt: big consecutive MSE
    assert u.mse_previous >= SEED_MSE_THRESHOLD
    assert u.state is BaselineState.DETACHMENT and u.settled_s == 0.0


def test_calibration_rig_preset_uses_seed_forces():
    cfg = BaselineConfig.calibration_rig(hold_time_s=0.2)
    assert cfg.force_contact_n == SEED_FORCE_CONTACT_N and cfg.hold_time_s == 0.2


@pytest.mark.parametrize("kwargs", [dict(startup_frames=1), dict(release_mse=20, contact_mse=10),
                                    dict(force_contact_n=0.1, force_release_n=0.2), dict(hold_time_s=-1)])
def test_bad_config_is_a_clear_error(kwargs):
    with pytest.raises(TensorTouchError, match="BaselineConfig"):
        BaselineConfig(**kwargs)


def test_image_shape_change_is_a_clear_error():
    tracker = BaselineTracker(BaselineConfig(startup_frames=2))
    tracker.update(rest_image(), None, 0.0)
    with pytest.raises(TensorTouchError, match="reset"):
        tracker.update(np.zeros((3, 16, 16), np.float32), None, 0.01)


def test_tracker_copies_input_buffer():
    tracker = BaselineTracker(BaselineConfig(startup_frames=2))
    buf = rest_image()
    tracker.update(buf, None, 0.0)
    tracker.update(buf, None, 0.01)
    kept = tracker.baseline.copy()
    buf += 0.5  # the frame loop reuses its buffer
    np.testing.assert_array_equal(tracker.baseline, kept)
