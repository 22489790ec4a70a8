"""A whole hand per process: N fingertip sensors, one Zenoh session, optional CAN summary.

Each finger runs the single-sensor frame loop (runtime/apps/loop.py SensorLoop over SensorPipeline) in
its own thread, with its own camera, baseline state, calibration, key space
(`tensortouch/<serial>/...`) and liveliness token. onnxruntime releases the GIL, so the threads
run inference in parallel; `inference_workers` bounds how many do at once (= cores: more only
thrashes). The fingers share one zenoh session and either one onnxruntime session (`share_model`,
less memory) or one each (equally fast here within noise: docs/BENCHMARKS.md "Whole hand").

Faults stay inside their finger: a camera that stops (unplugged) makes that finger publish
`camera_lost` in its status while it reconnects every `reconnect_s`; after `offline_after_s` its
liveliness token is withdrawn until the camera is back. A replaced model file is verified and
swapped in without a restart, or rejected with `model_invalid` while the old one keeps running.
CAN send errors show up as `can_errors`. See docs/hand.md.
"""
from __future__ import annotations

import logging
import threading
import time
from pathlib import Path

from ...contracts.errors import CaptureError, TensorTouchError
from ...contracts.store import CalibrationStore
from ..stages.geometry import surface_grid
from .hand_config import FingerConfig, HandConfig
from .zenoh_session import default_endpoint, release

log = logging.getLogger(__name__)

HAND_FLAGS = frozenset({"can_errors", "model_invalid"})   # set by the hand, not by the frame loop


class GatedModel:
    """A FieldModel behind a semaphore shared by all fingers; `swap()` replaces it atomically."""

    def __init__(self, model, gate: threading.Semaphore | None):
        self.inner = model
        self.gate = gate

    def __call__(self, x):
        if self.gate is None:
            return self.inner(x)
        with self.gate:
            return self.inner(x)

    def swap(self, model) -> None:
        self.inner = model

    def __getattr__(self, name):           # package, precision, run_normalized, ...
        return getattr(self.inner, name)


class Finger:
    """One sensor of the hand: camera lifecycle + SensorLoop + Publisher, in its own thread."""

    def __init__(self, hand: "Hand", cfg: FingerConfig, pipeline, slot: int):
        self.hand, self.cfg, self.pipeline, self.slot = hand, cfg, pipeline, slot
        self.publisher = None
        self.ros2 = None                   # this finger's ROS 2 topics (hand config [ros2])
        self.loop = None
        self.state = "starting"            # running | camera_lost | offline | ended | stopped
        self.frames = 0
        self.reconnects = 0
        self.last_error: str | None = None
        self.extra_flags: set[str] = set()
        self.last_frame_t: float | None = None
        self._lost_since: float | None = None
        self.thread = threading.Thread(target=self._run, name=f"finger-{cfg.name}", daemon=True)

    @property
    def sensor_id(self) -> str:
        return self.cfg.serial

    def info(self) -> dict:
        base = self.loop.info() if self.loop is not None else {}
        return {**base, "finger": self.cfg.name, "hand": self.hand.cfg.name, "can_slot": self.slot,
                "source": self.cfg.source_uri, "state": self.state, "gel_surface": surface_grid(self.pipeline.cal)}

    # ------------------------------------------------------------------ thread
    def _run(self) -> None:
        from .loop import LoopConfig, SensorLoop

        hcfg = self.hand.cfg
        stop = self.hand.stop_event
        while not stop.is_set():
            try:
                camera = self.hand.camera_factory(self.cfg)
                camera.connect()
            except CaptureError as exc:
                self._lost(exc)
                stop.wait(hcfg.reconnect_s)
                continue
            self._online()
            loop = SensorLoop(camera, self.pipeline, self.publisher,
                              LoopConfig(publish_fields=hcfg.publish_fields, fields_every=hcfg.fields_every,
                                         status_every_s=hcfg.status_every_s,
                                         max_camera_failures=hcfg.max_camera_failures),
                              store=self.hand.store, on_result=self._on_result, ros2=self.ros2)
            loop.frames = self.frames
            loop.flags |= self.extra_flags
            self.loop = loop
            if stop.is_set():
                camera.disconnect()
                break
            ended = False
            try:
                loop.run()
                ended = not stop.is_set()
            except TensorTouchError as exc:          # camera failed max_camera_failures times in a row
                self._lost(exc)
            except Exception as exc:  # noqa: BLE001 - a bug in one finger must not kill the hand
                log.exception("finger %s: frame loop crashed", self.cfg.name)
                self._lost(exc)
            finally:
                self.frames = loop.frames
                try:
                    camera.disconnect()
                except Exception as exc:  # noqa: BLE001
                    log.debug("disconnect %s: %s", self.cfg.name, exc)
            if ended:
                self.state = "ended"
                log.info("finger %s: source ended after %d frames", self.cfg.name, self.frames)
                break
            if self.state == "camera_lost":
                stop.wait(hcfg.reconnect_s)
        if self.state != "ended":
            self.state = "stopped"

    def _online(self) -> None:
        if self.publisher is None:
            self.publisher = self.hand.make_publisher(self)
        if self.ros2 is None and self.hand.ros2 is not None:
            self.ros2 = self.hand.ros2.sensor(self.sensor_id, calibration=lambda: self.pipeline.cal)
        if self._lost_since is not None:
            self.reconnects += 1
            self.pipeline.set_calibration(self.pipeline.cal)      # fresh baseline after a replug
            log.warning("finger %s (%s): camera back after %.1f s", self.cfg.name, self.sensor_id,
                        time.monotonic() - self._lost_since)
        self._lost_since = None
        self.state = "running"

    def _lost(self, exc: BaseException) -> None:
        now = time.monotonic()
        first = self._lost_since is None
        if first:
            self._lost_since = now
            log.warning("finger %s (%s): camera lost: %s", self.cfg.name, self.sensor_id, exc)
        self.last_error = str(exc)
        self.state = "camera_lost"
        if self.hand.can is not None:
            from ...contracts.can_frame import FingerSummary

            self.hand.can.update(self.slot, FingerSummary(0, status={"camera_lost"} | self._can_bits()))
        if self.publisher is None and first:
            try:
                self.publisher = self.hand.make_publisher(self)
            except TensorTouchError as e:
                log.error("finger %s: cannot declare publisher: %s", self.cfg.name, e)
        if self.publisher is None:
            return
        if now - self._lost_since >= self.hand.cfg.offline_after_s:
            log.warning("finger %s (%s): offline, liveliness token withdrawn", self.cfg.name, self.sensor_id)
            self.publisher.close()
            self.publisher = None
            self.state = "offline"
            return
        p = self.pipeline
        self.publisher.publish_status(
            {"state": "CAMERA_LOST", "flags": sorted({"camera_lost"} | self.extra_flags), "fps": 0.0,
             "frames": self.frames, "error": self.last_error,
             "model": p.model.package.name, "model_hash": p.model.package.sha256(p.model.precision),
             "calibration_version": p.cal.version}, seq=p.seq, t=time.time())

    def _can_bits(self) -> set[str]:
        return {"invalid"} if "model_invalid" in self.extra_flags else set()

    def _on_result(self, result) -> None:
        loop = self.loop
        loop.flags = (loop.flags - HAND_FLAGS) | self.extra_flags
        self.last_frame_t = time.monotonic()
        if self.hand.can is not None:
            from ...contracts.can_frame import summary_from_result

            self.hand.can.update(self.slot, summary_from_result(result, loop.flags))
        if self.hand.on_result is not None:
            self.hand.on_result(self, result)


class Hand:
    """Builds and runs every finger of a HandConfig. `camera_factory(finger_cfg) -> Camera` and an
    open zenoh `session` / python-can `can_bus` may be injected (tests, benchmarks)."""

    def __init__(self, cfg: HandConfig, *, session=None, camera_factory=None, can_bus=None,
                 on_result=None, models_root: Path | None = None):
        from ..pipeline import open_pipeline
        from ..stages.model import FieldModel, find_package
        from .publisher import open_session

        self.cfg = cfg
        self.on_result = on_result
        self.stop_event = threading.Event()
        self.store = CalibrationStore(cfg.calibration_store) if cfg.calibration_store else CalibrationStore()
        self.camera_factory = camera_factory or self._default_camera
        self.package = find_package(cfg.model, models_root)
        gate = threading.BoundedSemaphore(cfg.inference_workers) if cfg.inference_workers > 0 else None
        fingers = [f for f in cfg.fingers if f.enabled]
        cals = {}
        for f in fingers:
            try:
                cals[f.name] = self.store.load(f.calibration_id)
            except TensorTouchError as exc:
                raise TensorTouchError(f"finger {f.name!r} (sensor {f.serial}): {exc}") from None
        shared = GatedModel(FieldModel(self.package, cfg.precision, cfg.threads), gate) if cfg.share_model else None
        self.models: list[GatedModel] = [shared] if shared else []
        self.fingers: dict[str, Finger] = {}
        slots = cfg.slots()
        for f in fingers:
            model = shared or GatedModel(FieldModel(self.package, cfg.precision, cfg.threads), gate)
            if not shared:
                self.models.append(model)
            pipe = open_pipeline(self.package, cals[f.name], sensor_id=f.calibration_id, model=model)
            self.fingers[f.name] = Finger(self, f, pipe, slots[f.name])
        self._own_session = session is None
        self.session = session if session is not None else open_session(
            listen=cfg.listen, connect=cfg.connect, config_file=cfg.zenoh_config, multicast=cfg.multicast)
        self.ros2 = None
        if cfg.ros2 is not None:
            from .ros2_publisher import Ros2Node

            self.ros2 = Ros2Node(self.session, cfg.ros2)
        self.can = None
        if cfg.can is not None or can_bus is not None:
            from ...drivers.can_bus import CanConfig, CanSummarySender

            self.can = CanSummarySender(cfg.can or CanConfig(), max(slots.values()) + 1, bus=can_bus)
        self._model_sig = self._model_signature()
        self._supervisor = threading.Thread(target=self._supervise, name="hand-supervisor", daemon=True)

    # ------------------------------------------------------------------ wiring
    def _default_camera(self, f: FingerConfig):
        from ...drivers.camera import camera_from_uri

        uri = f.source_uri
        live = uri.startswith(("usb:", "v4l2:", "/dev/video"))
        return camera_from_uri(uri) if live else camera_from_uri(uri, **self.cfg.camera_options)

    def make_publisher(self, finger: Finger):
        from .publisher import Publisher

        return Publisher(finger.sensor_id, session=self.session, info=finger.info,
                         status_extra={"finger": finger.cfg.name, "hand": self.cfg.name})

    # ------------------------------------------------------------------ lifetime
    def start(self) -> "Hand":
        import cv2

        cv2.setNumThreads(self.cfg.opencv_threads)     # process-wide, as `tensortouch run` sets it for one sensor
        if self.can is not None:
            self.can.start()
        for f in self.fingers.values():
            f.thread.start()
        self._supervisor.start()
        log.info("hand %s: %d finger(s) %s, model %s (%s, %s), Zenoh %s", self.cfg.name, len(self.fingers),
                 ", ".join(f"{n}={f.sensor_id}" for n, f in self.fingers.items()), self.package.name,
                 self.cfg.precision, "shared session" if self.cfg.share_model else "one session per finger",
                 " ".join(self.cfg.listen + self.cfg.connect) or f"listen {default_endpoint()}")
        return self

    def wait(self, timeout: float | None = None) -> bool:
        """Block until every finger ended (finite replays) or `timeout` s; True if all ended."""
        deadline = None if timeout is None else time.monotonic() + timeout
        for f in self.fingers.values():
            left = None if deadline is None else max(0.0, deadline - time.monotonic())
            f.thread.join(left)
        return all(not f.thread.is_alive() for f in self.fingers.values())

    def stop(self) -> None:
        self.stop_event.set()
        for f in self.fingers.values():
            if f.loop is not None:
                f.loop.stop()
        for f in self.fingers.values():
            if f.thread.is_alive():
                f.thread.join(timeout=5.0)
        if self._supervisor.is_alive():
            self._supervisor.join(timeout=2.0)
        if self.can is not None:
            self.can.stop()
        for f in self.fingers.values():
            if f.publisher is not None:
                f.publisher.close()
                f.publisher = None
        if self.ros2 is not None:
            self.ros2.close()
        if self._own_session:
            release(self.session.close, "session close", log)

    def __enter__(self) -> "Hand":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    def summary(self) -> dict:
        out = {}
        for name, f in self.fingers.items():
            lat = f.loop.latency.summary().get("total", {}) if f.loop else {}
            out[name] = {"sensor_id": f.sensor_id, "state": f.state, "frames": f.loop.frames if f.loop else f.frames,
                         "reconnects": f.reconnects, "p50_ms": lat.get("p50"), "p99_ms": lat.get("p99"),
                         "flags": sorted(f.loop.flags) if f.loop else []}
        return out

    # ------------------------------------------------------------------ supervisor
    def _supervise(self) -> None:
        last_model_check = time.monotonic()
        while not self.stop_event.wait(0.1):
            if self.can is not None:
                can_flags = self.can.flags()
                for f in self.fingers.values():
                    f.extra_flags = (f.extra_flags - {"can_errors"}) | can_flags
            now = time.monotonic()
            if now - last_model_check >= self.cfg.model_poll_s:
                last_model_check = now
                self._check_model()

    def _model_signature(self) -> tuple:
        sig = []
        for p in sorted(self.package.folder.iterdir()):
            try:
                st = p.stat()
                sig.append((p.name, st.st_mtime_ns, st.st_size))
            except OSError:
                sig.append((p.name, None, None))
        return tuple(sig)

    def _check_model(self) -> None:
        from ..stages.model import FieldModel, load_package

        sig = self._model_signature()
        if sig == self._model_sig:
            return
        self._model_sig = sig
        try:
            pkg = load_package(self.package.folder)           # verifies manifest and hashes
            if pkg.size != self.package.size:
                raise TensorTouchError(f"{pkg.folder}: input size {list(pkg.size)} differs from the running "
                                       f"model's {list(self.package.size)} (calibrations are per size)")
            new = [FieldModel(pkg, self.cfg.precision, self.cfg.threads) for _ in self.models]
        except TensorTouchError as exc:
            log.error("hand %s: model files changed but the new package is rejected, keeping the running "
                      "model %s: %s", self.cfg.name, self.package.sha256(self.cfg.precision)[:12], exc)
            for f in self.fingers.values():
                f.extra_flags = f.extra_flags | {"model_invalid"}
            return
        for m, n in zip(self.models, new):
            m.swap(n)
        self.package = pkg
        for f in self.fingers.values():
            f.extra_flags = f.extra_flags - {"model_invalid"}
        log.info("hand %s: model %s reloaded without restart (%s)", self.cfg.name, pkg.name,
                 pkg.sha256(self.cfg.precision)[:12])
