"""`tensortouch` console entry point.

Deploy subcommands (run, listen, ...) live here. Train-side, twin and workbench subcommands are
contributed by `tools/` through the `tensortouch.commands` entry-point group: each entry point is
a function `register(subparsers)` that adds its parsers. The runtime never imports `tools/`; it only
asks the installed package metadata which commands exist, so a deploy install without the `train`
extra still works and simply lacks those commands.
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
    problems = []
    for ep in metadata.entry_points(group=ENTRY_POINT_GROUP):
        try:
            register = ep.load()
            register(sub)
        except Exception as exc:  # a tools/ extra is not installed, or the plugin is broken
            problems.append(f"{ep.name}: unavailable ({exc}); install the train extra: pip install -e '.[train]'")
    return problems


def build_parser() -> tuple[argparse.ArgumentParser, list[str]]:
    parser = argparse.ArgumentParser(prog="tensortouch", description="TensorTouch: calibrated optical tactile sensing (runtime, train, twin, workbench).")
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    _register_deploy_commands(sub)
    problems = _register_plugins(sub)
    return parser, problems


def main(argv: list[str] | None = None) -> int:
    held = _SignalHold()           # SIGTERM/SIGINT while the subcommands are imported: remembered
    argv = list(sys.argv[1:] if argv is None else argv)
    try:
        parser, problems = build_parser()
        args = parser.parse_args(argv)
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
        return int(args.func(args) or 0)
    except TensorTouchError as exc:
        print(f"tensortouch {args.command}: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130


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
