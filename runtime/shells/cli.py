"""`tensortouch` console entry point.

Deploy subcommands (run, listen, ...) live here. Train-side, twin and workbench subcommands are
contributed by `tools/` through the `tensortouch.commands` entry-point group: each entry point is
a function `register(subparsers)` that adds its parsers. The runtime never imports `tools/`; it only
asks the installed package metadata which commands exist. Registering a command imports only what
its parser needs (no torch, scipy, zenoh, onnxruntime: `tensortouch --help` starts in well under a
second); a command declares the optional extra it needs (`set_defaults(extra="train")`), and run
without it prints one line naming the extra and how to install it (contracts/extras.py), exit 2.

Exit codes: 0 done; 1 the command ran but found nothing (`find` with no camera, `listen` with no
message); 2 bad input, a missing file or a missing extra (one line, no traceback); 130 interrupted
(Ctrl-C; a command that resumes says how).
"""
from __future__ import annotations

import argparse
import logging
import shlex
import sys
from importlib import metadata

from ...contracts.errors import TensorTouchError

log = logging.getLogger(__name__)

ENTRY_POINT_GROUP = "tensortouch.commands"


def _register_deploy_commands(sub) -> None:
    from . import commands

    commands.register(sub)


def _register_plugins(sub) -> list[str]:
    from ...contracts.extras import hint_for_import_error

    problems = []
    for ep in metadata.entry_points(group=ENTRY_POINT_GROUP):
        try:
            register = ep.load()
            register(sub)
        except ModuleNotFoundError as exc:  # a tools/ module imports an extra's package at registration
            problems.append(f"{ep.name} commands: " + (hint_for_import_error(exc) or f"unavailable ({exc})"))
        except Exception as exc:  # noqa: BLE001 - a broken plugin must not take the other commands down
            problems.append(f"{ep.name} commands: unavailable ({type(exc).__name__}: {exc})")
    return problems


def _missing_extra_line(exc: ModuleNotFoundError, args, command: str) -> str | None:
    """The one line for a module some extra provides (None: not an extra's module, a real bug)."""
    from ...contracts.extras import hint_for_import_error

    line = hint_for_import_error(exc, prefer=getattr(args, "extra", None))
    return f"tensortouch {command}: {line}" if line else None


def build_parser() -> tuple[argparse.ArgumentParser, list[str]]:
    parser = argparse.ArgumentParser(prog="tensortouch", description="TensorTouch: calibrated optical tactile sensing (runtime, train, twin, workbench).")
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    _register_deploy_commands(sub)
    problems = _register_plugins(sub)
    describe_commands(parser)
    return parser, problems


def subcommands(parser: argparse.ArgumentParser):
    """(name, parser, help) of each subcommand directly under `parser`."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            helps = {a.dest: a.help for a in action._choices_actions}
            for name, child in action.choices.items():
                yield name, child, helps.get(name)


def describe_commands(parser: argparse.ArgumentParser) -> None:
    """Every command's `--help` opens with a description: its one-line help where it has no longer one."""
    for _, child, text in subcommands(parser):
        if not child.description and text:
            text = text.replace("%%", "%")
            child.description = text[0].upper() + text[1:] + ("" if text.endswith(".") else ".")
        describe_commands(child)


def main(argv: list[str] | None = None) -> int:
    held = _SignalHold()           # SIGTERM/SIGINT while the subcommands are imported: remembered
    argv = list(sys.argv[1:] if argv is None else argv)
    try:
        parser, problems = build_parser()
        first = next((a for a in argv if not a.startswith("-")), None)
        if problems and first is not None and first not in _commands(parser):
            for line in problems:                 # an unknown command may be one a missing extra adds
                print("tensortouch:", line, file=sys.stderr)
        try:
            args = parser.parse_args(argv)
        except ModuleNotFoundError as exc:        # a subcommand's options live in a module of an extra
            line = _missing_extra_line(exc, None, first or "")
            if line is None:
                raise
            print(line, file=sys.stderr)
            return 2
        except TensorTouchError as exc:           # its extra is missing (checked before its module loads)
            print(f"tensortouch {first}: {exc}", file=sys.stderr)
            return 2
    finally:
        pending = held.release()
    args.command_line = shlex.join(["tensortouch", *argv])    # what a manifest records as "the command"
    if pending:
        if getattr(args, "handles_stop_signals", False):
            args.pending_signals = pending   # the command stops cleanly at once (tensortouch hand)
        else:
            return held.redeliver(pending[0])
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO,
                        format="%(levelname)s %(name)s: %(message)s")
    if not getattr(args, "func", None):
        parser.print_help()
        for line in problems:
            print("note:", line, file=sys.stderr)
        return 0 if args.command is None else 2
    code = dispatch(args)
    if getattr(args, "exit_without_finalizing", False):
        _exit_now(code)
    return code


def dispatch(args) -> int:
    """Run a parsed command: its exit code, or 2 with one line on stderr for a TensorTouchError (bad
    input), 130 on Ctrl-C. `main` calls it; tests call it with `build_parser()`'s parser built once."""
    try:
        if getattr(args, "extra", None):
            from ...contracts.extras import require

            require(args.extra)
        return int(args.func(args) or 0)
    except TensorTouchError as exc:
        print(f"tensortouch {args.command}: {exc}", file=sys.stderr)
        return 2
    except (FileNotFoundError, NotADirectoryError, IsADirectoryError, PermissionError) as exc:
        if not exc.filename:                  # not about a path the command was given: a real bug
            raise
        print(f"tensortouch {args.command}: {exc.filename}: {exc.strerror or exc}", file=sys.stderr)
        return 2
    except ModuleNotFoundError as exc:
        line = _missing_extra_line(exc, args, args.command)
        if line is None:
            raise
        print(line, file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return _interrupted(args)
    except SystemError as exc:
        # Ctrl-C inside compiled code (a numba kernel) comes back as a SystemError whose context is the interrupt
        if not _caused_by_interrupt(exc):
            raise
        return _interrupted(args)


def _interrupted(args: argparse.Namespace) -> int:
    hint = getattr(args, "resume_hint", None)       # set by commands that pick up where they stopped
    print(f"tensortouch {args.command}: interrupted"
          + (f"; rerun `{getattr(args, 'command_line', args.command)}` to resume ({hint})" if hint else ""), file=sys.stderr)
    return 130


def _caused_by_interrupt(exc: BaseException) -> bool:
    """True when a KeyboardInterrupt is in `exc`'s chain of causes and contexts."""
    seen: set[int] = set()
    while exc is not None and id(exc) not in seen:
        if isinstance(exc, KeyboardInterrupt):
            return True
        seen.add(id(exc))
        exc = exc.__cause__ or exc.__context__
    return False


def _commands(parser: argparse.ArgumentParser) -> set[str]:
    """The names the top-level parser takes as COMMAND."""
    return {name for name, _, _ in subcommands(parser)}


class _SignalHold:
    """Holds SIGTERM and SIGINT during start-up; `release()` restores the handlers and returns what came."""

    SIGNALS = ("SIGTERM", "SIGINT")

    def __init__(self):
        import signal

        self.pending: list[int] = []
        self.previous = {}
        try:
            for name in self.SIGNALS:
                sig = getattr(signal, name)
                self.previous[sig] = signal.signal(sig, lambda n, frame: self.pending.append(n))
        except ValueError:          # not the main thread (an embedding caller): leave signals alone
            self.previous = {}

    def release(self) -> list[int]:
        import signal

        for sig, handler in self.previous.items():
            signal.signal(sig, handler)
        return list(self.pending)

    @staticmethod
    def redeliver(sig: int) -> int:
        """What the signal would have done without the hold: SIGINT → exit 130, others → raised again."""
        import signal

        if sig == signal.SIGINT:
            return 130
        signal.raise_signal(sig)
        return 128 + sig


def _exit_now(code: int) -> None:
    """End the process without interpreter finalization, for commands that already closed everything
    they opened (sessions, devices, files) but whose native libraries may still run threads that call
    back into Python: during finalization such a call aborts the process ("FATAL: exception not
    rethrown", rc 134) instead of exiting with `code`."""
    import os

    logging.shutdown()
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):
            pass
    os._exit(code)


if __name__ == "__main__":
    sys.exit(main())
