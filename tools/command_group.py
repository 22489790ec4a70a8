"""A `tensortouch` command with subcommands of its own, as the tools' `register(sub)` functions add them,
and its subcommands declared as a table."""
from __future__ import annotations

import argparse
import importlib


def command_group(sub, name: str, help: str, dest: str, metavar: str, extra: str | None = None):
    """Add command `name` to the argparse subparsers `sub` and return its own subparsers (the chosen
    one stored as `dest`, shown as `metavar`; a LazySubcommands, so `add_module` works on it); run
    without a subcommand it prints its help and returns 2. `extra`: the optional extra its
    subcommands need (the `tensortouch` shell checks it before one runs)."""
    parser = sub.add_parser(name, help=help, description=help)
    group = parser.add_subparsers(dest=dest, metavar=metavar, action=LazySubcommands)
    parser.set_defaults(func=lambda a: (parser.print_help(), 2)[1])
    if extra:
        parser.set_defaults(extra=extra)
    return group


def arg(*flags: str, **options) -> tuple[tuple[str, ...], dict]:
    """One option of a subcommand: what argparse's `add_argument` takes."""
    return flags, options


def add_commands(group, commands) -> None:
    """Add to the subparsers `group` one subcommand per row `(name, help, handler, options)` of
    `commands`; `options` are `arg(...)` in the order the help lists them."""
    for name, help, handler, options in commands:
        parser = group.add_parser(name, help=help, description=help)
        for flags, kw in options:
            parser.add_argument(*flags, **kw)
        parser.set_defaults(func=handler)


class LazySubcommands(argparse._SubParsersAction):
    """Subparsers whose options are added only when that subcommand is chosen: listing them (`--help`)
    imports nothing; choosing one imports its module (and the extra's packages it needs) then."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self._pending: dict[str, tuple[argparse.ArgumentParser, str, str, str]] = {}

    def add_module(self, name: str, module: str, help: str, extra: str | None = None,
                   add: str = "add_arguments", run: str = "run") -> argparse.ArgumentParser:
        """Subcommand `name` from `module`, which exposes `add_arguments(parser)` and `run(args) -> int`
        (other names: `add`, `run`); `extra`: the optional extra it needs (checked before it runs)."""
        parser = self.add_parser(name, help=help, description=help)
        if extra:
            parser.set_defaults(extra=extra)
        self._pending[name] = (parser, module, add, run)
        return parser

    def load(self, name: str) -> None:
        pending = self._pending.pop(name, None)
        if pending is None:
            return
        parser, module, add, run = pending
        mod = importlib.import_module(module)
        if not (callable(getattr(mod, add, None)) and callable(getattr(mod, run, None))):
            raise TypeError(f"subcommand {name!r}: {module} must define {add}(parser) and {run}(args)")
        getattr(mod, add)(parser)
        parser.set_defaults(func=getattr(mod, run))

    def __call__(self, parser, namespace, values, option_string=None):
        if values and values[0] in self._pending:
            extra = self._pending[values[0]][0].get_default("extra") or getattr(namespace, "extra", None)
            if extra:               # say which extra is missing before importing a module that needs it
                from ..contracts.extras import require

                require(extra)
            self.load(values[0])
        super().__call__(parser, namespace, values, option_string)


def lazy_group(parser: argparse.ArgumentParser, dest: str, metavar: str, rows) -> LazySubcommands:
    """Subparsers under `parser` with one subcommand per row `(name, module, help[, extra])` (LazySubcommands)."""
    group = parser.add_subparsers(dest=dest, metavar=metavar, required=True, action=LazySubcommands)
    for name, module, help, *extra in rows:
        group.add_module(name, module, help, *extra)
    return group
