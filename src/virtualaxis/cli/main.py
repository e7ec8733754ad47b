"""Entry point of the ``virtualaxis`` command.

Commands are modules in this package; each defines ``register(subparsers)`` adding one sub-parser
whose ``func(args) -> int`` runs it. Expected user errors (``ConfigError``, ``InputError``,
``CliError``) are printed as one ``error: ...`` line with exit status 2, never as a traceback.

Last resort: any other exception is printed as one ``internal error: ...`` line with exit status 1 (the
traceback only with ``--debug`` or ``VIRTUALAXIS_DEBUG=1``); such a line is a bug to report, each user
mistake has its own check. SIGTERM, SIGHUP and the other terminating signals Python can catch are handled like
SIGINT (``KeyboardInterrupt``), so that outputs being written are removed instead of left truncated; the exit
status is 130 (SIGINT) or 128 + the signal's number (143 for SIGTERM, 129 for SIGHUP); an interrupt that arrives
while a finalizer runs (which the interpreter drops) is raised again once the finalizer has returned. An OS error
that reaches this level (no space left, no permission, a name too long) is one ``error:`` line naming the file,
exit 2.
"""

from __future__ import annotations

import _thread
import argparse
import importlib
import os
import signal
import sys
import threading
import time
import traceback

from virtualaxis.cli.errors import CliError, StdoutError
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
    "health",
    "fmu",
)


class _Parser(argparse.ArgumentParser):
    """argparse with the CLI's error contract: a wrong option (``--points abc``, a missing ``--out``, an unknown
    choice) is ONE line ``error: <command>: <what argparse says>`` and exit status 2, not a usage block followed
    by a differently prefixed line. Sub-parsers inherit the class."""

    #: the commands' parsers by name (set on the top-level parser by :func:`build_parser`)
    command_parsers: dict[str, argparse.ArgumentParser] = {}

    def error(self, message: str):  # noqa: D401 - argparse's hook
        hint = f" (see {self.prog} --help)"
        self.exit(2, f"error: {self.prog}: {' '.join(message.split())}{hint}\n")

    def parse_args(self, args=None, namespace=None):
        """An argument no parser knows is the command's error (its prog and help), not the top level's."""
        ns, extras = self.parse_known_args(args, namespace)
        if extras:
            owner = self.command_parsers.get(getattr(ns, "command", None) or "", self)
            owner.error(f"unrecognized arguments: {' '.join(extras)}")
        return ns


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
    parser.command_parsers = dict(sub.choices)
    return parser


class _Terminated(KeyboardInterrupt):
    """A terminating signal (SIGTERM, SIGHUP, ...), raised like SIGINT so that the same clean-up runs."""

    def __init__(self, signum: int):
        super().__init__(signum)
        self.signum = signum


def _on_terminate(signum, frame) -> None:
    raise _Terminated(signum)


#: an interrupt dropped in a finalizer is raised again this long after [s]
RAISE_AGAIN_AFTER_S = 0.02


def _interrupt_main_soon(signum: int) -> None:
    time.sleep(RAISE_AGAIN_AFTER_S)
    _thread.interrupt_main(signum)


def _raise_dropped_again(previous_hook):
    """A ``sys.unraisablehook`` that raises an interrupt again when the interpreter dropped it: an exception raised
    in a finalizer (``__del__``) is only reported, so a Ctrl-C or SIGTERM that arrives while one runs (``canopen``
    sends an SDO request and waits for its answer when it collects an aborted transfer's stream) would be lost
    and the command would run on to the end. ``_thread.interrupt_main``, from a thread of its own, has the main
    thread call the signal's handler again once the finalizer has returned (dropped again: again). Other
    unraisable exceptions go to ``previous_hook``."""

    def hook(unraisable) -> None:
        exc = unraisable.exc_value
        if isinstance(exc, KeyboardInterrupt) and threading.current_thread() is threading.main_thread():
            # (from another thread, a moment later: in this one the handler would run, and raise, inside this hook)
            _thread.start_new_thread(_interrupt_main_soon, (getattr(exc, "signum", signal.SIGINT),))
            return
        previous_hook(unraisable)

    return hook


#: signals whose default action ends the process and which Python can catch: each ends a command like SIGINT
#: (incomplete outputs removed, exit status 128 + the signal's number). A signal the caller set to "ignore"
#: (``nohup`` ignores SIGHUP) or handles itself stays so. SIGPIPE and SIGXFSZ are ignored by Python itself (a write then
#: fails with an OS error, which is reported).
TERMINATING_SIGNALS = tuple(
    getattr(signal, name) for name in ("SIGTERM", "SIGHUP", "SIGQUIT", "SIGUSR1", "SIGUSR2", "SIGALRM", "SIGXCPU",
                                       "SIGVTALRM", "SIGPROF", "SIGPWR", "SIGIO", "SIGSTKFLT")
    if hasattr(signal, name))


def _install_signal_handlers() -> dict[int, object]:
    """Terminating signals raise :class:`_Terminated`; returns the previous handlers."""
    old: dict[int, object] = {}
    for sig in TERMINATING_SIGNALS:
        if signal.getsignal(sig) != signal.SIG_DFL:  # ignored (nohup) or handled by the caller: left alone
            continue
        old[sig] = signal.signal(sig, _on_terminate)
    return old


def _default_signals() -> None:
    """After an interrupt has been handled: a second Ctrl-C (or signal) ends the process at once instead of
    interrupting the clean-up or waiting for anything."""
    if threading.current_thread() is not threading.main_thread():
        return
    for sig in (signal.SIGINT, *TERMINATING_SIGNALS):
        if signal.getsignal(sig) not in (signal.SIG_IGN, None):
            signal.signal(sig, signal.SIG_DFL)


def _os_error_line(exc: OSError) -> str:
    """An OS error about a file or stream, as one line naming it: ``<path>: <what the system says>``."""
    names = [_short(os.fsdecode(n)) for n in (exc.filename, exc.filename2) if isinstance(n, (str, bytes))]
    what = exc.strerror or " ".join(str(exc).split()) or type(exc).__name__
    return f"{' -> '.join(names)}: {what}" if names else what


def _short(path: str, keep: int = 120) -> str:
    """A path for an error line: at most ``keep`` characters (a 4096-character name is cut in the middle)."""
    return path if len(path) <= keep else f"{path[:keep // 2]}...{path[-keep // 2:]}"


class _GuardedStdout:
    """``sys.stdout`` while a command runs: a failed write or flush becomes :class:`StdoutError` naming
    standard output (an ``OSError`` from print() names no file). A broken pipe (``| head``) stays as it is."""

    def __init__(self, stream):
        self._stream = stream

    def _guard(self, fn, *args):
        try:
            return fn(*args)
        except BrokenPipeError:
            raise
        except OSError as exc:
            raise StdoutError(exc.errno, exc.strerror or str(exc)) from None

    def write(self, text: str) -> int:
        return self._guard(self._stream.write, text)

    def flush(self) -> None:
        self._guard(self._stream.flush)

    def __getattr__(self, name: str):
        return getattr(self._stream, name)


def _discard_stdout() -> None:
    """After standard output failed: send what is still buffered to /dev/null, so that the interpreter's own
    flush at exit does not fail again (a Python warning and status 120)."""
    try:
        fd = sys.__stdout__.fileno() if sys.__stdout__ is not None else 1
        null = os.open(os.devnull, os.O_WRONLY)
        os.dup2(null, fd)
        os.close(null)
    except (OSError, ValueError):
        pass


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
    old_handlers: dict[int, object] = {}
    old_unraisable = sys.unraisablehook
    if threading.current_thread() is threading.main_thread():
        old_handlers = _install_signal_handlers()
        sys.unraisablehook = _raise_dropped_again(old_unraisable)
    from virtualaxis.cli.outputs import reset_claims

    reset_claims()
    real_stdout = sys.stdout
    sys.stdout = _GuardedStdout(real_stdout)
    try:
        status = int(args.func(args) or 0)
        sys.stdout.flush()  # now, not at exit (where a failure is only a warning)
        return status
    except (ConfigError, InputError, CliError) as exc:
        print(f"error: {_one_line(exc)}", file=sys.stderr)
        return 2
    except _Terminated as exc:
        if argv is None:  # (the process's own command line: it ends now; a caller of main([...]) keeps its handlers)
            _default_signals()
        print(f"terminated ({signal.Signals(exc.signum).name}); incomplete outputs removed", file=sys.stderr)
        return 128 + exc.signum
    except KeyboardInterrupt:
        if argv is None:
            _default_signals()
        print("interrupted; incomplete outputs removed", file=sys.stderr)
        return 130
    except MemoryError:
        print(f"error: out of memory in '{args.command}' (an input or option asks for more than this machine "
              "has; see docs/bad-input.md)", file=sys.stderr)
        return 1
    except BrokenPipeError:
        return 1
    except RecursionError:  # a file nested deeper than any reader recurses (TOML, JSON): input, not a bug
        print(f"error: '{args.command}': an input is nested too deeply to read (tables or arrays inside each "
              "other thousands of levels deep)", file=sys.stderr)
        return 2
    except StdoutError as exc:
        if argv is None:
            _discard_stdout()
        print(f"error: standard output: cannot write ({exc.strerror})", file=sys.stderr)
        return 2
    except OSError as exc:  # a file system refused (no space, no permission, a name too long, ...)
        print(f"error: {_os_error_line(exc)}", file=sys.stderr)
        return 2
    except Exception as exc:  # the last resort; every expected mistake has its own check
        if debug:
            traceback.print_exc()
        where = traceback.extract_tb(exc.__traceback__)[-1] if exc.__traceback__ else None
        loc = f" at {os.path.basename(where.filename)}:{where.lineno}" if where else ""
        print(f"internal error in '{args.command}': {type(exc).__name__}: {_one_line(exc)}{loc} (a bug; rerun "
              "with --debug for the traceback)", file=sys.stderr)
        return 1
    finally:
        if isinstance(sys.stdout, _GuardedStdout):
            sys.stdout = real_stdout
        if threading.current_thread() is threading.main_thread():
            for sig, handler in old_handlers.items():
                signal.signal(sig, handler)
            sys.unraisablehook = old_unraisable


def _one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split()) or type(exc).__name__


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
