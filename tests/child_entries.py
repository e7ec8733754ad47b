"""Entry points of test child processes for ``services.child.ChildProcess`` (imported in the child)."""

from __future__ import annotations

import time

from virtualaxis.services.child import enter_child


def busy_then_ready(link_fd: int) -> None:
    """Computes for the seconds serve's start-up message names, then reports ready (a child whose imports a busy
    host stretches)."""
    got = enter_child(link_fd)
    if got is None:
        return
    link, init = got
    end = time.monotonic() + float(init[1])
    while time.monotonic() < end:
        sum(i * i for i in range(1000))
    link.send(("ready", "busy"))
    link.recv()  # (until serve says stop or goes)


def asleep_then_ready(link_fd: int) -> None:
    """Sleeps for the seconds the start-up message names (computes nothing: a child that is stuck), then ready."""
    got = enter_child(link_fd)
    if got is None:
        return
    link, init = got
    time.sleep(float(init[1]))
    link.send(("ready", "asleep"))
    link.recv()
