"""A service's server in its own child process, joined to serve by a socket pair.

The OPC UA server and the live page's HTTP server run in a plain child interpreter (``python -c``, not
multiprocessing's spawn, which would re-run the caller's ``__main__``) so that their clients never take the
drive's runtime thread's interpreter. The two ends:

- serve's end, :class:`ChildProcess`: starts the child, sends it the start-up message and waits for its
  ``("ready", value)``; a bridge thread hands each message of the child to the service's handler and sends the
  handler's reply back; :meth:`ChildProcess.stop` asks the child to stop, then kills it after a timeout. If the
  child ends on its own, serve prints one warning line and goes on serving CANopen (``status``).
- the child's end, :class:`ParentLink`: the inherited socket, a send that several threads may call, and the
  child's set-up (:func:`enter_child`): Ctrl-C is serve's to handle (it stops the child). The child runs below
  the drive (``threads.CHILD_PROLOGUE``: nice 10, never the drive's real-time priority). The child ends on the
  socket's EOF, i.e. with serve even if serve is killed.

Messages are tuples whose first item names their kind; ``("stop",)`` and ``("error", text)`` are the link's own.
"""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

from virtualaxis.services.threads import CHILD_PROLOGUE

__all__ = ["ChildProcess", "ParentLink", "enter_child"]

_SRC = str(Path(__file__).resolve().parents[2])  # the virtualaxis package this process runs
#: a child that is not ready after its start timeout still gets this long [s] at a time while it computes ...
START_PROGRESS_S = 10.0
#: ... up to this many times its start timeout in all
START_MAX_FACTOR = 5.0


class ChildProcess:
    """serve's end of a service's server process.

    ``option`` is the command-line option that asked for the service (``"--opcua 127.0.0.1:4840"``), ``what`` the
    server's name in messages (``"the OPC UA server"``), ``without`` what serving goes on without when the child
    ends on its own (``"OPC UA"``)."""

    def __init__(self, option: str, what: str, without: str):
        self.option = option
        self.what = what
        self.without = without
        self.status = "not started"  # running, stopped, failed (why), or ended (exit code N)
        self._proc: subprocess.Popen | None = None
        self._conn: Connection | None = None
        self._send_lock = threading.Lock()
        self._stopping = threading.Event()
        self._gone = threading.Event()  # the child ended (or was stopped)
        self._bridge: threading.Thread | None = None

    @property
    def pid(self) -> int | None:
        return self._proc.pid if self._proc is not None else None

    @property
    def gone(self) -> bool:
        return self._gone.is_set()

    def start(self, entry: str, init: tuple, timeout_s: float, pass_fds: tuple[int, ...] = ()) -> Any:
        """Start ``entry`` (``"package.module:function"``, called as ``function(link_fd, *pass_fds)`` in the
        child), send it ``init`` and return the value of its ``("ready", value)``. The descriptors in
        ``pass_fds`` are the child's afterwards (closed here). OSError naming :attr:`option` if the child does
        not get ready."""
        module, function = entry.split(":")
        ours, theirs = socket.socketpair()
        env = dict(os.environ, PYTHONPATH=os.pathsep.join([_SRC, *filter(None, [os.environ.get("PYTHONPATH")])]))
        code = f"import sys; {CHILD_PROLOGUE}from {module} import {function}; {function}(*map(int, sys.argv[1:]))"
        try:
            self._proc = subprocess.Popen([sys.executable, "-c", code, str(theirs.fileno()), *map(str, pass_fds)],
                                          pass_fds=(theirs.fileno(), *pass_fds), env=env)
        finally:
            theirs.close()
            for fd in pass_fds:
                os.close(fd)
        self._conn = Connection(ours.detach())
        try:
            self._conn.send(init)
            self._wait_ready(timeout_s)
            kind, value = self._conn.recv()
        except (EOFError, OSError) as exc:
            self.stop()
            if isinstance(exc, OSError) and str(exc).startswith(self.option):
                raise
            raise OSError(f"{self.option}: {self.what} process ended while starting") from None
        if kind != "ready":
            self.stop()
            raise OSError(f"{self.option}: {value}")
        self.status = "running"
        return value

    def _wait_ready(self, timeout_s: float) -> None:
        """Wait for the child's first message: ``timeout_s``, and beyond it for as long as the child keeps
        computing (its CPU time grew in the last :data:`START_PROGRESS_S`, or half the timeout if shorter: a host
        busy with other work starves a child that runs below the drive, and its imports then take minutes), at
        most :data:`START_MAX_FACTOR` times ``timeout_s``. OSError naming :attr:`option` when it is not there by
        then; EOFError when the child ended."""
        t0 = time.monotonic()
        deadline, hard = t0 + timeout_s, t0 + START_MAX_FACTOR * timeout_s
        window = min(START_PROGRESS_S, timeout_s / 2)
        samples: list[tuple[float, float]] = []  # (time, the child's CPU time), one per second
        while not self._conn.poll(min(1.0, max(0.0, deadline - time.monotonic()), window / 2)):
            if self._proc.poll() is not None:
                raise EOFError
            now = time.monotonic()
            cpu = self._child_cpu_s()
            if cpu is not None:
                samples.append((now, cpu))
            if now < deadline:
                continue
            before = [c for t, c in samples if t <= now - window]
            if cpu is not None and before and cpu > before[-1] and now < hard:
                deadline = min(hard, now + window)  # (still working: starved, not stuck)
                continue
            raise OSError(f"{self.option}: {self.what} did not start in {now - t0:.0f} s")

    def _child_cpu_s(self) -> float | None:
        """The child's user + system CPU time [s] (Linux ``/proc``; None elsewhere)."""
        try:
            fields = Path(f"/proc/{self._proc.pid}/stat").read_text().rsplit(")", 1)[1].split()
            return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
        except (OSError, ValueError, IndexError, AttributeError):
            return None

    def serve(self, handle: Callable[[tuple], tuple | None], name: str) -> None:
        """Start the bridge thread: each message of the child but ``("error", text)`` goes to ``handle``, whose
        return value (if not None) is sent back."""
        self._bridge = threading.Thread(target=self._serve, args=(handle,), name=name, daemon=True)
        self._bridge.start()

    def send(self, msg: tuple) -> bool:
        """Send ``msg`` to the child (from any thread); False if the child is gone."""
        conn = self._conn
        if conn is None or self._gone.is_set():
            return False
        try:
            with self._send_lock:
                conn.send(msg)
        except (EOFError, OSError, ValueError):
            return False
        return True

    def stop(self, timeout_s: float = 5.0) -> None:
        """Ask the child to stop; kill it if it has not ended after ``timeout_s``."""
        self._stopping.set()
        if self._proc is not None:
            self.send(("stop",))
            try:
                self._proc.wait(timeout=timeout_s)
            except subprocess.TimeoutExpired:
                self._proc.kill()
                self._proc.wait(timeout=timeout_s)
            if self.status == "running":
                self.status = "stopped"
        if self._bridge is not None:
            self._bridge.join(timeout_s)
        if self._conn is not None:
            self._conn.close()
            self._conn = None

    def _serve(self, handle: Callable[[tuple], tuple | None]) -> None:
        conn = self._conn
        while True:
            try:
                msg = conn.recv()
            except (EOFError, OSError):
                break
            if msg[0] == "error":
                self.status = f"failed ({msg[1]})"
                continue
            reply = handle(msg)
            if reply is not None:
                self.send(reply)
        self._gone.set()
        if self._stopping.is_set():
            return
        # the child ended on its own: say so once, keep serving CANopen
        try:
            code = self._proc.wait(timeout=2.0)
        except subprocess.TimeoutExpired:
            code = None
        why = self.status[len("failed "):] if self.status.startswith("failed") else ""
        self.status = f"ended (exit code {code})"
        print(f"warning: {self.option.split()[0]}: {self.what} process ended (exit code {code})"
              f"{' ' + why if why else ''}; serving CANopen goes on without {self.without}",
              file=sys.stderr, flush=True)


class ParentLink:
    """The child's end of the socket pair to serve: :meth:`send` may be called from any thread and never raises
    (serve gone: the message is dropped; the reading thread sees the EOF)."""

    def __init__(self, fd: int):
        self.conn = Connection(fd)
        self._send_lock = threading.Lock()

    def recv(self) -> tuple:
        return self.conn.recv()

    def send(self, msg: tuple) -> None:
        try:
            with self._send_lock:
                self.conn.send(msg)
        except (EOFError, OSError, ValueError):
            pass


def enter_child(fd: int) -> tuple[ParentLink, tuple] | None:
    """The set-up of a service's child process (which :meth:`ChildProcess.start` started below the drive:
    ``CHILD_PROLOGUE``): Ctrl-C is left to serve (which stops this process); returns the link and serve's start-up
    message, or None if serve is already gone."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    link = ParentLink(fd)
    try:
        init = link.recv()
    except (EOFError, OSError):
        return None
    return link, init
