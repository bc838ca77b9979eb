"""The `crowdbake` command line.

Each subcommand lives in its own module in this package and exposes
`register(subparsers)`, which adds its parser and sets `func` to a handler
taking the parsed namespace and returning an exit code. Modules are found by
name, so adding a command never edits this file.
"""
from __future__ import annotations

import argparse
import importlib
import logging
import pkgutil
import sys

from crowdbake import __version__
from crowdbake.cli.common import CommandError


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="crowdbake",
        description="Bake clothed characters into crowd bundles (cycle search, poses, LODs, UV-mapped impostors).",
    )
    parser.add_argument("--version", action="version", version=f"crowdbake {__version__}")
    parser.add_argument("-v", "--verbose", action="store_true", help="log debug messages to stderr")
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND")
    for module_info in sorted(pkgutil.iter_modules(__path__), key=lambda m: m.name):
        if module_info.name.startswith("_") or module_info.name == "common":
            continue
        module = importlib.import_module(f"{__name__}.{module_info.name}")
        module.register(subparsers)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.WARNING,
        format="%(levelname)s %(name)s: %(message)s",
    )
    if not getattr(args, "func", None):
        parser.print_help(sys.stderr)
        return 2
    try:
        return int(args.func(args) or 0)
    except CommandError as error:
        # One line and a non-zero exit: what CI pipelines and people read first.
        print(f"crowdbake {args.command}: error: {error}", file=sys.stderr)
        return error.exit_code
    except KeyboardInterrupt:
        print(f"crowdbake {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
