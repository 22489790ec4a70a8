"""`tensortouch twin record|show|calibration|demo|gauge` (registered through the tensortouch.commands entry point).

    tensortouch twin record --unit TWIN-0001 --pokes 5 --effect temperature_softening:alpha=0.02 \\
        --out cache/sessions/s1 [--seed 0] [--physics fe|hertz-fallback] [--frames ffv1|mjpg|png]
    tensortouch twin show SESSION --out sheet.png
    tensortouch twin calibration --unit TWIN-0001 [--store DIR]   # write the unit's true calibration
"""
from __future__ import annotations

import logging

from ..command_group import command_group
from ..progress import stage_progress

log = logging.getLogger(__name__)


def _record(args) -> int:
    from ...contracts.errors import TensorTouchError
    from .effect_specs import parse_effect_arg
    from .record import RecordConfig, Recorder

    try:
        effects = [parse_effect_arg(e) for e in args.effect or []]
    except ValueError as exc:
        raise TensorTouchError(str(exc)) from None
    cfg = RecordConfig(serial=args.unit, pokes=args.pokes, seed=args.seed, effects=effects,
                       physics=args.physics, frame_format=args.frames, model_size=args.model_size, world=args.world)
    cfg.rig.camera_fps = args.fps
    if args.hysteresis_tau is not None:
        cfg.rig.hysteresis_tau_s = args.hysteresis_tau
    if args.hysteresis_fraction is not None:
        cfg.rig.hysteresis_fraction = args.hysteresis_fraction
    cfg.noise.jpeg_quality = args.jpeg
    cfg.noise.exposure = args.exposure
    if args.read_noise is not None:
        cfg.noise.read_sigma = args.read_noise
    rec = Recorder(cfg, args.out, progress=stage_progress(cfg.serial))
    if args.calibration:
        from .unit import write_true_calibration

        version = write_true_calibration(rec.unit, args.store, args.model_size)
        print(f"true calibration of {args.unit}: {version}")
    path = rec.run()
    t = rec.timing
    print(f"session {path}: {t.get('frames_rendered', 0)} frames rendered, physics {t['physics_s']:.1f} s, "
          f"render {t['render_s']:.1f} s, total {t['total_s']:.1f} s")
    return 0


def _show(args) -> int:
    from .show import contact_sheet

    print(contact_sheet(args.session, args.out, n=args.frames))
    return 0


def _calibration(args) -> int:
    from .unit import TwinUnit, write_true_calibration

    print(write_true_calibration(TwinUnit(args.unit), args.store, args.model_size))
    return 0


def register(sub) -> None:
    tsub = command_group(sub, "twin", "digital twin sensor: record sessions, contact sheets, true calibration",
                         "twin_command", "TWIN_COMMAND", extra="train")
    r = tsub.add_parser("record", help="simulate a recording session of one twin unit")
    r.add_argument("--unit", required=True, help="twin unit serial (sets the unit's variation; = sensor id)")
    r.add_argument("--pokes", type=int, default=5, help="number of indenter pokes in the plan")
    r.add_argument("--effect", action="append", metavar="NAME:param=value,...",
                   help="switch a physical effect on in truth (repeatable); see docs/effects.md")
    r.add_argument("--out", required=True, help="session directory (resumes an unfinished one)")
    r.add_argument("--seed", type=int, default=0, help="plan seed (indenters, positions, depths)")
    r.add_argument("--physics", choices=("fe", "hertz-fallback"), default="fe",
                   help="fe (default): per-poke FE solves, cached; hertz-fallback: analytic, for quick previews")
    r.add_argument("--frames", choices=("ffv1", "mjpg", "png"), default="ffv1",
                   help="ffv1 = lossless .avi (default), png = lossless folder, mjpg = small lossy .avi")
    r.add_argument("--world", choices=("label", "rig"), default="label",
                   help="label (default): the labels' own FE and an ideal rig (the ceiling); rig: per-unit gel, "
                        "Yeoh, mocap extrinsic error, F/T bias + cross-talk, clock offsets, coloured noise, finer "
                        "FE (docs/twin.md \"Worlds\")")
    r.add_argument("--fps", type=float, default=30.0, help="camera frame rate (frames/s)")
    r.add_argument("--model-size", type=int, default=128, help="model input size (px) of the calibration written with the session")
    r.add_argument("--hysteresis-tau", type=float, help="gel recovery time constant, s (default 1.5)")
    r.add_argument("--hysteresis-fraction", type=float, help="share of the deformation that recovers slowly (default 0.15)")
    r.add_argument("--exposure", type=float, default=1.0, help="exposure gain on rendered intensities")
    r.add_argument("--read-noise", type=float, help="camera read noise std on 0..1 intensities (default 0.006)")
    r.add_argument("--jpeg", type=int, default=0, metavar="QUALITY",
                   help="JPEG round trip of every frame inside the camera (0 = off), as a USB MJPG camera")
    r.add_argument("--calibration", action="store_true", help="also write the unit's true calibration")
    r.add_argument("--store", help="calibration store root (default: contracts.paths.calibration_dir())")
    r.set_defaults(func=_record, resume_hint="an unfinished session folder is resumed")
    s = tsub.add_parser("show", help="contact sheet of a session: frames, deformation, force trace")
    s.add_argument("session", help="session folder")
    s.add_argument("--out", required=True, help="PNG file to write")
    s.add_argument("--frames", type=int, default=5, help="frames in the sheet (rest + force peaks)")
    s.set_defaults(func=_show)
    c = tsub.add_parser("calibration", help="write a twin unit's true calibration into the calibration store")
    c.add_argument("--unit", required=True, help="twin unit serial (e.g. TWIN-0001)")
    c.add_argument("--store", help="calibration store root (default: contracts.paths.calibration_dir())")
    c.add_argument("--model-size", type=int, default=128, help="model input size (px) of the tables")
    c.set_defaults(func=_calibration)
    for name, module, helptext in (
            ("demo", "tensortouch.tools.twin.demo", "regenerate the shipped demo session (runtime/demo) and its true calibration"),
            ("gauge", "tensortouch.tools.recalib.twin_gauge", "play a session's force as a serial force gauge (recalibration tests)")):
        tsub.add_module(name, module, helptext)

