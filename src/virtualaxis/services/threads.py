"""Thread settings that keep the side channels out of the drive's way.

- :func:`below_the_drive`: a side channel's process (Modbus server, MQTT publisher, OPC UA and live-page
  servers) runs below the drive. It leaves an inherited SCHED_FIFO (``serve --rt-priority N``) for SCHED_OTHER,
  and it runs at nice :data:`SIDE_CHANNEL_NICE`, so that on a host without real-time priority the drive's
  runtime thread, waking for its cycle, still preempts a client's request being served: as in a field drive,
  communication is the background task and the control cycle the foreground one. (Threads *inside*
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
#: nice value of the side channels' processes (0 is serve's; 19 the lowest priority)
SIDE_CHANNEL_NICE = 10
#: the first statement of a side channel's child interpreter (``python -c``): below the drive before anything else
#: is imported (numpy's BLAS threads start at import and keep the priority they start with)
CHILD_PROLOGUE = "from virtualaxis.services.threads import below_the_drive; below_the_drive(); "


def leave_realtime() -> None:
    """Run the calling thread at SCHED_OTHER (no-op where it already does or where it cannot be set)."""
    try:
        if os.sched_getscheduler(0) in (os.SCHED_FIFO, os.SCHED_RR):
            os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    except (AttributeError, OSError):
        pass


def below_the_drive(nice: int = SIDE_CHANNEL_NICE) -> None:
    """Run the calling process at SCHED_OTHER and at least nice ``nice``. Called first in a side channel's
    process (:data:`CHILD_PROLOGUE`): on Linux a thread's priority is its own, and threads started later inherit
    it."""
    leave_realtime()
    try:
        if os.getpriority(os.PRIO_PROCESS, 0) < nice:
            os.setpriority(os.PRIO_PROCESS, 0, nice)
    except (AttributeError, OSError):
        pass


def short_gil_slices(interval_s: float = SWITCH_INTERVAL_S) -> None:
    """Lower the interpreter's switch interval to ``interval_s`` (never raises it)."""
    if sys.getswitchinterval() > interval_s:
        sys.setswitchinterval(interval_s)
