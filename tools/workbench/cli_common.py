"""Shared pieces of the workbench's command-line shells (cli.py, effects_cli.py): the calibration
store, the effect registry, the sensor id and the model a command runs."""
from __future__ import annotations

import json
from pathlib import Path

from ..progress import count_progress


def session_args(p, session: bool = True) -> None:
    if session:
        p.add_argument("session", help="session directory (docs/session.md)")
    p.add_argument("--sensor", help="sensor id in the calibration store (default: the session's)")
    p.add_argument("--store", help="calibration store root (default: calibration_store/)")
    p.add_argument("--plugins", action="append", default=[], metavar="DIR", help="folder of effect plugins")


def store_of(args):
    from ...contracts.store import CalibrationStore

    return CalibrationStore(args.store) if args.store else CalibrationStore()


def registry_of(args):
    from ...contracts.errors import TensorTouchError
    from ...runtime.stages.effects import Registry

    try:
        return Registry.default(plugin_dirs=args.plugins)
    except ValueError as exc:
        raise TensorTouchError(str(exc)) from None


def sensor_of(args) -> str:
    """The sensor id of --sensor or of the session, checked: it names store folders and cache files."""
    from ...contracts.names import check_name

    if args.sensor:
        return check_name(args.sensor, "--sensor")
    if getattr(args, "session", None):
        return check_name(json.loads((Path(args.session) / "session.json").read_text())["sensor_id"],
                          f"{Path(args.session) / 'session.json'}: sensor_id")
    from ...contracts.errors import TensorTouchError

    raise TensorTouchError("--sensor is required")


def default_model_path(sensor: str) -> Path:
    from ...contracts.names import check_name
    from .compare import cache_root

    return cache_root() / "models" / f"{check_name(sensor, 'sensor id')}.json"


def last_diagnosis_path(sensor: str) -> Path:
    from ...contracts.names import check_name
    from .compare import cache_root

    return cache_root() / f"diagnosis-{check_name(sensor, 'sensor id')}.json"


def contact_law(args, sensor: str, store, path=None):
    from ...contracts.errors import TensorTouchError
    from .compare import load_table
    from .models import ContactLaw

    if getattr(args, "model_from", None):
        sources = [args.model_from] if isinstance(args.model_from, str) else list(args.model_from)
        cal = store.load(sensor)
        tables = [load_table(s, cal, cache=not args.no_cache)[0] for s in sources]
        law = ContactLaw.fit_sessions(tables, sources)
        law.save(default_model_path(sensor))
        print(f"nominal contact law ({', '.join(sorted(law.laws))}) fitted on {', '.join(sources)} -> "
              f"{default_model_path(sensor)}")
        return law
    path = Path(path) if path else default_model_path(sensor)
    if not path.is_file():
        raise TensorTouchError(f"{path}: no model for sensor {sensor} (no contact law fitted); fit one on a calibration "
                               "session with --model-from CALIB_SESSION (or give --model FILE)")
    return ContactLaw.load(path)


def model_of(args, sensor: str, store):
    """--model: package (path/name) -> the deployed network; 'contact-law' or a .json -> contact law;
    default: the installed package when it fits the calibration and the session has frames."""
    from ...contracts.errors import ModelPackageError
    from ...runtime.stages.model import find_package
    from .network import NetworkConfig, NetworkModel

    choice = getattr(args, "model", None)
    cfg = NetworkConfig(precision=getattr(args, "precision", "int8"))
    if choice == "contact-law" or (choice and choice.endswith(".json")) or getattr(args, "model_from", None):
        return contact_law(args, sensor, store, None if choice in (None, "contact-law") else choice)
    if choice:
        return NetworkModel(find_package(choice), cfg)
    cal = store.load(sensor)
    session = getattr(args, "session", None)
    has_frames = bool(session) and "frames" in json.loads((Path(session) / "session.json").read_text()).get("streams", {})
    try:
        package = find_package()
    except ModelPackageError as exc:
        why = str(exc).split(".")[0]
    else:
        if tuple(package.size) == tuple(cal.model_size) and (has_frames or not session):
            return NetworkModel(package, cfg)
        why = (f"calibration {sensor}/{cal.version} is for {list(cal.model_size)} px, model {package.name} for "
               f"{list(package.size)} px" if tuple(package.size) != tuple(cal.model_size) else "the session has no frames")
    print(f"note: model = the nominal contact law ({why}); use --model PATH|NAME for the network")
    return contact_law(args, sensor, store)


def progress(i: int, n: int, seconds: float) -> None:
    _network_pass(i, n)


_network_pass = count_progress("network pass", "frame")


def compare_session(args, store=None, sensor=None):
    from .compare import run_compare

    sensor = sensor or sensor_of(args)
    store = store or store_of(args)
    model = model_of(args, sensor, store)
    if getattr(args, "correction_from", None):
        from .nominal import fit_and_store_correction

        if not hasattr(model, "build_table"):
            from ...contracts.errors import TensorTouchError

            raise TensorTouchError("--correction-from needs the network model (the contact law has no correction)")
        version, text = fit_and_store_correction(args.correction_from, sensor, store, model, registry_of(args),
                                                 cache=not args.no_cache, progress=progress)
        print(text)
    return run_compare(args.session, sensor, store, model, registry_of(args), cache=not args.no_cache,
                       progress=progress)
