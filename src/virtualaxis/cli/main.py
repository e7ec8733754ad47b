"""Entry point of the ``virtualaxis`` command.

Commands are modules in this package; each defines ``register(subparsers)`` adding one sub-parser
whose ``func(args) -> int`` runs it. Expected user errors (``ConfigError``, ``InputError``,
``CliError``) are printed as one ``error: ...`` line with exit status 2, never as a traceback.
"""

from __future__ import annotations

import argparse
import importlib
import sys

from virtualaxis.cli.errors import CliError
from virtualaxis.config.errors import ConfigError, InputError

# module names in virtualaxis.cli; a command whose optional dependency is missing is skipped
COMMANDS = (
    "simulate",
    "modal",
    "frf",
    "study",
    "rcsa",
    "identify_joints",
    "serve",
    "demo",
    "diagnose",
    "gap_bench",
)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="virtualaxis",
        description="A virtual CNC ball-screw servo axis: plant, CiA 402 drive, gap diagnosis.",
    )
    from virtualaxis import __version__

    parser.add_argument("--version", action="version", version=f"virtualaxis {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMANDS:
        try:
            mod = importlib.import_module(f"virtualaxis.cli.{name}")
        except ModuleNotFoundError as exc:
            if exc.name and exc.name.startswith("virtualaxis.cli."):
                continue  # command not built yet
            raise
        mod.register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        return int(args.func(args) or 0)
    except (ConfigError, InputError, CliError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
