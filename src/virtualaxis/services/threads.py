"""Thread settings that keep the side channels out of the drive's way.

- :func:`leave_realtime`: the Modbus server process started by a ``serve --rt-priority N`` process inherits
  SCHED_FIFO; it drops back to SCHED_OTHER so that the scheduler always prefers the drive. (Threads *inside*
  ``serve`` keep the process' priority on purpose: a thread preempted while it holds the interpreter lock
  would stall the drive's runtime thread, a priority inversion through the GIL.)
- :func:`short_gil_slices`: CPython hands the GIL to a waiting thread only after the holder has run for the
  switch interval (default 5 ms) unless the holder blocks first. A service thread that handles a burst of
  requests could then hold the drive's runtime thread for up to 5 ms; with the interval at
  :data:`SWITCH_INTERVAL_S` the runtime thread waits at most that long for any service thread.
"""

from __future__ import annotations

import os
import sys

SWITCH_INTERVAL_S = 20e-6


def leave_realtime() -> None:
    """Run the calling thread at SCHED_OTHER (no-op where it already does or where it cannot be set)."""
    try:
        if os.sched_getscheduler(0) in (os.SCHED_FIFO, os.SCHED_RR):
            os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    except (AttributeError, OSError):
        pass


def short_gil_slices(interval_s: float = SWITCH_INTERVAL_S) -> None:
    """Lower the interpreter's switch interval to ``interval_s`` (never raises it)."""
    if sys.getswitchinterval() > interval_s:
        sys.setswitchinterval(interval_s)
