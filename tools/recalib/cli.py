"""`tensortouch recalibrate --sensor ID`: the guided field recalibration (docs/recalibration.md).

Thin shell: opens the calibration store, the model package, the camera (live, replay or twin
recording) and the reference (serial gauge, typed, or the recording's force stream), runs
tools.recalib.session, prints before/after held-out errors and stores a new calibration version
(or refuses). Exit status: 0 stored (or --dry-run), 1 refused / not enough pokes, 2 error.
"""
from __future__ import annotations

import logging
import math
import sys

log = logging.getLogger(__name__)


def register(sub) -> None:
    p = sub.add_parser("recalibrate", help="field recalibration from 5–7 pokes (force correction, θ/φ tables)",
                       description="Guided field recalibration: poke the gel 5–7 times where shown; the "
                                   "reference force comes from a serial force gauge, is typed in, or is "
                                   "read from a recording's force stream. Fits the zero-constrained "
                                   "random-forest force correction, shows before/after held-out error and "
                                   "stores a new calibration version (refused if it is worse, unless --force).")
    p.add_argument("--sensor", required=True, help="sensor id = calibration store folder")
    p.add_argument("--source", help="camera: replay:SESSION_DIR | file:VIDEO | v4l2:/dev/videoN | usb:SERIAL")
    p.add_argument("--gauge", default=None,
                   help="serial:/dev/ttyUSB0 | any pyserial URL (loop://, socket://host:port) | typed | "
                        "session (the replayed recording's wrench stream; default for replay sources that have one, "
                        "else typed)")
    p.add_argument("--gauge-protocol", choices=("tt", "mark10"), default="tt",
                   help="tt: 'F <newtons>*<xor>' stream; mark10: '?' request, '<value> <unit>' reply")
    p.add_argument("--baud", type=int, default=None, help="gauge baud rate (default 115200 tt, 9600 mark10)")
    p.add_argument("--pokes", type=int, default=6, choices=range(5, 8), metavar="{5,6,7}", help="guided pokes to record (5–7)")
    p.add_argument("--reach-deg", type=float, default=None,
                   help="suggest pokes only up to this angle from the dome apex (deg), e.g. the range the model "
                        "was trained on (default: 85 %% of the gel's θ range)")
    p.add_argument("--geometry", action="store_true",
                   help="also refresh θ/φ tables and gel centre (needs true poke positions: twin truth or mocap poses)")
    p.add_argument("--recentre", choices=("rim", "off"), default="rim",
                   help="rim (default): before the pokes, find the gel rim in the first frames (gel untouched) and "
                        "re-crop on it if the centre moved >= 0.5 px or the radius >= 0.5 %% (stored with the "
                        "correction); if no clean rim is found the stored crop is kept. off: keep the stored crop")
    p.add_argument("--rest-frames", type=int, default=10, help="frames at rest for the rim (default 10)")
    p.add_argument("--force", action="store_true", help="store even if the held-out error does not improve")
    p.add_argument("--dry-run", action="store_true", help="fit and report, store nothing")
    p.add_argument("--report", help="write the session report (pokes, errors, decision) as JSON here")
    p.add_argument("--store", help="calibration store folder (default: calibration_store/)")
    p.add_argument("--model", help="model package name or path (default: newest installed)")
    p.add_argument("--precision", choices=("int8", "fp32"), default="int8", help="network precision the recalibration replays")
    p.add_argument("--threads", type=int, default=1, help="onnxruntime threads")
    p.set_defaults(func=cmd_recalibrate, extra="train")


def _frames(camera, pipeline, restamp: bool = False):
    """(t, clusters) per frame; `restamp` puts a replay on the serial gauge's monotonic clock."""
    import time

    from ...drivers.camera.camera import EndOfStream

    while True:
        try:
            frame = camera.read()
        except EndOfStream:
            return
        t = time.monotonic() if restamp else frame.t
        yield t, pipeline.process(frame.image, frame.t).clusters


def _recentre(camera, pipeline, cal, n: int, say):
    """Geometry first: the gel rim in `n` rest frames → (calibration with the re-crop, crop changes,
    rim report, the rest frames). The frames also start the pipeline's baseline (fed by the caller)."""
    from ...contracts.errors import CalibrationError
    from ...drivers.camera.camera import EndOfStream
    from .rim import crop_changes, fit_rim, recrop, rest_image

    say(f"keep the gel untouched: reading {n} frames to find the gel rim")
    frames = []
    try:
        for _ in range(n):
            frames.append(camera.read())
    except EndOfStream:
        pass
    try:
        fit = fit_rim(rest_image([f.image for f in frames]), cal.gel_center_px, cal.gel_radius_px)
    except CalibrationError as exc:
        say(f"crop kept (no re-centring): {exc}")
        return cal, {}, {"error": str(exc)}, frames
    changes = crop_changes(cal, fit)
    say(f"gel rim: centre ({fit.center[0]:.1f}, {fit.center[1]:.1f}) px, {fit.shift_px:.2f} px from the stored one; "
        f"radius x{fit.scale:.4f}; " + ("crop re-centred" if changes else "crop kept (within tolerance)"))
    new = recrop(cal, changes)
    if changes:
        pipeline.set_calibration(new, pipeline.correction)
    return new, changes, {**fit.to_dict(), "changes": changes}, frames


def _chain(first, pipeline, rest, restamp: bool = False):
    """The rest frames (through the pipeline, so its baseline starts with them) and then the stream."""
    import time

    for f in first:
        yield (time.monotonic() if restamp else f.t), pipeline.process(f.image, f.t).clusters
    yield from rest


def _reference(args, session, say):
    from ...contracts.errors import TensorTouchError
    from .session import GaugeReference, StreamReference, TypedReference

    kind = args.gauge or ("session" if session is not None and session.has("wrench") else "typed")
    if kind == "session":
        if session is None or not session.has("wrench"):
            raise TensorTouchError("--gauge session needs a replay:SESSION_DIR source with a wrench stream")
        return StreamReference.from_session(session), None
    if kind == "typed":
        return TypedReference(say=say), None
    from ...drivers.gauge import ForceGauge, GaugeConfig

    url = kind.split(":", 1)[1] if kind.startswith("serial:") else kind
    baud = args.baud or (9600 if args.gauge_protocol == "mark10" else 115200)
    gauge = ForceGauge(GaugeConfig(url, protocol=args.gauge_protocol, baudrate=baud)).open()
    gauge.start()
    return GaugeReference(gauge), gauge


def _print_errors(an, say) -> None:
    loo, act = an.fit.loo, an.active
    say(f"held-out force magnitude error over {len(an.pokes)} pokes (leave-one-out):")
    say(f"  uncorrected model          MAE {loo['before']['mae_n']:.3f} N  ({loo['before']['mre']:.1%})")
    say(f"  active calibration         MAE {act['mae_n']:.3f} N  ({act['mre']:.1%})")
    say(f"  new correction (held out)  MAE {loo['after']['mae_n']:.3f} N  ({loo['after']['mre']:.1%})")
    if an.geometry is not None:
        g = an.geometry
        rms = sum(r * r for r in g.residual_deg["theta"]) / len(g.residual_deg["theta"])
        say(f"geometry: gel centre ({g.center[0]:.1f}, {g.center[1]:.1f}) px, moved {g.fit['center_shift_px']:.2f} px; "
            f"θ residual rms {rms ** 0.5:.2f}°")


def cmd_recalibrate(args, say=None) -> int:
    from ...contracts.errors import TensorTouchError
    from ...contracts.session import load_session
    from ...contracts.store import CalibrationStore
    from ...drivers.camera import camera_from_uri
    from ...runtime.pipeline import open_pipeline
    from ...runtime.stages.correction import ForceCorrection
    from ...runtime.stages.model import find_package
    from .pokes import PokeRules
    from .session import (
        SessionConfig,
        analyse,
        run_guided,
        session_truth_xyz,
    )
    from .store_ops import store_recalibration

    say = say or (lambda msg: print(msg, file=sys.stderr))
    if args.report:
        _check_report_path(args.report)        # before anything is stored
    store = CalibrationStore(args.store) if args.store else CalibrationStore()
    cal = stored = store.load(args.sensor)
    package = find_package(args.model)
    if not args.source:
        raise TensorTouchError("--source is required (the live camera, or replay:SESSION_DIR)")
    path, _, query = args.source.partition("?")
    session = load_session(path.split(":", 1)[1]) if path.startswith("replay:") else None
    pipeline = open_pipeline(package, cal, precision=args.precision, threads=args.threads, sensor_id=args.sensor,
                             correction=ForceCorrection(None, None))  # raw model force, effects on
    reach = getattr(args, "reach_deg", None)
    cfg = SessionConfig(pokes=args.pokes, rules=PokeRules(reach_theta_rad=None if reach is None else math.radians(reach)))
    reference, gauge = _reference(args, session, say)
    say(f"recalibrating {args.sensor} (active {cal.version}) with model {package.name}; reference: {reference.name}")
    try:
        # a replay paired with a live serial gauge runs at its recorded pace on the gauge's clock
        live_ref = gauge is not None
        fast = {"realtime": False} if session is not None and not live_ref and "realtime=" not in query else {}
        with camera_from_uri(args.source, **fast) as cam:
            crop, rim, first = {}, None, []
            if getattr(args, "recentre", "off") == "rim":
                cal, crop, rim, first = _recentre(cam, pipeline, cal, getattr(args, "rest_frames", 10), say)
            restamp = live_ref and session is not None
            frames = _chain(first, pipeline, _frames(cam, pipeline, restamp=restamp), restamp)
            outcome = run_guided(frames, cal, reference, cfg, say)
    except TensorTouchError as exc:
        raise TensorTouchError(f"{exc}\nsession aborted: nothing was stored, the active calibration is still "
                               f"{store.current(args.sensor)}") from None
    finally:
        if gauge is not None:
            gauge.close()
    if len(outcome.accepted) < cfg.fit.min_pokes:
        say(f"only {len(outcome.accepted)} pokes accepted ({len(outcome.rejected)} rejected); need "
            f"{cfg.fit.min_pokes}. Nothing stored; active calibration still {cal.version}.")
        return 1
    truth = session_truth_xyz(session, outcome.accepted) if args.geometry and session is not None else None
    if args.geometry and truth is None:
        raise TensorTouchError("--geometry needs true poke positions: use a replay:SESSION_DIR source "
                               "recorded with mocap poses or from the twin")
    an = analyse(outcome.accepted, cal, cfg, force=args.force, truth_xyz=truth)
    _print_errors(an, say)
    say(an.decision.reason)
    report = {"sensor": args.sensor, "base_version": cal.version, "model": package.name,
              "reference": reference.name, "rim": rim, **an.summary(),
              "accepted": [p.to_dict() for p in outcome.accepted], "rejected": [p.to_dict() for p in outcome.rejected]}
    code = 1
    crop_prov = {"from": {k: stored.meta[k] for k in ("gel_center_px", "gel_radius_px")}, "rim": rim}
    if an.decision.store and not args.dry_run:
        geometry = None if an.geometry is None else {"gel_center_px": an.geometry.center, "theta": an.geometry.theta,
                                                     "phi": an.geometry.phi}
        prov = {"pokes": len(an.pokes), "source": args.source, "reference": reference.name,
                "model": {"name": package.name, "sha256": package.sha256(args.precision)},
                "errors": {"uncorrected": an.fit.loo["before"], "active": an.active, "held_out": an.fit.loo["after"]},
                "forced": bool(args.force and an.decision.after_mae_n >= an.decision.before_mae_n),
                "poke_data": [{"pred_force_n": p.pred_force.tolist(), "ref_force_n": p.ref_force_n,
                               "uv_px": p.uv_px.tolist()} for p in outcome.accepted]}
        if crop:
            prov["crop"] = crop_prov
        version = store_recalibration(store, cal, prov, correction=(an.fit.spec, an.fit.onnx_bytes), geometry=geometry,
                                      crop=crop)
        report["stored_version"] = version
        say(f"stored {args.sensor}/{version} and made it active (was {cal.version}); a running sensor picks it up "
            f"within a second; undo with: tensortouch calib rollback {args.sensor}")
        code = 0
    elif args.dry_run:
        say("--dry-run: nothing stored")
        code = 0
    elif crop:   # the correction was refused, but the rim showed a moved crop: store the re-crop alone
        prov = {"method": "recalibrate-rim", "pokes": 0, "source": args.source,
                "crop": crop_prov,
                "errors": {"uncorrected": an.fit.loo["before"], "active": an.active, "held_out": an.fit.loo["after"]}}
        version = store_recalibration(store, stored, prov, crop=crop)
        report["stored_version"] = version
        say(f"the correction was not stored; the re-centred crop alone was stored as {args.sensor}/{version} "
            f"(was {stored.version}); undo with: tensortouch calib rollback {args.sensor}")
        code = 1
    if args.report:
        try:
            _write_report(args.report, report)
        except OSError as exc:
            stored = report.get("stored_version")
            what = (f"{args.sensor}/{stored} was stored and is active (was {cal.version}; undo with: "
                    f"tensortouch calib rollback {args.sensor})" if stored and store.current(args.sensor) == stored
                    else f"{args.sensor}/{stored} was stored" if stored
                    else f"nothing was stored, the active calibration is still {store.current(args.sensor)}")
            raise TensorTouchError(f"--report {args.report}: cannot write the report ({exc.strerror or exc}); "
                                   f"{what}") from None
    return code


def _check_report_path(path: str) -> None:
    """--report must name a file in an existing, writable folder: checked before anything is stored."""
    import os
    from pathlib import Path

    from ...contracts.errors import TensorTouchError

    p = Path(path)
    folder = p.parent if str(p.parent) else Path(".")
    if p.is_dir():
        raise TensorTouchError(f"--report {path}: is a folder, expected a file name; nothing was stored")
    if not folder.is_dir():
        raise TensorTouchError(f"--report {path}: folder {folder} does not exist; nothing was stored")
    if not os.access(folder, os.W_OK | os.X_OK):
        raise TensorTouchError(f"--report {path}: folder {folder} is not writable; nothing was stored")


def _write_report(path: str, report: dict) -> None:
    """The report as JSON, written atomically (contracts.files)."""
    from ...contracts.files import atomic_write_json

    atomic_write_json(path, report, indent=2, default=float, mkdir=False)

