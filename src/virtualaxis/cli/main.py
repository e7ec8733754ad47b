"""Entry point of the ``virtualaxis`` command.

Commands are modules in this package; each defines ``register(subparsers)`` adding one sub-parser
whose ``func(args) -> int`` runs it. Expected user errors (``ConfigError``, ``InputError``,
``CliError``) are printed as one ``error: ...`` line with exit status 2, never as a traceback.

Last resort: any other exception is printed as one ``internal error: ...`` line with exit status 1 (the
traceback only with ``--debug`` or ``VIRTUALAXIS_DEBUG=1``); such a line is a bug to report, each user
mistake has its own check. SIGTERM is handled like SIGINT (``KeyboardInterrupt``), so that outputs being
written are removed instead of left truncated; the exit status is 130 (SIGINT) or 143 (SIGTERM).
"""

from __future__ import annotations

import argparse
import importlib
import os
import signal
import sys
import threading
import traceback

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
    "fault",
    "conformance",
    "fmu",
)


class _Parser(argparse.ArgumentParser):
    """argparse with the CLI's error contract: a wrong option (``--points abc``, a missing ``--out``, an unknown
    choice) is ONE line ``error: <command>: <what argparse says>`` and exit status 2, not a usage block followed
    by a differently prefixed line. Sub-parsers inherit the class."""

    def error(self, message: str):  # noqa: D401 - argparse's hook
        hint = f" (see {self.prog} --help)"
        self.exit(2, f"error: {self.prog}: {' '.join(message.split())}{hint}\n")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="virtualaxis",
        description="A virtual CNC ball-screw servo axis: plant, CiA 402 drive, gap diagnosis.",
    )
    from virtualaxis import __version__

    parser.add_argument("--version", action="version", version=f"virtualaxis {__version__}")
    parser.add_argument("--debug", action="store_true",
                        help="show the traceback of an internal error (also: VIRTUALAXIS_DEBUG=1)")
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


class _Terminated(KeyboardInterrupt):
    """SIGTERM, raised like SIGINT so that the same clean-up runs."""


def _on_sigterm(signum, frame) -> None:
    raise _Terminated()


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # --help, --version (0) or an option error (2, one line printed by _Parser)
        return exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 2)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    debug = bool(getattr(args, "debug", False)) or os.environ.get("VIRTUALAXIS_DEBUG", "") not in ("", "0")
    old_term = None
    if threading.current_thread() is threading.main_thread():
        old_term = signal.signal(signal.SIGTERM, _on_sigterm)
    from virtualaxis.cli.outputs import reset_claims

    reset_claims()
    try:
        return int(args.func(args) or 0)
    except (ConfigError, InputError, CliError) as exc:
        print(f"error: {_one_line(exc)}", file=sys.stderr)
        return 2
    except _Terminated:
        print("terminated (SIGTERM); incomplete outputs removed", file=sys.stderr)
        return 143
    except KeyboardInterrupt:
        print("interrupted; incomplete outputs removed", file=sys.stderr)
        return 130
    except MemoryError:
        print(f"error: out of memory in '{args.command}' (an input or option asks for more than this machine "
              "has; see docs/bad-input.md)", file=sys.stderr)
        return 1
    except BrokenPipeError:
        return 1
    except Exception as exc:  # the last resort; every expected mistake has its own check
        if debug:
            traceback.print_exc()
        where = traceback.extract_tb(exc.__traceback__)[-1] if exc.__traceback__ else None
        loc = f" at {os.path.basename(where.filename)}:{where.lineno}" if where else ""
        print(f"internal error in '{args.command}': {type(exc).__name__}: {_one_line(exc)}{loc} (a bug; rerun "
              "with --debug for the traceback)", file=sys.stderr)
        return 1
    finally:
        if old_term is not None:
            signal.signal(signal.SIGTERM, old_term)


def _one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split()) or type(exc).__name__


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
