"""`virtualaxis serve` in a child process on a private udp_multicast group (hop_limit 0, loopback only), for
tests that need a drive served the way a user serves it: a master in this process, the drive in another."""

from __future__ import annotations

import contextlib
import os
import random
import subprocess
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass, field

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
# (not `python -m virtualaxis.cli.main`: that imports cli.main twice and its CliError would not be caught)
CLI = [sys.executable, "-c", "import sys; from virtualaxis.cli.main import main; sys.exit(main())"]


@dataclass
class Served:
    """A running `serve` process and the bus string a master opens to reach it."""

    proc: subprocess.Popen
    spec: str  # udp_multicast:GROUP,port=PORT
    group: str
    port: int
    ready_line: str
    stdout: str = ""
    stderr: str = ""
    returncode: int | None = None
    extra: dict = field(default_factory=dict)

    def bus_kwargs(self) -> dict:
        """Keyword arguments of ``can.Bus`` / ``canopen.Network.connect`` for this group."""
        return {"interface": "udp_multicast", "channel": self.group, "port": self.port, "hop_limit": 0}

    def stop(self, timeout_s: float = 20.0) -> int:
        """SIGTERM, wait, collect the output; returns the exit code."""
        if self.returncode is None:
            self.proc.terminate()
            try:
                out, err = self.proc.communicate(timeout=timeout_s)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                out, err = self.proc.communicate()
            self.stdout += out or ""
            self.stderr += err or ""
            self.returncode = self.proc.returncode
        return self.returncode


def private_group() -> tuple[str, int]:
    """A multicast group and port of its own for one test (tests of several developers run at once)."""
    rng = random.Random(os.getpid() * 7919 + time.perf_counter_ns())
    return f"239.74.{rng.randint(100, 250)}.{rng.randint(1, 250)}", rng.randint(46000, 49000)


@contextlib.contextmanager
def served(*serve_args: str, ready_timeout_s: float = 60.0, env: dict | None = None) -> Iterator[Served]:
    """``virtualaxis serve --can udp_multicast:... *serve_args`` until the block ends (SIGTERM)."""
    group, port = private_group()
    spec = f"udp_multicast:{group},port={port}"
    args = list(serve_args)
    if "--status-interval" not in args:
        args += ["--status-interval", "0"]
    proc = subprocess.Popen(
        [*CLI, "serve", "--can", spec, *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env={**os.environ, "PYTHONUNBUFFERED": "1", **(env or {})},
        cwd=ROOT,
    )
    deadline = time.monotonic() + ready_timeout_s
    line = ""
    while time.monotonic() < deadline:
        line = proc.stdout.readline()
        if not line or line.startswith("ready:"):
            break
    if not line.startswith("ready:"):
        proc.kill()
        out, err = proc.communicate()
        raise AssertionError(f"serve did not start: {line!r}\n{out}\n{err}")
    s = Served(proc, spec, group, port, line)
    try:
        yield s
    finally:
        s.stop()


def children(pid: int) -> list[int]:
    """The child processes of process ``pid`` (of all its threads), from /proc."""
    out = []
    for task in os.listdir(f"/proc/{pid}/task"):
        try:
            with open(f"/proc/{pid}/task/{task}/children") as f:
                out += [int(p) for p in f.read().split()]
        except (FileNotFoundError, ProcessLookupError):  # a thread that ended meanwhile: it has no children
            continue
    return out
