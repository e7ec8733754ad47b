"""Pacing of the drives on one bus: real time (wall clock) or SYNC lockstep.

- **real time**: every drive advances one position-loop cycle per period of the wall clock
  (``time.perf_counter``; a short ``Event.wait`` that a received frame interrupts, then a spin for the
  last ``spin_s`` that yields the GIL with ``sleep(0)`` so that the receive threads are never held up).
  A cycle that starts more than one period late is an *overrun*: counted
  (:attr:`RuntimeStats.overruns`, OD 0x2110:2), the late cycles are still run back to back (at most
  ``max_catch_up`` before the bus is polled again) so that the plant time stays equal to the wall time;
  only when the loop falls more than ``max_lag_s`` behind are the missed cycles given up, and they are
  counted (:attr:`RuntimeStats.skipped`, and as overruns). Nothing is absorbed silently. SYNC frames are
  answered as they arrive (synchronous RPDOs applied, TPDOs sent with the values of the latest drive cycle).
- **lockstep**: the plant advances only on SYNC: for each SYNC, every drive runs exactly one communication
  cycle (0x1006 / position cycle, at least one drive cycle) and then its slave sends the TPDOs due. The
  result depends only on the frames, never on the machine's speed. SDO, NMT, heartbeat and timers keep
  running between SYNCs.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field

import can

from virtualaxis.runtime.axes import AxisNode


@dataclass
class RuntimeStats:
    cycles: int = 0  # drive cycles run (per axis)
    overruns: int = 0  # cycles that started more than one period late
    skipped: int = 0  # cycles given up after falling more than max_lag_s behind (also counted as overruns)
    max_late_s: float = 0.0  # largest lateness of a cycle start
    syncs: int = 0  # SYNC frames handled (per axis, first axis)
    loops: int = 0  # poll loop iterations
    busy_s: float = 0.0  # time spent polling and computing (not waiting)
    first_deadline_s: float = 0.0  # real time: perf_counter deadline of the first cycle
    next_deadline_s: float = 0.0  # real time: deadline of the next cycle to run
    checked_s: float = 0.0  # real time: last time the loop ran every cycle due
    started_s: float = field(default_factory=time.perf_counter)

    def as_dict(self) -> dict:
        elapsed = time.perf_counter() - self.started_s
        return {
            "cycles": self.cycles,
            "overruns": self.overruns,
            "skipped": self.skipped,
            "max_late_ms": self.max_late_s * 1e3,
            "syncs": self.syncs,
            "loops": self.loops,
            "elapsed_s": elapsed,
            "busy_share": self.busy_s / elapsed if elapsed > 0 else 0.0,
        }


class _Wake(can.Listener):
    def __init__(self, event: threading.Event):
        self.event = event

    def on_message_received(self, msg: can.Message) -> None:
        self.event.set()

    def on_error(self, exc: Exception) -> None:
        pass


class Runtime:
    """Runs the axes of one bus in a background thread (:meth:`start` / :meth:`stop`) or in the caller's
    thread (:meth:`run`)."""

    def __init__(
        self,
        bus: can.BusABC,
        axes: list[AxisNode],
        *,
        lockstep: bool = False,
        period_s: float | None = None,
        spin_s: float = 150e-6,
        idle_poll_s: float = 1e-3,
        max_catch_up: int = 5,
        max_lag_s: float = 0.5,
    ):
        if not axes:
            raise ValueError("no axes to run")
        self.bus = bus
        self.axes = axes
        self.lockstep = lockstep
        self.period_s = period_s or axes[0].drive.cycle_s
        for ax in axes:
            if abs(ax.drive.cycle_s - self.period_s) > 1e-12:
                raise ValueError(
                    f"axis {ax.name}: position cycle {ax.drive.cycle_s} s differs from {self.period_s} s; "
                    "all axes of one runtime share the drive cycle"
                )
        self.spin_s = spin_s
        self.idle_poll_s = idle_poll_s
        self.max_catch_up = max_catch_up  # late cycles run back to back before the bus is polled again
        self.max_lag_s = max_lag_s
        self.stats = RuntimeStats()
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._notifier: can.Notifier | None = None
        self._t0 = time.perf_counter()
        self.lock = threading.RLock()  # held while the loop works; take it to touch the axes from outside

    def now(self) -> float:
        return time.perf_counter() - self._t0

    # ------------------------------------------------------------------ lifecycle
    def open(self) -> None:
        """Start receiving and boot every slave (boot-up frame, PRE-OPERATIONAL)."""
        if self._notifier is not None:
            return
        listeners = [ax.slave.listener() for ax in self.axes] + [_Wake(self._wake)]
        self._notifier = can.Notifier(self.bus, listeners, timeout=0.05)
        now = self.now()
        for ax in self.axes:
            ax.slave.boot(now)
            ax.app.flush()

    def start(self) -> Runtime:
        self.open()
        self._stop.clear()
        self._thread = threading.Thread(target=self.run, name="virtualaxis-runtime", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        self._wake.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            self._thread = None
        if self._notifier is not None:
            self._notifier.stop()
            self._notifier = None

    def __enter__(self) -> Runtime:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    # ------------------------------------------------------------------ loop
    def run(self, duration_s: float | None = None) -> RuntimeStats:
        """Run until :meth:`stop` (or for ``duration_s``)."""
        self.open()
        end = None if duration_s is None else time.perf_counter() + duration_s
        period = self.period_s
        axes = self.axes
        stats = self.stats
        stats.started_s = time.perf_counter()
        next_cycle = time.perf_counter() + period
        stats.first_deadline_s = stats.next_deadline_s = next_cycle
        wake, stop = self._wake, self._stop
        perf = time.perf_counter
        sleep = time.sleep
        while not stop.is_set():
            t_busy = perf()
            if end is not None and t_busy >= end:
                break
            wake.clear()
            with self.lock:
                now = t_busy - self._t0
                for ax in axes:
                    counters = ax.slave.poll(now)
                    ax.app.flush()
                    if not counters:
                        continue
                    if ax is axes[0]:
                        stats.syncs += len(counters)
                    for counter in counters:
                        if self.lockstep:
                            ax.drive.step(ax.sync_cycles())
                            ax.app.flush()
                            if ax is axes[0]:
                                stats.cycles += ax.sync_cycles()
                        ax.slave.on_sync(counter, now)
                        ax.app.flush()
                if not self.lockstep:
                    t = perf()
                    if t - next_cycle > self.max_lag_s:
                        # hopelessly behind (machine overloaded or suspended): restart the schedule and
                        # count the cycles given up
                        lost = int((t - next_cycle) / period)
                        stats.skipped += lost
                        for ax in axes:
                            ax.drive.record_overrun(lost)
                        next_cycle += lost * period
                    caught_up = 0
                    while t >= next_cycle and caught_up < self.max_catch_up:
                        caught_up += 1
                        late = t - next_cycle
                        if late > stats.max_late_s:
                            stats.max_late_s = late
                        if late > period:
                            stats.overruns += 1
                            for ax in axes:
                                ax.drive.record_overrun()
                        for ax in axes:
                            ax.drive.step(1)
                            ax.app.flush()
                        stats.cycles += 1
                        next_cycle += period
                        t = perf()
                    stats.next_deadline_s = next_cycle
                    stats.checked_s = t
            stats.loops += 1
            t = perf()
            stats.busy_s += t - t_busy
            # wait for the next cycle (real time) or for a frame / the timer tick (both modes)
            deadline = t + self.idle_poll_s if self.lockstep else min(next_cycle, t + self.idle_poll_s)
            remaining = deadline - t
            if remaining > self.spin_s:
                wake.wait(remaining - self.spin_s)
            while not wake.is_set() and perf() < deadline:
                sleep(0)  # yields the GIL: the bus receive threads must not wait for the spin
        return stats
