"""Dynamic baseline (seed §III.F): which undeformed image the network compares the current one with.

Silicone creeps back slowly after a press and may keep a permanent offset, so a fixed reference
image drifts out of date. This explicit state machine keeps a *master* baseline (the most stable
of the first N frames) and a *current* baseline that it replaces when the gel has settled into a
new resting state after a contact.

States and transitions (Mb = MSE(image, current baseline), F = force estimate in N or None):

    STARTUP     collect `startup_frames` frames; the one with the smallest MSE to its predecessor
                becomes master and current baseline                              -> STABLE
    STABLE      no contact. F >= force_contact_n or Mb >= contact_mse            -> CONTACT
    CONTACT     in contact; never changes the baseline (creep under load is not a new rest state).
                F known and F < force_release_n (or F unknown and Mb < release_mse):
                    Mb < release_mse (gel already back at the baseline)          -> STABLE
                    otherwise (force gone, gel not recovered)                    -> DETACHMENT
    DETACHMENT  force gone, gel still away from the baseline.
                F >= force_contact_n                                             -> CONTACT
                Mb < release_mse (gel recovered to the current baseline)         -> STABLE
                image settled for hold_time_s: consecutive-frame MSE < stable_mse (seed: 8) on
                every frame AND MSE to the first frame of the settling window < stable_mse
                    -> current baseline := this image (changed=True)             -> STABLE

The window test matters for a gel that creeps back over seconds: at 120 Hz each frame differs
from the previous one by far less than MSE 8 while the gel is still moving, so consecutive-frame
MSE alone would accept a half-recovered gel. Without a force estimate (F None) a held press and a
permanent offset look alike, so the tracker stays in CONTACT until the image returns; the frame
loop feeds the model's previous force estimate, so F is known after the first inference.

MSE follows the seed: mean over all pixels (and channels) of the squared difference on 0-255
values; images given in [0, 1] (the Preprocessor's float output) are scaled by `pixel_scale`.
"""
from __future__ import annotations

import enum
import logging
import math
from dataclasses import dataclass

import numpy as np

from ...contracts.errors import TensorTouchError

log = logging.getLogger(__name__)

SEED_MSE_THRESHOLD = 8.0
"""Seed §III.F: MSE (0-255 images) below which the gel counts as settled."""
SEED_FORCE_CONTACT_N = 1.5
SEED_FORCE_DETACH_N = 1.1
"""Seed §III.C contact / detachment force thresholds (N) on the calibration rig's F/T sensor."""


class BaselineState(enum.Enum):
    STARTUP = "startup"
    STABLE = "stable"
    CONTACT = "contact"
    DETACHMENT = "detachment"


@dataclass(frozen=True)
class BaselineConfig:
    """Named defaults. Thresholds on MSE are for 0-255 images (see module doc)."""

    startup_frames: int = 30
    """N frames collected at start; the most stable one becomes the master baseline."""
    stable_mse: float = SEED_MSE_THRESHOLD
    """Seed MSE_threshold: a settled gel changes less than this between frames (and over hold_time_s)."""
    contact_mse: float = 2.0 * SEED_MSE_THRESHOLD
    """MSE to the current baseline from which the image alone declares contact."""
    release_mse: float = SEED_MSE_THRESHOLD
    """MSE to the current baseline below which the gel counts as back at rest (hysteresis < contact_mse)."""
    force_contact_n: float = 0.2
    """Force estimate (N) from which a contact is declared."""
    force_release_n: float = 0.1
    """Force estimate (N) below which the contact is over (hysteresis < force_contact_n)."""
    hold_time_s: float = 1.0
    """How long the image must stay settled in DETACHMENT before it becomes the baseline (s)."""
    pixel_scale: float = 255.0
    """Multiplier that brings image values to 0-255 before the MSE (255 for [0, 1] floats, 1 for uint8)."""

    def __post_init__(self) -> None:
        problems = []
        if self.startup_frames < 2:
            problems.append(f"startup_frames={self.startup_frames} (need >= 2 to compare consecutive frames)")
        if not 0 < self.release_mse <= self.contact_mse:
            problems.append(f"release_mse={self.release_mse} must be > 0 and <= contact_mse={self.contact_mse}")
        if not 0 <= self.force_release_n <= self.force_contact_n:
            problems.append(f"force_release_n={self.force_release_n} must be >= 0 and <= "
                            f"force_contact_n={self.force_contact_n}")
        if self.stable_mse <= 0 or self.hold_time_s < 0 or self.pixel_scale <= 0:
            problems.append("stable_mse and pixel_scale must be > 0, hold_time_s >= 0")
        if problems:
            raise TensorTouchError("BaselineConfig: " + "; ".join(problems))

    @classmethod
    def calibration_rig(cls, **overrides) -> "BaselineConfig":
        """The seed's force thresholds (1.5 N contact, 1.1 N detach), meant for a real F/T sensor.

        On a fingertip those would let a light, held touch (< 1.1 N) become the baseline, hence the
        lower defaults for the model's own force estimate."""
        return cls(**{"force_contact_n": SEED_FORCE_CONTACT_N, "force_release_n": SEED_FORCE_DETACH_N,
                      **overrides})


@dataclass(frozen=True)
class BaselineUpdate:
    """What `BaselineTracker.update` reports for one frame."""

    state: BaselineState
    previous_state: BaselineState
    baseline: np.ndarray | None
    """Current baseline (same layout as the input images) to feed the model; None during STARTUP."""
    changed: bool
    """True when the baseline changed on this frame (master chosen, or updated after detachment)."""
    mse_baseline: float
    """MSE to the current baseline (before any change made on this frame); NaN during STARTUP."""
    mse_master: float
    mse_previous: float
    """MSE to the previous frame; NaN on the very first frame."""
    settled_s: float
    """How long the image has been settled in DETACHMENT (s); 0 in other states."""

    @property
    def state_changed(self) -> bool:
        return self.state is not self.previous_state


class BaselineTracker:
    """The state machine. Feed one preprocessed image per frame: `update(image, force_n, t)`."""

    def __init__(self, config: BaselineConfig | None = None):
        self.config = config or BaselineConfig()
        self.reset()

    def reset(self) -> None:
        """Forget everything and collect a new master baseline (state STARTUP)."""
        self.state = BaselineState.STARTUP
        self.master: np.ndarray | None = None
        self.baseline: np.ndarray | None = None
        self._previous: np.ndarray | None = None
        self._best: tuple[float, np.ndarray] | None = None  # startup: (mse to predecessor, image)
        self._seen = 0
        self._anchor: np.ndarray | None = None  # first image of the current settling window
        self._anchor_t = 0.0
        self._scratch: np.ndarray | None = None

    def reset_to_master(self) -> None:
        """Drop adaptations: current baseline := master, state STABLE (no-op during STARTUP)."""
        if self.master is not None:
            self.baseline = self.master
            self.state = BaselineState.STABLE
            self._anchor = None

    # -- MSE -------------------------------------------------------------------------------
    def mse(self, a: np.ndarray, b: np.ndarray) -> float:
        """Seed MSE on 0-255 values: mean over all elements of (a - b)^2 * pixel_scale^2."""
        if self._scratch is None or self._scratch.shape != a.shape:
            self._scratch = np.empty(a.shape, dtype=np.float32)
        d = np.subtract(a, b, out=self._scratch, dtype=np.float32).reshape(-1)
        return float(np.dot(d, d)) / d.size * self.config.pixel_scale ** 2

    # -- per frame -------------------------------------------------------------------------
    def update(self, image: np.ndarray, force_n: float | None, t: float, *, owned: bool = False) -> BaselineUpdate:
        """Advance one frame. `image`: preprocessed (e.g. (3, S, S) float32 in [0, 1]); `force_n`:
        the latest force magnitude estimate in N or None; `t`: frame time in s. The tracker keeps images
        (previous frame, baseline, settling anchor), so it copies `image` unless `owned`: the caller hands
        over a fresh array it never writes to again (the pipeline's preprocessed frame)."""
        if self._previous is not None and image.shape != self._previous.shape:
            raise TensorTouchError(f"BaselineTracker: image shape {image.shape} differs from earlier "
                                   f"frames {self._previous.shape}; call reset() after changing the model size")
        if force_n is not None and not math.isfinite(force_n):
            force_n = None
        if not owned:
            image = np.array(image, copy=True)  # the caller may reuse its buffer
        m_prev = self.mse(image, self._previous) if self._previous is not None else math.nan
        before = self.state
        if before is BaselineState.STARTUP:
            update = self._startup(image, m_prev)
        else:
            update = self._track(image, force_n, t, m_prev)
        self._previous = image
        if update.state_changed or update.changed:
            log.debug("baseline %s -> %s%s (Mb=%.2f Mp=%.2f F=%s)", before.value, update.state.value,
                      " [baseline updated]" if update.changed else "", update.mse_baseline,
                      update.mse_previous, force_n)
        return update

    def _startup(self, image: np.ndarray, m_prev: float) -> BaselineUpdate:
        self._seen += 1
        if not math.isnan(m_prev) and (self._best is None or m_prev < self._best[0]):
            self._best = (m_prev, image)
        if self._seen < self.config.startup_frames:
            return BaselineUpdate(BaselineState.STARTUP, BaselineState.STARTUP, None, False,
                                  math.nan, math.nan, m_prev, 0.0)
        best_mse, best = self._best
        if best_mse >= self.config.stable_mse:
            log.warning("master baseline: most stable of %d startup frames still moved (MSE %.1f >= %.1f); "
                        "was the gel touched at start?", self.config.startup_frames, best_mse,
                        self.config.stable_mse)
        self.master = self.baseline = best
        self._best = None
        self.state = BaselineState.STABLE
        m_base = self.mse(image, best)
        return BaselineUpdate(BaselineState.STABLE, BaselineState.STARTUP, best, True,
                              m_base, m_base, m_prev, 0.0)

    def _track(self, image: np.ndarray, force: float | None, t: float, m_prev: float) -> BaselineUpdate:
        c, before = self.config, self.state
        m_base = self.mse(image, self.baseline)
        m_master = m_base if self.baseline is self.master else self.mse(image, self.master)
        pressed = force is not None and force >= c.force_contact_n
        released = (force < c.force_release_n) if force is not None else (m_base < c.release_mse)
        changed, settled = False, 0.0
        state = before
        if before is BaselineState.STABLE:
            if pressed or m_base >= c.contact_mse:
                state = BaselineState.CONTACT
        elif before is BaselineState.CONTACT:
            if released:
                state = BaselineState.STABLE if m_base < c.release_mse else BaselineState.DETACHMENT
        elif before is BaselineState.DETACHMENT:
            if pressed:
                state = BaselineState.CONTACT
            elif m_base < c.release_mse:
                state = BaselineState.STABLE
            else:
                settled = self._settling(image, t, m_prev)
                if settled >= c.hold_time_s:
                    self.baseline, changed, state = image, True, BaselineState.STABLE
        if state is BaselineState.DETACHMENT and before is not BaselineState.DETACHMENT:
            self._anchor, self._anchor_t = image, t  # start the settling window
        if state is not BaselineState.DETACHMENT:
            self._anchor = None
        self.state = state
        return BaselineUpdate(state, before, self.baseline, changed, m_base, m_master, m_prev, settled)

    def _settling(self, image: np.ndarray, t: float, m_prev: float) -> float:
        """Seconds the image has been settled (restarts the window when it moved)."""
        c = self.config
        moved = not m_prev < c.stable_mse
        if not moved and self._anchor is not None:
            moved = self.mse(image, self._anchor) >= c.stable_mse
        if moved or self._anchor is None:
            self._anchor, self._anchor_t = image, t
            return 0.0
        return t - self._anchor_t
