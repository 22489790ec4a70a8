"""A `tensortouch` command with subcommands of its own, as the tools' `register(sub)` functions add them,
and its subcommands declared as a table."""
from __future__ import annotations


def command_group(sub, name: str, help: str, dest: str, metavar: str):
    """Add command `name` to the argparse subparsers `sub` and return its own subparsers (the chosen
    one stored as `dest`, shown as `metavar`); run without a subcommand it prints its help and returns 2."""
    parser = sub.add_parser(name, help=help)
    group = parser.add_subparsers(dest=dest, metavar=metavar)
    parser.set_defaults(func=lambda a: (parser.print_help(), 2)[1])
    return group


def arg(*flags: str, **options) -> tuple[tuple[str, ...], dict]:
    """One option of a subcommand: what argparse's `add_argument` takes."""
    return flags, options


def add_commands(group, commands) -> None:
    """Add to the subparsers `group` one subcommand per row `(name, help, handler, options)` of
    `commands`; `options` are `arg(...)` in the order the help lists them."""
    for name, help, handler, options in commands:
        parser = group.add_parser(name, help=help)
        for flags, kw in options:
            parser.add_argument(*flags, **kw)
        parser.set_defaults(func=handler)
