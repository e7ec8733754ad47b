"""Pacing of the drives on one bus: real time (wall clock) or SYNC lockstep.

- **real time**: every drive advances one position-loop cycle per period of the wall clock
  (``time.perf_counter``; a wait that a received frame interrupts, with the thread's timer slack set to
  1 us so that it wakes on time without a spin; ``spin_s`` > 0 adds a spin before the deadline that yields
  the GIL with ``sleep(0)``. No spin by default: under SCHED_FIFO a spinning thread only eats the real-time
  budget (the kernel throttles real-time threads for tens of ms once they take 95 % of a CPU), and the
  SYNC -> TPDO latency does not depend on when a cycle starts).
  A cycle that starts more than one period late is an *overrun*: counted
  (:attr:`RuntimeStats.overruns`, OD 0x2110:2), the late cycles are still run back to back (at most
  ``max_catch_up`` before the bus is polled again) so that the plant time stays equal to the wall time;
  only when the loop falls more than ``max_lag_s`` behind are the missed cycles given up, and they are
  counted (:attr:`RuntimeStats.skipped`, and as overruns). Nothing is absorbed silently. SYNC frames are
  answered as they arrive (TPDOs sent with the values of the latest drive cycle, then the synchronous RPDOs
  applied).
- **lockstep**: the plant advances only on SYNC. At a SYNC every slave first answers it as a drive does: the
  TPDOs due go out with the values at the SYNC instant (the end of the previous communication cycle: what
  real-time pacing sends too) and the synchronous RPDOs received before it are applied; then every drive
  runs exactly one communication cycle (0x1006 / position cycle, at least one drive cycle) on the new
  set-points. The SYNC -> TPDO latency therefore contains no axis's computation (lockstep answers as fast as
  real-time pacing, whatever the number of axes), and the result depends only on the frames, never on the
  machine's speed, as long as the host keeps up. SDO, NMT, heartbeat and timers keep running between SYNCs.
  A pass that finds up to ``max_sync_backlog`` (default 2) SYNCs works them off in order (a host that was busy for
  a moment). When it does not keep up (more SYNCs arrived since the last pass: a saturated CPU), the runtime does
  what a drive does with cycles it could not run in time: it gives them up and counts them. Every SYNC of the
  backlog is still answered at once, in order, as real-time pacing answers a late SYNC (its TPDOs with the values
  of the last cycle run, its synchronous RPDOs applied: no set-point or controlword edge is lost, the master's
  PDO monitoring sees an answer to every SYNC), but only the LATEST SYNC's cycles run
  (:attr:`RuntimeStats.syncs_skipped`, the slave's ``syncs_skipped``, the cycles given up in
  :attr:`RuntimeStats.skipped` and as overruns, OD 0x2110:2). Working the backlog's cycles off instead
  (``catch_up_syncs=True``, the exact SYNC-count plant time of a deterministic run) makes every later answer
  later still on a machine that cannot keep up.

Drive time per SYNC in lockstep is the communication cycle the master declares (0x1006), bounded by
``max_sync_period_s`` (default :data:`LOCKSTEP_MAX_SYNC_PERIOD_S`): a larger 0x1006 is refused (SDO abort
0x06090031), so no SDO write can make one SYNC compute for minutes. A pass whose cycles take longer than
``stall_s`` of wall time (default :data:`LOCKSTEP_STALL_S`: SDO, NMT and the next SYNC waited that long) is a
*stall*: counted (:attr:`RuntimeStats.stalls`, :attr:`RuntimeStats.max_sync_work_s`) and ``Runtime.healthy`` is
then False. Once SYNCs run, the slave's timers (SYNC timeout, heartbeat producer / consumer, guarding, EMCY
inhibit, SDO timeout, RPDO deadlines) run on the drive's own cycle clock (:attr:`AxisNode.drive_time_s`, made
continuous with the wall clock at the first SYNC; a frame arrives at the drive time it is handled at), and what
falls due during a SYNC's cycles goes out right after them; before the first SYNC they run on the wall clock.

Order of a SYNC answer with several axes: every axis' TPDOs first (in axis order), then every axis' RPDOs
(``CanopenSlave.transmit_sync`` / ``apply_sync``). Answering axis by axis (RPDO applied, then TPDO) made the
n-th axis' TPDO wait for n - 1 set-point processings (~47 us each: +280 us for the 7th of 7 axes).

Frames: on a bus with a file descriptor (``udp_multicast``, ``socketcan``, and :class:`BitRateBus` around
them) the runtime thread reads the bus itself (``read_in_loop``, default): it waits on the descriptor, then
takes every waiting frame in one pass and routes it to its axes: no receive thread, no hand-over of each
frame between threads (7 axes at 1 ms: SYNC -> TPDO p50 ~0.85 -> ~0.43 ms, CPU of serve 115 -> 80 % of a
core, BENCHMARKS.md). Other buses (python-can ``virtual``), or ``read_in_loop=False``: a ``can.Notifier``
thread reads the bus and wakes the loop.

Emulated CAN timing (:class:`~virtualaxis.runtime.bitrate.BitRateBus`): while the loop runs, it releases the
bus's frames itself (``take_over``): it wakes when the next frame's last bit has passed on the emulated wire, as
it wakes for a drive cycle, and releases the frames that fell due between two axes' cycles or SYNC answers. A
transmit thread of the bus's own did it with a wake-up and an interpreter-lock hand-over per frame, and waited
for the lock while the loop computed (3 axes at 1 ms, 7 at 2 ms: late answers about halved, BENCHMARKS.md).
The bus's thread takes over again when the loop ends.

Nothing dies silently: an exception escaping a drive's cycle (``drive.step``) or its object copy
(``app.flush``) is caught, logged with its traceback (logger ``virtualaxis.runtime``; the first
:data:`LOGGED_TRACEBACKS` per axis, then every 1000th), counted (:attr:`RuntimeStats.drive_exceptions`,
per axis in :attr:`AxisNode.exceptions`) and the drive is put in FAULT with EMCY 0x6100 (internal software);
its slave keeps answering SDO and NMT, and a fault reset (or NMT reset node) recovers it. An exception that
escapes the loop itself stops the thread; it is logged and recorded in :attr:`RuntimeStats.thread_error`
(``Runtime.healthy`` is then False).
"""

from __future__ import annotations

import collections
import ctypes
import gc
import logging
import select
import threading
import time
import traceback
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field

import can

from virtualaxis.runtime.axes import AxisNode
from virtualaxis.runtime.frames import MalformedFrame, frame_problem

log = logging.getLogger("virtualaxis.runtime")
#: EMCY / fault code of an exception in the drive cycle (CiA 301: 0x6100 internal software)
INTERNAL_SOFTWARE_FAULT = 0x6100
#: tracebacks logged per axis before only every 1000th is
LOGGED_TRACEBACKS = 5
#: frames taken from the bus in one pass of the loop at most (a flood cannot starve the drive cycles)
DRAIN_LIMIT = 256
#: a job of another thread (``Runtime.run_in_gap``) runs when the next drive cycle is at least this far off [s]
#: (real time; in lockstep after a pass: there is no deadline to keep) ...
GAP_JOB_MIN_SLACK_S = 3e-4
#: ... or, without that slack, once it has waited this long [s]: a side channel's picture is late by at most this
GAP_JOB_MAX_WAIT_S = 0.25
#: while SYNCs come (one within this long [s]), a job runs right after a pass that answered one, so that it ends
#: before the next SYNC instead of delaying its answer
GAP_JOB_SYNC_RECENT_S = 0.01
#: timer slack of the runtime thread [ns] (Linux default 50 us; prctl PR_SET_TIMERSLACK)
TIMER_SLACK_NS = 1000
_PR_SET_TIMERSLACK = 29
#: lockstep: drive time one SYNC advances at most [s] (0x1006 above it is refused)
LOCKSTEP_MAX_SYNC_PERIOD_S = 0.1
#: lockstep: wall time one SYNC's cycles may take before the pass counts as a stall [s]
LOCKSTEP_STALL_S = 1.0


def freeze_startup_heap() -> None:
    """Collect once, then move every object alive now (EDS dictionaries, numba and canopen internals, the
    axes) out of the cyclic garbage collector's reach (``gc.freeze``). A full collection of a process serving
    seven axes walks ~170 000 objects: 80-150 ms during which nothing is served, every few seconds. Call it
    once the axes are built, in a process that serves (not in a test process that builds many runtimes:
    frozen cycles are never collected)."""
    gc.collect()
    gc.freeze()


def _fine_timer_slack() -> None:
    """This thread's timer slack to :data:`TIMER_SLACK_NS` (waits end on time without a spin); Linux only,
    silently nothing elsewhere."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(_PR_SET_TIMERSLACK, TIMER_SLACK_NS, 0, 0, 0)
    except (OSError, AttributeError):
        pass


@dataclass
class RuntimeStats:
    cycles: int = 0  # drive cycles run (per axis)
    overruns: int = 0  # cycles that started more than one period late
    skipped: int = 0  # cycles given up (real time: > max_lag_s behind; lockstep: skipped SYNCs), also overruns
    syncs_skipped: int = 0  # lockstep: SYNCs of a backlog answered without their cycles (per axis, first axis)
    max_late_s: float = 0.0  # largest lateness of a cycle start
    syncs: int = 0  # SYNC frames handled (per axis, first axis)
    stalls: int = 0  # lockstep: passes whose cycles took longer than stall_s (nothing was served meanwhile)
    max_sync_work_s: float = 0.0  # lockstep: longest wall time of one pass's cycles
    loops: int = 0  # poll loop iterations
    busy_s: float = 0.0  # time spent polling and computing (not waiting)
    first_deadline_s: float = 0.0  # real time: perf_counter deadline of the first cycle
    next_deadline_s: float = 0.0  # real time: deadline of the next cycle to run
    checked_s: float = 0.0  # real time: last time the loop ran every cycle due
    drive_exceptions: int = 0  # exceptions caught from drive cycles (all axes); each faults its drive
    last_exception: str = ""  # "axis X: ValueError: ..." of the latest one
    thread_error: str = ""  # traceback of an exception that stopped the runtime thread ("" = never)
    # every frame taken from the bus: received = routed + unrouted + error_frames + malformed
    frames_received: int = 0  # frames (and datagrams) taken from the bus
    frames_routed: int = 0  # handed to the axes that listen to their COB-ID
    frames_unrouted: int = 0  # well-formed, for no axis (other COB-IDs, 29-bit identifiers): dropped
    error_frames: int = 0  # CAN error frames: dropped
    frames_malformed: int = 0  # no classical CAN frame (runtime.frames): dropped, in every axis' 0x2100:1
    last_malformed: str = ""  # why the latest malformed frame was dropped
    gap_jobs: int = 0  # jobs of other threads run in the gap before the next cycle (run_in_gap)
    gap_jobs_forced: int = 0  # ... of them run outside their gap (no slack, or not after a SYNC's answer), late
    gap_job_errors: int = 0  # ... that raised (logged, the loop goes on)
    gap_job_min_slack_s: float = float("inf")  # real time: the least time to the next cycle an unforced job was given
    started_s: float = field(default_factory=time.perf_counter)

    def as_dict(self) -> dict:
        elapsed = time.perf_counter() - self.started_s
        return {
            "cycles": self.cycles,
            "overruns": self.overruns,
            "skipped": self.skipped,
            "max_late_ms": self.max_late_s * 1e3,
            "syncs": self.syncs,
            "syncs_skipped": self.syncs_skipped,
            "stalls": self.stalls,
            "max_sync_work_ms": self.max_sync_work_s * 1e3,
            "loops": self.loops,
            "elapsed_s": elapsed,
            "busy_share": self.busy_s / elapsed if elapsed > 0 else 0.0,
            "drive_exceptions": self.drive_exceptions,
            "last_exception": self.last_exception,
            "thread_error": self.thread_error,
            "frames_received": self.frames_received,
            "frames_routed": self.frames_routed,
            "frames_unrouted": self.frames_unrouted,
            "error_frames": self.error_frames,
            "frames_malformed": self.frames_malformed,
            "last_malformed": self.last_malformed,
            "gap_jobs": self.gap_jobs,
            "gap_jobs_forced": self.gap_jobs_forced,
            "gap_job_errors": self.gap_job_errors,
        }


def _receive_fd(bus: can.BusABC) -> int:
    """The descriptor the loop can wait on and read the bus through itself, -1 if it has none."""
    try:
        fd = bus.fileno()
    except Exception:  # noqa: BLE001 - NotImplementedError (virtual bus) or a closed bus
        return -1
    return fd if isinstance(fd, int) and fd >= 0 else -1


class _Router(can.Listener):
    """One listener for every axis of the bus: every frame taken from the bus is counted in ``stats``
    (:class:`RuntimeStats`) and either handed to the slaves that listen to its COB-ID (cached per COB-ID, the
    cache dropped whenever a slave's COB-IDs change; the loop woken only then) or dropped: a malformed frame
    (:func:`~virtualaxis.runtime.frames.frame_problem`, also counted in every axis' 0x2100 malformed frames),
    an error frame, a 29-bit frame or a frame for no axis (a node's controller filters them too).
    ``checked``: the bus has checked its frames already (``checks_frames``)."""

    def __init__(self, slaves: list, event: threading.Event, stats: RuntimeStats | None = None,
                 checked: bool = False):
        self.slaves = slaves
        self.event = event
        self.stats = stats if stats is not None else RuntimeStats()
        self.checked = checked
        self.routes: dict[int, tuple] = {}
        for slave in slaves:
            slave.on_dispatch_change = self.routes.clear

    @property
    def unrouted(self) -> int:
        """Well-formed frames for no axis (error frames and 29-bit frames included)."""
        return self.stats.frames_unrouted + self.stats.error_frames

    def on_message_received(self, msg: can.Message) -> None:
        """A frame from a receive thread: to its slaves, then the loop woken."""
        if self.route(msg):
            self.event.set()

    def route(self, msg: can.Message) -> bool:
        """A frame to the slaves that listen to its COB-ID (the loop reading the bus itself: no wake-up);
        True when some slave took it."""
        stats = self.stats
        stats.frames_received += 1
        if not self.checked:
            problem = frame_problem(msg)
            if problem is not None:
                self.malformed(problem)
                return False
        if msg.is_error_frame:
            stats.error_frames += 1
            return False
        if msg.is_extended_id:
            stats.frames_unrouted += 1
            return False
        cob = msg.arbitration_id
        targets = self.routes.get(cob)
        if targets is None:
            targets = tuple(s for s in self.slaves if s.listens_to(cob))
            self.routes[cob] = targets
        if not targets:
            stats.frames_unrouted += 1
            return False
        stats.frames_routed += 1
        for slave in targets:
            slave.receive(msg)
        return True

    def malformed(self, reason: str) -> None:
        """A frame from the bus that is no classical CAN frame: counted (the runtime's and every axis'
        0x2100 malformed frames) and dropped."""
        stats = self.stats
        stats.frames_malformed += 1
        stats.last_malformed = reason[:200]
        for slave in self.slaves:
            slave.counters["malformed_frames"] += 1

    def on_error(self, exc: Exception) -> None:
        """A receive error: a malformed frame the bus refused to decode (:class:`MalformedFrame`: counted as a
        frame received and malformed), else an error of the bus itself (every axis' internal errors)."""
        if isinstance(exc, MalformedFrame):
            self.stats.frames_received += 1
            self.malformed(str(exc))
            return
        for slave in self.slaves:
            slave.counters["internal_errors"] += 1


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
        spin_s: float = 0.0,
        idle_poll_s: float = 1e-3,
        max_catch_up: int = 5,
        max_lag_s: float = 0.5,
        catch_up_syncs: bool = False,
        max_sync_backlog: int = 2,
        read_in_loop: bool = True,
        max_sync_period_s: float = LOCKSTEP_MAX_SYNC_PERIOD_S,
        stall_s: float = LOCKSTEP_STALL_S,
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
        self.catch_up_syncs = catch_up_syncs  # lockstep: work a SYNC backlog off instead of skipping it
        # lockstep: SYNCs found in one pass whose cycles are still run in order; more: only the latest one's run
        self.max_sync_backlog = max(1, int(max_sync_backlog))
        self.read_in_loop = read_in_loop  # read the bus in the loop's thread (if it has a descriptor)
        if not max_sync_period_s > 0.0 or not stall_s > 0.0:
            raise ValueError(f"max_sync_period_s and stall_s must be > 0 s (got {max_sync_period_s}, {stall_s})")
        self.stall_s = stall_s  # lockstep: a pass's cycles longer than this (wall time) are a stall
        if lockstep:
            for ax in axes:
                ax.limit_sync_period(max_sync_period_s)
                ax.slave.frame_timestamps = False  # every frame arrives at the drive time it is handled at
        self.stats = RuntimeStats()
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._notifier: can.Notifier | None = None
        self._opened = False
        self._fd = -1  # the bus's receive descriptor when the loop reads the bus itself (-1: a Notifier does)
        self._bus_drain = None  # the bus's own drain(limit, on_error) -> frames, when it has one
        #: while the loop runs on a bus that lets it release the frames itself (``release_due(now)`` -> next due
        #: time, see :class:`~virtualaxis.runtime.bitrate.BitRateBus`): that function, else None
        self._release: Callable[[float], float | None] | None = None
        self._t0 = time.perf_counter()
        self.lock = threading.RLock()  # held while the loop works; take it to touch the axes from outside
        self._gap_jobs: collections.deque = collections.deque()  # (submitted at [perf_counter s], job)
        self._sync_answered_s = -1.0  # perf_counter of the last pass that answered a SYNC (gap jobs)
        self._answered: list = []  # real time: (axis, SYNC counters) whose TPDOs went out, RPDOs still to apply
        self._stepping: list = []  # lockstep: (axis, SYNC counters) answered in this pass, cycles still to run

    def now(self) -> float:
        return time.perf_counter() - self._t0

    def run_in_gap(self, job: Callable[[], None]) -> None:
        """Thread-safe: run ``job()`` in the runtime thread, in the gap before a drive cycle (at least
        :data:`GAP_JOB_MIN_SLACK_S` ahead of it; after :data:`GAP_JOB_MAX_WAIT_S` in any case), one job per pass of
        the loop, in the order submitted; while SYNCs come, right after one was answered. For a side channel's
        periodic reading of the drives: done by the thread that owns them, it never contends with a cycle for the
        interpreter lock or a drive's lock, as the same work in a thread of its own does (each forced switch of
        the interpreter lock costs the cycle a wake-up). An exception is logged and counted
        (``stats.gap_job_errors``). Jobs wait for the runtime thread (before :meth:`start` they do not run)."""
        self._gap_jobs.append((time.perf_counter(), job))

    def _run_gap_job(self, now: float, next_cycle: float | None, answered_sync: bool) -> None:
        """The oldest waiting job, if the gap allows it (see :meth:`run_in_gap`); ``answered_sync``: this pass
        answered a SYNC."""
        jobs = self._gap_jobs
        submitted, job = jobs[0]
        forced = ((next_cycle is not None and next_cycle - now < GAP_JOB_MIN_SLACK_S)
                  or (not answered_sync and now - self._sync_answered_s < GAP_JOB_SYNC_RECENT_S))
        if forced and now - submitted < GAP_JOB_MAX_WAIT_S:
            return
        jobs.popleft()
        stats = self.stats
        stats.gap_jobs += 1
        if forced:
            stats.gap_jobs_forced += 1
        elif next_cycle is not None and next_cycle - now < stats.gap_job_min_slack_s:
            stats.gap_job_min_slack_s = next_cycle - now
        try:
            job()
        except Exception:  # noqa: BLE001 - a side channel's job never stops the drive
            stats.gap_job_errors += 1
            if stats.gap_job_errors <= LOGGED_TRACEBACKS:
                log.exception("a job run in the gap before a drive cycle raised")

    # ------------------------------------------------------------------ lifecycle
    def open(self) -> None:
        """Start receiving and boot every slave (boot-up frame, PRE-OPERATIONAL)."""
        if self._opened:
            return
        self._opened = True
        self.router = _Router([ax.slave for ax in self.axes], self._wake, self.stats,
                              checked=bool(getattr(self.bus, "checks_frames", False)))
        self._fd = _receive_fd(self.bus) if self.read_in_loop else -1
        if self._fd >= 0:
            self._bus_drain = getattr(self.bus, "drain", None)
        else:
            self._notifier = can.Notifier(self.bus, [self.router], timeout=0.05)
        now = self.now()
        for ax in self.axes:
            ax.slave.boot(now)
            ax.app.flush()

    def _clock(self, ax: AxisNode, now: float) -> float:
        """The time ``ax``'s slave timers run on: in lockstep, once SYNCs started, the drive's own cycle clock
        (continuous with the wall clock at the first SYNC); else (real time, or lockstep before the first SYNC
        after a boot: boot-up, configuration, heartbeats of a node nobody drives yet) the wall clock ``now``
        (shifted to stay continuous)."""
        origin = ax.lockstep_origin_s
        if origin is None:
            return now + ax.wall_offset_s
        if ax.slave.boots != ax.clock_boots:  # the node booted again (NMT reset): wall clock until the next SYNC
            t = origin + ax.drive_time_s
            ax.lockstep_origin_s = None
            ax.wall_offset_s = t - now
            return t
        return origin + ax.drive_time_s

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
        self._opened = False

    def __enter__(self) -> Runtime:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    # ------------------------------------------------------------------ loop
    @property
    def healthy(self) -> bool:
        """False once a drive cycle raised, the runtime thread stopped on an exception or (lockstep) a pass's
        cycles stalled the node for longer than ``stall_s``."""
        return not self.stats.drive_exceptions and not self.stats.thread_error and not self.stats.stalls

    def run(self, duration_s: float | None = None) -> RuntimeStats:
        """Run until :meth:`stop` (or for ``duration_s``); an exception that escapes the loop is logged and
        recorded in ``stats.thread_error`` (then re-raised)."""
        try:
            return self._run(duration_s)
        except BaseException:
            self.stats.thread_error = traceback.format_exc()
            log.critical("runtime thread stopped:\n%s", self.stats.thread_error)
            raise

    def _drive_failed(self, ax: AxisNode, exc: BaseException) -> None:
        """An exception escaped ``ax``'s cycle: log, count, fault the drive (EMCY 0x6100)."""
        stats = self.stats
        stats.drive_exceptions += 1
        ax.exceptions += 1
        stats.last_exception = f"axis {ax.name}: {type(exc).__name__}: {exc}"
        if ax.exceptions <= LOGGED_TRACEBACKS or ax.exceptions % 1000 == 0:
            log.error("axis %s (node %d): drive cycle raised (exception %d of this axis); drive faulted with "
                      "0x%04X", ax.name, ax.node_id, ax.exceptions, INTERNAL_SOFTWARE_FAULT, exc_info=exc)
        try:
            ax.fault_internal(INTERNAL_SOFTWARE_FAULT)
        except Exception:  # noqa: BLE001 - the fault path itself is broken: counted and logged, loop goes on
            stats.drive_exceptions += 1
            if ax.exceptions <= LOGGED_TRACEBACKS:
                log.exception("axis %s: putting the drive in fault failed", ax.name)

    def _step(self, ax: AxisNode, n: int) -> None:
        ax.drive_cycles += n
        try:
            ax.drive.step(n)
            ax.app.flush()
        except Exception as exc:  # noqa: BLE001 - see module doc: caught, logged, counted, faulted
            self._drive_failed(ax, exc)

    def _flush(self, ax: AxisNode) -> None:
        try:
            ax.app.flush()
        except Exception as exc:  # noqa: BLE001
            self._drive_failed(ax, exc)

    def poll_once(self) -> None:
        """One pass of the loop's frame service in the caller's thread (no pacing): frames and timers of
        every slave, SYNCs answered and, in lockstep, the communication cycles run (benchmarks, tests). When
        the runtime reads the bus itself (``read_in_loop``, after :meth:`open`), the waiting frames are read
        first."""
        if self._fd >= 0:
            self._drain()
        with self.lock:
            self._service(self.now())

    def _service(self, now: float, queued_only: bool = False) -> None:
        """Frames and timers of every axis; the SYNCs received are answered in two passes over the axes: first
        every axis' synchronous TPDOs (the values at the SYNC instant), then every axis' synchronous RPDOs
        applied. The last axis' TPDO therefore waits only for the other axes' frame handling and TPDO
        transmission, not for their set-point processing (see ``CanopenSlave.on_sync`` for why a drive may
        answer in that order). ``queued_only`` (real time, between two axes' cycles): only the axes with
        frames waiting are polled (their timers run at the next full pass, at least once per loop)."""
        stepping = self._stepping
        answered = self._answered
        lockstep = self.lockstep
        for _, ax, counters in self._poll_axes(now, queued_only):
            if lockstep and len(counters) > self.max_sync_backlog and not self.catch_up_syncs:
                counters = self._skip_backlog(ax, counters, self._clock(ax, now))
            # the TPDOs of the oldest SYNC out now (real time with a backlog: one after the other, below)
            ax.slave.transmit_sync(counters[0], self._clock(ax, now))
            answered.append((ax, counters))
        if not answered:
            return
        for ax, counters in answered:
            if lockstep:
                # the cycles run once every axis has answered; the flush after them mirrors what the RPDOs
                # changed (the frames of the poll flushed their own changes through the application's hooks)
                ax.slave.apply_sync()
                stepping.append((ax, counters))
                continue
            if self._release is not None:  # (the first axes' TPDOs may be due on the wire by now)
                self._release_frames()
            self._flush(ax)
            ax.slave.apply_sync()
            self._flush(ax)
            for counter in counters[1:]:  # real time, several SYNCs in one pass: answered in order
                ax.slave.on_sync(counter, now)
                self._flush(ax)
        answered.clear()
        if stepping:
            axes0 = self.axes[0]
            t_cycles = time.perf_counter()
            for ax, counters in stepping:
                n = ax.sync_cycles()
                self._step(ax, n)
                for counter in counters[1:]:  # a backlog of SYNCs: one communication cycle per SYNC, in order
                    ax.slave.on_sync(counter, self._clock(ax, now))
                    self._flush(ax)
                    self._step(ax, n)
                ax.slave.poll_timers(self._clock(ax, now))  # what fell due in these cycles goes out now, in order
                self._flush(ax)
                if self._release is not None:
                    self._release_frames()
                if ax is axes0:
                    self.stats.cycles += n * len(counters)
            stepping.clear()
            took = time.perf_counter() - t_cycles
            if took > self.stats.max_sync_work_s:
                self.stats.max_sync_work_s = took
            if took > self.stall_s:
                self.stats.stalls += 1
                log.error("lockstep: one SYNC's cycles took %.3f s (> %.3f s): SDO, NMT and SYNC went unanswered "
                          "meanwhile", took, self.stall_s)

    def _poll_axes(self, now: float, queued_only: bool) -> Iterator[tuple[int, AxisNode, list[int]]]:
        """Frames and timers of every axis (``queued_only``: only of the axes with frames waiting), axis after
        axis; yields (index, axis, SYNC counters received) for each axis that received a SYNC, before the next
        axis is polled (an axis without one is flushed)."""
        axes = self.axes
        stats = self.stats
        for i, ax in enumerate(axes):
            if queued_only and not ax.slave.frames_queued:
                continue
            counters = ax.slave.poll(self._clock(ax, now))
            if not counters:
                self._flush(ax)
                continue
            if self.lockstep and ax.lockstep_origin_s is None:
                ax.lockstep_origin_s = now + ax.wall_offset_s - ax.drive_time_s
                ax.clock_boots = ax.slave.boots
            if i == 0:
                stats.syncs += len(counters)
            yield i, ax, counters

    def _skip_backlog(self, ax: AxisNode, counters: list[int], now: float) -> list[int]:
        """Lockstep, more SYNCs since the last pass than ``max_sync_backlog``: the cycles of all but the latest
        are given up (see the module doc: answered, RPDOs applied in order, no cycles, counted; a SYNC's RPDOs
        that carry only set-points the next SYNC replaces are not applied, ``CanopenSlave.skip_sync``);
        returns the latest."""
        skipped = counters[:-1]
        for counter in skipped:
            ax.slave.skip_sync(counter, now)
        self._flush(ax)
        lost = len(skipped) * ax.sync_cycles()
        ax.drive.record_overrun(lost)
        if ax is self.axes[0]:
            self.stats.syncs_skipped += len(skipped)
            self.stats.skipped += lost
            self.stats.overruns += lost
        return counters[-1:]

    # ------------------------------------------------------------------ frames
    def _drain(self) -> None:
        """Direct reading: every frame waiting on the bus (at most :data:`DRAIN_LIMIT`) to its slaves."""
        router = self.router
        route = router.route  # (this thread reads and serves the frames: nobody to wake)
        try:
            if self._bus_drain is not None:
                for msg in self._bus_drain(DRAIN_LIMIT, router.on_error):
                    route(msg)
                return
            recv = self.bus.recv
            for _ in range(DRAIN_LIMIT):
                msg = recv(0.0)
                if msg is None:
                    return
                route(msg)
        except Exception as exc:  # noqa: BLE001 - a receive error: counted, the loop goes on
            router.on_error(exc)

    def _frames_waiting(self) -> bool:
        """A frame has arrived that the loop has not taken yet."""
        if self._fd < 0:
            return self._wake.is_set()
        try:
            return bool(select.select((self._fd,), (), (), 0)[0])
        except (OSError, ValueError):
            return False

    def _wait(self, timeout_s: float) -> None:
        """Until a frame arrives or ``timeout_s`` has passed (or :meth:`stop`)."""
        if self._fd < 0:
            self._wake.wait(timeout_s)
            return
        try:
            select.select((self._fd,), (), (), timeout_s)
        except (OSError, ValueError):  # the bus was closed under the loop: stop() follows
            self._stop.wait(timeout_s)

    def _release_frames(self) -> float | None:
        """The frames whose time on the emulated wire has passed out now; when the next one is due (None: none
        waits, or the bus releases its frames itself)."""
        release = self._release
        return None if release is None else release(time.perf_counter())

    def _run(self, duration_s: float | None = None) -> RuntimeStats:
        self.open()
        _fine_timer_slack()
        take_over = getattr(self.bus, "take_over", None)
        if callable(take_over) and callable(getattr(self.bus, "release_due", None)):
            take_over()  # (the loop releases the emulated bus's frames: it wakes on time anyway)
            self._release = self.bus.release_due
        try:
            return self._loop(duration_s)
        finally:
            if self._release is not None:
                self._release = None
                self.bus.hand_back()

    def _loop(self, duration_s: float | None) -> RuntimeStats:
        direct = self._fd >= 0
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
            syncs0 = stats.syncs
            if end is not None and t_busy >= end:
                break
            if direct:
                self._drain()  # (reading the socket itself, the loop waits on it, not on the wake event)
            else:
                wake.clear()
            with self.lock:
                self._service(perf() - self._t0)
                if not self.lockstep:
                    t = perf()
                    if t - next_cycle > self.max_lag_s:
                        # hopelessly behind (machine overloaded or suspended): restart the schedule and
                        # count the cycles given up
                        lost = int((t - next_cycle) / period)
                        stats.skipped += lost
                        stats.overruns += lost
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
                            self._step(ax, 1)
                            if self._release is not None:
                                self._release_frames()
                            if len(axes) > 1 and self._frames_waiting():
                                # a frame arrived meanwhile (a SYNC?): answer it before the next axis's
                                # cycle, so no SYNC waits for the cycles of every axis
                                if direct:
                                    self._drain()
                                else:
                                    wake.clear()
                                self._service(perf() - self._t0, queued_only=True)
                        stats.cycles += 1
                        next_cycle += period
                        t = perf()
                    stats.next_deadline_s = next_cycle
                    stats.checked_s = t
            due = self._release_frames()
            t = perf()
            answered_sync = stats.syncs != syncs0
            if answered_sync:
                self._sync_answered_s = t
            if self._gap_jobs:
                self._run_gap_job(t, None if self.lockstep else next_cycle, answered_sync)
                due = self._release_frames()
                t = perf()
            stats.loops += 1
            stats.busy_s += t - t_busy
            # wait for the next cycle (real time) or for a frame / the timer tick (both modes), or until the
            # next emulated frame is due on the wire
            deadline = t + self.idle_poll_s if self.lockstep else min(next_cycle, t + self.idle_poll_s)
            if due is not None and due < deadline:
                deadline = due
            remaining = deadline - t
            spin = 0.0 if self.lockstep else self.spin_s  # (lockstep: no deadline to meet, nothing to spin for)
            if remaining > spin:
                self._wait(remaining - spin)
            if spin:
                while not self._frames_waiting() and perf() < deadline:
                    sleep(0)  # yields the GIL (other threads: side channels, a Notifier)
        return stats
