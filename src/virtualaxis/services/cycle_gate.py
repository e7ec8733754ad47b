"""Side-channel work in the gap after the drive answered a SYNC, never while it is answering one.

The periodic side-channel jobs inside ``serve`` (the Modbus register image, 100 builds/s of ~50-100 us of
Python per axis; the MQTT sampler, 100 snapshots/s) share the interpreter lock and the drive's lock with the
runtime thread. Run at their own 10 ms phase, a job that starts just before a SYNC arrives delays that SYNC's
TPDOs by its length: measured (``benchmarks/bench_side_channels.py --raw``), 60-90 % of the slowest 1 % of
SYNC -> TPDO latencies under load fell on the job's phase. A real drive does its acyclic communication in the
gap of the communication cycle after the cyclic data went out; :class:`CycleGate` gives the jobs that gap:

- :class:`GateBus` wraps serve's bus and calls :meth:`CycleGate.mark` each time the runtime thread sends a PDO
  (COB-ID 0x180..0x4FF: the TPDOs due at a SYNC; a counter increment, plus a wake-up only while a job waits);
- a job calls :meth:`CycleGate.wait_next` when it is due and starts right after the next burst of PDOs went
  out (all axes' TPDOs at one SYNC; over when none followed for 100 us), i.e. with the rest of the
  communication cycle (about 0.6 ms of the 1 ms SYNC period) before the next SYNC. With no PDO traffic (no
  master, no SYNC, PRE-OPERATIONAL) it waits at most ``timeout_s`` (2 ms) and runs anyway, so a job is late by
  at most that.
"""

from __future__ import annotations

import threading
import time

import can

from virtualaxis.services.wrapped_bus import WrappedBus

PDO_TX_COBS = range(0x180, 0x500)
DEFAULT_WAIT_S = 0.002  # longest wait for a PDO before a due job runs anyway [s]
DEFAULT_SETTLE_S = 1e-4  # a PDO burst (all axes at one SYNC) is over when none followed for this long [s]


class CycleGate:
    """Counts the PDOs sent (:meth:`mark`, runtime thread) and lets jobs wait for the next one."""

    def __init__(self) -> None:
        self._cond = threading.Condition(threading.Lock())
        self._waiting = 0
        self.marks = 0  # PDOs sent (only the runtime thread writes it)
        self.waits = 0  # job waits, and those that ran on the timeout (no PDO came)
        self.timeouts = 0

    def mark(self) -> None:
        self.marks += 1
        if self._waiting:
            with self._cond:
                self._cond.notify_all()

    def wait_next(self, timeout_s: float = DEFAULT_WAIT_S, settle_s: float = DEFAULT_SETTLE_S) -> bool:
        """Block until the next PDO is sent and no further one followed for ``settle_s`` (the PDOs of all axes
        at one SYNC go out back to back) -- True; or until ``timeout_s`` passed without a PDO -- False."""
        with self._cond:
            n0 = self.marks
            self._waiting += 1
            try:
                ok = self._cond.wait_for(lambda: self.marks != n0, timeout_s)
                end = time.perf_counter() + timeout_s
                while ok and time.perf_counter() < end:
                    n1 = self.marks
                    if not self._cond.wait_for(lambda: self.marks != n1, settle_s):  # noqa: B023 - called here
                        break
            finally:
                self._waiting -= 1
        self.waits += 1
        if not ok:
            self.timeouts += 1
        return ok

    def stats(self) -> dict:
        return {"pdos_marked": self.marks, "job_waits": self.waits, "job_waits_timed_out": self.timeouts}


class GateBus(WrappedBus):
    """A bus wrapper that marks ``gate`` after every PDO it sends (everything else passes through)."""

    def __init__(self, inner: can.BusABC, gate: CycleGate):
        self.gate = gate
        super().__init__(inner)

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        self.inner.send(msg, timeout)
        if msg.arbitration_id in PDO_TX_COBS and not msg.is_extended_id:
            self.gate.mark()
