"""A `tensortouch` command with subcommands of its own, as the tools' `register(sub)` functions add them."""
from __future__ import annotations


def command_group(sub, name: str, help: str, dest: str, metavar: str):
    """Add command `name` to the argparse subparsers `sub` and return its own subparsers (the chosen
    one stored as `dest`, shown as `metavar`); run without a subcommand it prints its help and returns 2."""
    parser = sub.add_parser(name, help=help)
    group = parser.add_subparsers(dest=dest, metavar=metavar)
    parser.set_defaults(func=lambda a: (parser.print_help(), 2)[1])
    return group
