"""CanopenSlave: the CiA 301 slave stack (one node) around an EDS-loaded object dictionary.

Threading: python-can delivers frames on its Notifier thread, :meth:`CanopenSlave.receive` only enqueues.
Everything else (SDO answers, PDOs, timers, application hooks) runs in the caller's thread inside
:meth:`poll` / :meth:`on_sync` / :meth:`emcy`. A frame never raises out of ``poll``: malformed frames are
counted (``counters``, OD 0x2100) and answered as a drive answers them; an unexpected exception while
handling a frame is counted as ``internal_errors``.
"""

from __future__ import annotations

import logging
import math
import select
import time
from collections import deque
from collections.abc import Callable
from pathlib import Path

import can

from virtualaxis.canopen_slave import errors as ab
from virtualaxis.canopen_slave.app import BaseApplication, CanopenApplication, check_application
from virtualaxis.canopen_slave.cobid import check_write as check_cob_id
from virtualaxis.canopen_slave.cobid import is_cob_id_object
from virtualaxis.canopen_slave.counters import COUNTERS_2100, abort_key, new_counters
from virtualaxis.canopen_slave.emcy import EmcyProducer
from virtualaxis.canopen_slave.errors import ABORT_CODES, SdoAbort
from virtualaxis.canopen_slave.heartbeat import (
    HEARTBEAT_BASE,
    HeartbeatConsumer,
    HeartbeatProducer,
    NodeGuarding,
)
from virtualaxis.canopen_slave.nmt import (
    COMMAND_STATES,
    NMT_COB,
    NMT_STATE,
    RESET_COMMUNICATION,
    RESET_NODE,
    NmtState,
    parse_command,
)
from virtualaxis.canopen_slave.od import Entry, ObjectStore
from virtualaxis.canopen_slave.pdo import PdoEngine
from virtualaxis.canopen_slave.sdo_server import SdoServer
from virtualaxis.canopen_slave.store import ParameterStore
from virtualaxis.canopen_slave.sync import SyncConsumer

#: receive queue limit; frames beyond it are dropped and counted as ``rx_overruns``
RX_QUEUE_LIMIT = 4096
#: objects kept through NMT reset communication (status, not parameters)
_STATUS_OBJECTS = frozenset({0x1001, 0x1003})
COB_EXTENDED = 0x20000000          # 29-bit frame bit of a COB-ID object (refused by each object's own rule)
_NOTHING_DUE: list = []           # shared, never mutated: a SYNC without synchronous RPDO data

DIAGNOSTICS, ABORT_COUNTERS, RESET_COUNTERS = 0x2100, 0x2101, 0x2102

log = logging.getLogger(__name__)


class _SlaveListener(can.Listener):
    def __init__(self, slave: CanopenSlave):
        self._slave = slave

    def on_message_received(self, msg: can.Message) -> None:
        self._slave.receive(msg)

    def on_error(self, exc: Exception) -> None:  # python-can calls this on a receive error; keep running
        from virtualaxis.runtime.frames import MalformedFrame  # (at call time: runtime imports this module)

        self._slave.counters["malformed_frames" if isinstance(exc, MalformedFrame) else "internal_errors"] += 1


def _superseded(due: list, following: list) -> bool:
    """Every RPDO of ``due`` (one SYNC's synchronous RPDO data) comes again in ``following`` (the next SYNC's)
    with the same bytes outside its set-point objects (:attr:`Rpdo.held_bytes`)."""
    for rpdo, data in due:
        again = next((d for r, d in following if r is rpdo), None)
        if again is None or any(data[a:b] != again[a:b] for a, b in rpdo.held_bytes):
            return False
    return True


class CanopenSlave:
    """One CANopen node served from an EDS. See docs/canopen-slave-api.md."""

    def __init__(self, bus: can.BusABC, node_id: int, eds_path: str | Path, *,
                 app: CanopenApplication | None = None, store_path: str | Path | None = None):
        if not isinstance(node_id, int) or not 1 <= node_id <= 127:
            raise ValueError(f"node id must be 1..127 (got {node_id!r})")
        self.bus = bus
        self.node_id = node_id
        self.counters: dict[str, int] = new_counters()
        self.od = ObjectStore(eds_path, node_id)
        self.nmt_state = NMT_STATE.INITIALISING
        self._queue: deque[can.Message] = deque()
        self._now = 0.0
        self._rx_fd: int | None = None   # the bus's receive file descriptor (-1: none), looked up once
        self._sync_cob = -1             # COB-ID of SYNC while it is monitored (receive-path delay measured)
        self._wall_to_now = 0.0          # caller's clock - time.time() at the last poll [s]
        #: True: a frame's arrival is its receive timestamp on the caller's clock; False: the ``now_s`` of the
        #: poll that handles it (a caller whose clock is the drive's own cycle clock, SYNC lockstep)
        self.frame_timestamps = True
        #: boot-ups sent (power-on and every NMT reset)
        self.boots = 0
        #: whether a frame of another node with this node-ID has been reported (:meth:`_on_own_cob_id`; once)
        self.node_id_conflict_reported = False
        self._sync_counters: list[int] = []
        self._due_sync_rpdos: deque[list] = deque(maxlen=16)
        #: per SYNC taken from the bus by the last poll, in order: whether the node was OPERATIONAL when it came
        #: (a SYNC of PRE-OPERATIONAL answered after an NMT start in the same poll gets no TPDO)
        self._sync_in_operational: deque[bool] = deque()
        self._applied_ahead = 0
        self._handlers: dict[int, Callable[[can.Message, float], None]] = {}
        self._in_error_reaction = False
        #: communication errors still present: EMCY code -> the sources of it (a heartbeat monitor's node id,
        #: 0 for SYNC / life guarding); each clears itself when its cause is gone (:meth:`clear_comm_error`)
        self._comm_errors: dict[int, set[int]] = {}
        #: 0x603F holds the code of a communication EMCY (not an application fault's cause)
        self._error_code_from_comm = False
        #: EMCYs raised while INITIALISING (a reset's reaction): (code, data), sent right after the boot-up
        self._emcy_after_boot: list[tuple[int, bytes]] = []
        #: called (no arguments) whenever the COB-IDs this node listens to change (a frame router's cache)
        self.on_dispatch_change: Callable[[], None] | None = None
        app = BaseApplication() if app is None else check_application(app)
        self.app: CanopenApplication = app
        # the hooks bound once (RPDOs are a hot path); a bare node's do nothing (BaseApplication)
        self._hook_validate = app.validate_write
        self._hook_after = app.after_write
        self._hook_before_read = app.before_read
        self._hook_nmt = app.on_nmt_state
        self._hook_comm_error = app.on_communication_error
        self._hook_reset = app.on_reset
        self.hook_begin_pdo = app.begin_pdo
        self.hook_end_pdo = app.end_pdo
        #: objects whose write only sets a value that the next write replaces (the application's
        #: ``setpoint_objects``, e.g. CiA 402 targets); see :meth:`skip_sync`
        self.setpoint_objects = frozenset(app.setpoint_objects)
        self.store = ParameterStore(store_path, self.od)
        self._power_on_values(0x0000, 0xFFFF)
        self.sdo = SdoServer(self)
        self.sync = SyncConsumer(self)
        self.emcy_producer = EmcyProducer(self)
        self.heartbeat = HeartbeatProducer(self)
        self.heartbeat_consumer = HeartbeatConsumer(self)
        self.guarding = NodeGuarding(self)
        self.pdo = PdoEngine(self)     # last: builds the dispatch table
        self.rebuild_dispatch()

    # ================================================================== public API
    def receive(self, msg: can.Message) -> None:
        """Thread-safe: enqueue one received frame (called from python-can's Notifier thread)."""
        if len(self._queue) >= RX_QUEUE_LIMIT:
            self.counters["rx_overruns"] += 1
            return
        self._queue.append(msg)
        if msg.arbitration_id == self._sync_cob and msg.timestamp and self.frame_timestamps:
            self.sync.note_delivery(time.time() - msg.timestamp)   # receive-path delay of SYNC frames

    def listener(self) -> can.Listener:
        """A python-can Listener feeding :meth:`receive` (add it to a ``can.Notifier``)."""
        return _SlaveListener(self)

    def boot(self, now_s: float) -> None:
        """Send the boot-up frame and enter PRE-OPERATIONAL."""
        self.boots += 1
        self._now = now_s
        self.send(HEARTBEAT_BASE + self.node_id, b"\x00")
        self.heartbeat.restart(now_s)
        self._set_state(NMT_STATE.PRE_OPERATIONAL)
        pending, self._emcy_after_boot = self._emcy_after_boot, []
        for code, data in pending:  # errors raised while the node initialised: sent once it can, after boot-up
            self.emcy_producer.produce(code, self.od.entries[(0x1001, 0)].value, data, now_s)

    def poll(self, now_s: float) -> list[int]:
        """Handle queued frames and timers; returns the SYNC counters received since the last poll."""
        self._now = now_s
        self._wall_to_now = now_s - time.time()
        queue = self._queue
        counters = self.counters
        if self.nmt_state == NMT_STATE.INITIALISING:      # not booted yet: a node hears nothing
            counters["frames_received"] += len(queue)
            queue.clear()
            return []
        handlers = self._handlers
        self._sync_in_operational.clear()  # (the last poll's SYNCs have all been answered)
        while queue:
            msg = queue.popleft()
            counters["frames_received"] += 1
            if msg.is_error_frame or msg.is_extended_id:
                continue
            handler = handlers.get(msg.arbitration_id)
            if handler is None:
                continue
            try:
                handler(msg, now_s)
            except Exception:  # noqa: BLE001 - the drive cycle must survive any frame
                counters["internal_errors"] += 1
        self.poll_timers(now_s)
        return self._take_sync_counters()

    def poll_timers(self, now_s: float) -> None:
        """The timers only (heartbeat producer and consumer, guarding, EMCY inhibit, SDO timeout, RPDO deadlines,
        SYNC timeout) at ``now_s``; no frame is taken (:meth:`poll` does both)."""
        self._now = now_s
        if self.nmt_state == NMT_STATE.INITIALISING:
            return
        counters = self.counters
        try:
            self.heartbeat.poll(now_s)
            if self.heartbeat_consumer.monitors:
                self.heartbeat_consumer.poll(now_s)
            self.guarding.poll(now_s)
            if self.emcy_producer.pending:
                self.emcy_producer.poll(now_s)
            if self.sdo.state:
                self.sdo.check_timeout(now_s)
            if self.nmt_state == NMT_STATE.OPERATIONAL:
                self.pdo.poll(now_s)
                if self.sync.timeout_s and self.sync.check_timeout(now_s, self._rx_pending):
                    self._sync_timeout()
        except Exception:  # noqa: BLE001
            counters["internal_errors"] += 1

    def apply_sync_rpdos(self) -> None:
        """Optional, before the application cycle of the oldest pending SYNC: apply the synchronous RPDOs
        received before that SYNC now (``on_sync`` for that SYNC then only transmits)."""
        due = self._due_sync_rpdos.popleft() if self._due_sync_rpdos else None
        self._applied_ahead += 1
        if due and self.nmt_state == NMT_STATE.OPERATIONAL:
            try:
                for rpdo, data in due:
                    self.pdo.apply(rpdo, data)
            except Exception:  # noqa: BLE001
                self.counters["internal_errors"] += 1

    def _take_due_sync_rpdos(self):
        """The synchronous RPDOs received before the SYNC now handled (None when they were applied ahead)."""
        if self._applied_ahead:
            self._applied_ahead -= 1
            return None
        return self._due_sync_rpdos.popleft() if self._due_sync_rpdos else None

    def _apply_rpdos(self, due) -> None:
        if due:
            for rpdo, data in due:
                self.pdo.apply(rpdo, data)

    def on_sync(self, counter: int, now_s: float) -> None:
        """Answer a SYNC: the TPDOs due at it go out with the values sampled at the SYNC (:meth:`transmit_sync`),
        then the synchronous RPDOs received before it are applied (:meth:`apply_sync`).

        CiA 301 samples synchronous TPDO data at the SYNC and actuates synchronous RPDO data at the SYNC; a
        drive samples its actual values first and then takes the new set-points into its next cycle, so an
        object that the same SYNC's RPDO writes shows in a TPDO at the following SYNC. A runtime serving
        several nodes calls the two halves apart: every node's TPDOs first, then every node's RPDOs."""
        self.transmit_sync(counter, now_s)
        self.apply_sync()

    def transmit_sync(self, counter: int, now_s: float) -> None:
        """First half of :meth:`on_sync`: send the synchronous TPDOs due at this SYNC (only when the node was
        OPERATIONAL when the SYNC came and still is, within the synchronous window 0x1007)."""
        self._now = now_s
        came_in_operational = self._sync_in_operational.popleft() if self._sync_in_operational else True
        if self.nmt_state != NMT_STATE.OPERATIONAL or not came_in_operational:
            return
        try:
            if self.sync.window_open(now_s):
                self.pdo.on_sync(counter, self.sync.counter_enabled, now_s)
        except Exception:  # noqa: BLE001
            self.counters["internal_errors"] += 1

    def apply_sync(self) -> None:
        """Second half of :meth:`on_sync`: apply the synchronous RPDOs received before the SYNC just answered
        (dropped outside OPERATIONAL)."""
        due = self._take_due_sync_rpdos()
        if self.nmt_state != NMT_STATE.OPERATIONAL:
            return
        try:
            self._apply_rpdos(due)
        except Exception:  # noqa: BLE001
            self.counters["internal_errors"] += 1

    def skip_sync(self, counter: int, now_s: float) -> None:
        """A SYNC whose application cycle the runtime gives up (lockstep, a backlog the host could not keep up
        with): answered like any SYNC -- the TPDOs due go out with the values of the last cycle run, then the
        synchronous RPDOs received before it are applied (no controlword edge is lost) -- and counted in
        ``counters["syncs_skipped"]``; the plant does not run its cycle. Its RPDOs are left out when every one
        of them comes again in the next SYNC with the same bytes in each object that is not a set-point
        (:attr:`setpoint_objects`): they carried nothing but set-points that the next SYNC's replace before any
        cycle runs (counted in ``counters["rpdos_superseded"]``)."""
        self.counters["syncs_skipped"] += 1
        self.transmit_sync(counter, now_s)
        due = self._due_sync_rpdos
        if not self._applied_ahead and len(due) > 1 and due[0] and _superseded(due[0], due[1]):
            self.counters["rpdos_superseded"] += len(due.popleft())
            return
        self.apply_sync()

    def read(self, index: int, sub: int = 0):
        """Internal read, no access checks (KeyError for an object not in the EDS)."""
        if index == DIAGNOSTICS or index == ABORT_COUNTERS:
            self._refresh_counters()
        return self.od.entries[(index, sub)].value

    def write(self, index: int, sub: int, value) -> None:
        """Internal write, no access or limit checks; a changed value marks event-driven TPDOs."""
        entry = self.od.entries[(index, sub)]
        if entry.value != value:
            entry.value = value
            for tpdo in entry.tpdos:
                tpdo.dirty = True
            if index < 0x2000:
                self._comm_after(index, sub)

    def entry(self, index: int, sub: int = 0) -> Entry:
        """The live entry (for a hot path: pass it to :meth:`write_entry` instead of looking it up)."""
        return self.od.entries[(index, sub)]

    def write_entry(self, entry: Entry, value) -> None:
        """Like :meth:`write` for an application object, with the entry already looked up."""
        if entry.value != value:
            entry.value = value
            for tpdo in entry.tpdos:
                tpdo.dirty = True

    def emcy(self, code: int, register_bits: int = 0, data: bytes = b"", communication: bool = False) -> None:
        """Record and send an emergency: 0x1001 |= generic bit + register_bits, push 0x1003, 0x603F = code.

        ``communication``: the stack's own error (SYNC / heartbeat / RPDO deadline, a PDO or SYNC of the wrong
        length, bus off recovered). Such a code never replaces an application error's code in 0x603F: a
        master that finds the drive in FAULT reads the fault's cause there, not a later SYNC gap or RPDO
        deadline. It takes 0x603F only when that is 0 or holds another communication error's code while the
        application reports no error of its own."""
        entries = self.od.entries
        register = entries[(0x1001, 0)]
        self.write(0x1001, 0, (register.value | register_bits | (0x01 if code else 0)) & 0xFF)
        if code:
            self.emcy_producer.push_history(code)
            error_code = entries.get((0x603F, 0))
            if error_code is not None and (not communication or not error_code.value
                                           or (self._error_code_from_comm and not self._app_has_error())):
                self.write(0x603F, 0, code & 0xFFFF)
                self._error_code_from_comm = communication
        if self.nmt_state in (NMT_STATE.PRE_OPERATIONAL, NMT_STATE.OPERATIONAL):
            self.emcy_producer.produce(code, register.value, data, self._now)
        elif self.nmt_state == NMT_STATE.INITIALISING:  # raised by a reset (e.g. 0x6007 on Reset Communication)
            self._emcy_after_boot.append((code, data))

    def _app_has_error(self) -> bool:
        """The application reports an error of its own (a drive in fault or with a warning)."""
        return bool(self.app.has_error())

    def set_application_error_code(self, code: int) -> None:
        """0x603F as the application holds it (the code of its newest error, 0 with none): 0 shows the newest
        communication error still active instead (reset with it, :meth:`clear_comm_error`), as 0x603F tells the
        errors still active."""
        if (0x603F, 0) not in self.od.entries:
            return
        from_comm = not code and bool(self._comm_errors)
        self.write(0x603F, 0, next(reversed(self._comm_errors)) if from_comm else code)
        self._error_code_from_comm = from_comm

    def emcy_reset(self) -> None:
        """The application's errors are gone: with no communication error left either, EMCY 0x0000 (error
        reset / no error) and 0x1001 = 0x603F = 0. A communication error still present keeps 0x1001's generic
        and communication bits and shows its code in 0x603F, and no EMCY goes out (0x0000 would tell the master
        that no error is left; it goes out when that error clears, :meth:`clear_comm_error`)."""
        self.write(0x1001, 0, 0x11 if self._comm_errors else 0)
        self.set_application_error_code(0)
        if not self._comm_errors and self.nmt_state in (NMT_STATE.PRE_OPERATIONAL, NMT_STATE.OPERATIONAL):
            self.emcy_producer.produce(0x0000, 0, b"", self._now)

    def raise_comm_error(self, code: int, source: int = 0, data: bytes = b"") -> None:
        """A communication error (SYNC timeout 0x8100, heartbeat / life guarding 0x8130): EMCY with the
        communication bit of 0x1001, remembered until :meth:`clear_comm_error` for the same code and source."""
        self._comm_errors.setdefault(code, set()).add(source)
        self.emcy(code, 0x10, data, communication=True)

    def comm_error_sources(self, code: int) -> frozenset[int]:
        """The sources of the communication error ``code`` still present (empty when it is not)."""
        return frozenset(self._comm_errors.get(code, ()))

    def clear_comm_error(self, code: int, source: int = 0) -> None:
        """The cause of a communication error is gone (SYNC / heartbeat back). When no communication error is
        left, 0x1001's communication bit clears; when nothing else is left either (the application reports no
        error, 0x1001 holds no other bit), 0x1001 = 0, 0x603F = 0 and EMCY 0x0000 (error reset) goes out, as
        CiA 301 has it. While the application is in error the EMCY stays unsent (a master's EMCY consumer
        would take 0x0000 as 'all errors gone')."""
        sources = self._comm_errors.get(code)
        if not sources or source not in sources:
            return
        sources.discard(source)
        if sources:
            return
        del self._comm_errors[code]
        if self._comm_errors:
            return
        entries = self.od.entries
        register = entries[(0x1001, 0)].value & ~0x10
        if register & ~0x01 or self._app_has_error():
            self.write(0x1001, 0, register)
            return
        self.write(0x1001, 0, 0)
        if self._error_code_from_comm and (0x603F, 0) in entries:
            self.write(0x603F, 0, 0)
            self._error_code_from_comm = False
        if self.nmt_state in (NMT_STATE.PRE_OPERATIONAL, NMT_STATE.OPERATIONAL):
            self.emcy_producer.produce(0x0000, 0, b"", self._now)

    # ================================================================== services' helpers
    def send(self, cob_id: int, data: bytes | bytearray) -> None:
        try:
            self.bus.send(can.Message(arbitration_id=cob_id, data=data, is_extended_id=False))
        except (can.CanError, OSError, ValueError):
            self.counters["tx_errors"] += 1

    def communication_error(self, kind: str, detail: int) -> None:
        try:
            self._hook_comm_error(kind, detail)
        except Exception:  # noqa: BLE001
            self.counters["internal_errors"] += 1

    def error_behaviour(self) -> None:
        """0x1029:1 reaction to a communication error (heartbeat / life guarding lost)."""
        mode = self.od.value(0x1029, 1) if (0x1029, 1) in self.od.entries else 0
        if mode == 0 and self.nmt_state == NMT_STATE.OPERATIONAL:
            self._set_state(NMT_STATE.PRE_OPERATIONAL)
        elif mode == 2:
            self._set_state(NMT_STATE.STOPPED)

    def rebuild_dispatch(self) -> None:
        """COB-ID -> handler table; rebuilt whenever a COB-ID or a monitored node changes."""
        if not hasattr(self, "pdo"):
            return
        handlers: dict[int, Callable[[can.Message, float], None]] = {}
        consumer = self.heartbeat_consumer
        for cob in consumer.monitors:
            handlers[cob] = self._on_heartbeat
        for cob, rpdo in self.pdo.rpdo_by_cob.items():
            handlers[cob] = rpdo_handler(self, rpdo)
        self._sync_cob = -1
        if not self.od.value(0x1005) & 0x80000000:
            handlers[self.sync.cob_id] = self._on_sync_frame
            self._sync_cob = self.sync.cob_id
        handlers[self.sdo.rx_cob] = self._on_sdo
        handlers[HEARTBEAT_BASE + self.node_id] = self._on_guard
        handlers[self.sdo.tx_cob] = self._on_own_cob_id
        handlers[NMT_COB] = self._on_nmt
        self._handlers = handlers
        if self.on_dispatch_change is not None:
            self.on_dispatch_change()

    @property
    def frames_queued(self) -> bool:
        """Frames received (:meth:`receive`) that :meth:`poll` has not handled yet."""
        return bool(self._queue)

    def listens_to(self, cob_id: int) -> bool:
        """True if a frame on ``cob_id`` (11-bit, data or RTR) is for this node (NMT, SYNC, SDO, RPDOs, the
        monitored heartbeats, node guarding)."""
        return cob_id in self._handlers

    def entry_size(self, index: int, sub: int) -> int | None:
        entry = self.od.entries.get((index, sub))
        return entry.size if entry is not None else None

    # ================================================================== SDO object access
    def _lookup(self, index: int, sub: int) -> Entry:
        obj = self.od.objects.get(index)
        if obj is None:
            raise SdoAbort(ab.NO_OBJECT)
        entry = obj.subs.get(sub)
        if entry is None:
            raise SdoAbort(ab.NO_SUBINDEX)
        if index == 0x1003 and sub > obj.subs[0].value:
            raise SdoAbort(ab.NO_DATA, "no error recorded at this sub-index")
        return entry

    def sdo_check_writable(self, index: int, sub: int) -> Entry:
        entry = self._lookup(index, sub)
        if not entry.writable:
            raise SdoAbort(ab.WRITE_READ_ONLY)
        return entry

    def sdo_check_length(self, index: int, sub: int, size: int) -> None:
        entry = self._lookup(index, sub)
        if entry.size is not None:
            if size > entry.size:
                raise SdoAbort(ab.LENGTH_TOO_HIGH)
            if size < entry.size:
                raise SdoAbort(ab.LENGTH_TOO_LOW)

    def sdo_upload(self, index: int, sub: int) -> bytes:
        entry = self._lookup(index, sub)
        if not entry.readable:
            raise SdoAbort(ab.READ_WRITE_ONLY)
        if index == DIAGNOSTICS or index == ABORT_COUNTERS:
            self._refresh_counters()
        self._call_app(self._hook_before_read, index, sub)
        return entry.encode(entry.value)

    def sdo_download(self, index: int, sub: int, data: bytes) -> None:
        entry = self.sdo_check_writable(index, sub)
        self.sdo_check_length(index, sub, len(data))
        value = entry.decode(data)
        if index == 0x1010 or index == 0x1011:
            self.store.command(index, sub, value)
            return
        if index == 0x1003:  # CiA 301: any value but 0 at sub 0 is refused 0x06090030, whatever the EDS limits
            self.emcy_producer.validate_write(index, sub, value)
        self._check_limits(entry, value)
        if index == RESET_COUNTERS:
            if value != 1:
                raise SdoAbort(ab.INVALID_VALUE, "write 1 to reset the counters")
            for key in self.counters:
                self.counters[key] = 0
            return
        if index < 0x2000:
            self._comm_validate(index, sub, value)
        self._call_app(self._hook_validate, index, sub, value)
        self.write(index, sub, value) if index < 0x2000 else self.write_entry(entry, value)
        self._call_app(self._hook_after, index, sub, entry.value)

    def _call_app(self, hook, *args) -> None:
        try:
            hook(*args)
        except SdoAbort:
            raise
        except Exception as exc:  # noqa: BLE001 - an application bug must not stop the drive
            self.counters["internal_errors"] += 1
            raise SdoAbort(ab.GENERAL_ERROR, str(exc)) from None

    @staticmethod
    def _check_limits(entry: Entry, value) -> None:
        if isinstance(value, float) and not math.isfinite(value):
            raise SdoAbort(ab.INVALID_VALUE, "not a finite number")
        if entry.high is not None and value > entry.high:
            raise SdoAbort(ab.VALUE_TOO_HIGH)
        if entry.low is not None and value < entry.low:
            raise SdoAbort(ab.VALUE_TOO_LOW)

    def store_all_from_pdo(self, entries, values) -> None:
        """The entries of one received PDO, in mapping order, each: limits and the application's
        validate_write, then stored and after_write; a refused value is dropped and counted
        (``rpdo_values_refused``), the others are stored. One call per PDO (a hot path: the limits are compared
        inline and :meth:`_check_limits` runs only to refuse)."""
        validate, after, counters = self._hook_validate, self._hook_after, self.counters
        for entry, value in zip(entries, values, strict=True):
            try:
                high, low = entry.high, entry.low
                if ((high is not None and value > high) or (low is not None and value < low)
                        or (isinstance(value, float) and not math.isfinite(value))):
                    self._check_limits(entry, value)
                validate(entry.index, entry.sub, value)
            except SdoAbort:
                counters["rpdo_values_refused"] += 1
                continue
            except Exception:  # noqa: BLE001
                counters["internal_errors"] += 1
                continue
            if entry.value != value:
                entry.value = value
                for tpdo in entry.tpdos:
                    tpdo.dirty = True
            try:
                after(entry.index, entry.sub, value)
            except Exception:  # noqa: BLE001
                counters["internal_errors"] += 1

    def store_from_pdo(self, entry: Entry, value) -> None:
        """One RPDO value (see :meth:`store_all_from_pdo`)."""
        self.store_all_from_pdo((entry,), (value,))

    # ================================================================== communication objects
    def _comm_validate(self, index: int, sub: int, value) -> None:
        if is_cob_id_object(index, sub) and isinstance(value, int) and not value & COB_EXTENDED:
            check_cob_id(self, index, value)
        if self.pdo.owns(index):
            self.pdo.validate_write(index, sub, value)
        elif index in (0x1005, 0x1006, 0x1007, 0x1019):
            self.sync.validate_write(index, sub, value)
        elif index in (0x1003, 0x1014):
            self.emcy_producer.validate_write(index, sub, value)
        elif index == 0x1016 and sub > 0:
            self.heartbeat_consumer.validate_write(index, sub, value)

    def _comm_after(self, index: int, sub: int) -> None:
        if not hasattr(self, "pdo"):
            return
        if self.pdo.owns(index):
            self.pdo.after_write(index, sub)
        elif index in (0x1005, 0x1006, 0x1007, 0x1019):
            self.sync.after_write(index, sub)
        elif index == 0x1003:
            self.emcy_producer.after_write(index, sub)
        elif index == 0x1016:
            self.heartbeat_consumer.after_write(index, sub)
        elif index == 0x1017:
            self.heartbeat.restart(self._now)
        elif index in (0x100C, 0x100D):
            self.guarding.last_rtr_s = None if self.od.value(0x100C) == 0 else self.guarding.last_rtr_s

    def _refresh_counters(self) -> None:
        entries = self.od.entries
        counters = self.counters
        for sub, (key, _name) in enumerate(COUNTERS_2100, start=1):
            entry = entries.get((DIAGNOSTICS, sub))
            if entry is not None:
                entry.value = counters[key] & 0xFFFFFFFF
        for sub, code in enumerate(ABORT_CODES, start=1):
            entry = entries.get((ABORT_COUNTERS, sub))
            if entry is not None:
                entry.value = counters[abort_key(code)] & 0xFFFFFFFF

    def _power_on_values(self, lo: int, hi: int, keep: frozenset[int] = frozenset()) -> None:
        self.od.reset(lo, hi, keep)
        self.store.apply(lo, hi)
        if not self.store.available:   # 0x1010/0x1011 read 0: "does not save / restore on command"
            for index in (0x1010, 0x1011):
                obj = self.od.objects.get(index)
                if obj is not None:
                    for sub, entry in obj.subs.items():
                        if sub:
                            entry.value = 0

    # ================================================================== NMT
    def _set_state(self, state: NmtState) -> None:
        if state == self.nmt_state:
            return
        self.nmt_state = state
        if state == NMT_STATE.OPERATIONAL:
            self.pdo.on_operational()
            self.sync.last_sync_s = None        # SYNC monitoring restarts with the next SYNC
            self.sync.timed_out = False
        elif state == NMT_STATE.STOPPED:
            self.sdo.reset()
        self._due_sync_rpdos.clear()
        self._applied_ahead = 0
        try:
            self._hook_nmt(state)
        except Exception:  # noqa: BLE001
            self.counters["internal_errors"] += 1

    def _reset(self, application: bool) -> None:
        self.nmt_state = NMT_STATE.INITIALISING
        if application:
            self._power_on_values(0x0000, 0xFFFF)
            self._comm_errors.clear()
            self._error_code_from_comm = False
        else:
            self._power_on_values(0x1000, 0x1FFF, keep=_STATUS_OBJECTS)
        self.sdo.reset()
        self.emcy_producer.reset()
        self.guarding.reset()
        self.sync.configure()
        self.heartbeat_consumer.configure()
        self._sync_counters = []
        self._due_sync_rpdos.clear()
        self._applied_ahead = 0
        self.pdo.configure_all()
        try:
            self._hook_reset(application)
        except Exception:  # noqa: BLE001
            self.counters["internal_errors"] += 1
        self.boot(self._now)

    # ================================================================== frame handlers
    def _on_nmt(self, msg: can.Message, _now_s: float) -> None:
        kind, command = parse_command(msg.data, self.node_id)
        if kind == "malformed":
            self.counters["malformed_frames"] += 1
        elif kind == "other_node":
            self.counters["nmt_other_node_ignored"] += 1
        elif command == RESET_NODE:
            self._reset(application=True)
        elif command == RESET_COMMUNICATION:
            self._reset(application=False)
        elif command in COMMAND_STATES:
            self._set_state(COMMAND_STATES[command])
        else:
            self.counters["nmt_invalid_command"] += 1

    def _on_sdo(self, msg: can.Message, now_s: float) -> None:
        if msg.is_remote_frame:
            self.counters["malformed_frames"] += 1
            return
        if self.nmt_state == NMT_STATE.STOPPED:
            self.counters["sdo_ignored_stopped"] += 1
            return
        self.sdo.on_frame(bytes(msg.data), now_s)

    def _on_guard(self, msg: can.Message, now_s: float) -> None:
        if msg.is_remote_frame:
            self.guarding.on_rtr(now_s)
        else:  # a boot-up or heartbeat on this node's own error-control COB-ID
            self._on_own_cob_id(msg, now_s)

    def _on_own_cob_id(self, msg: can.Message, _now_s: float) -> None:
        """A data frame on a COB-ID that only a node with this node-ID sends (its boot-up / heartbeat 0x700+id,
        its SDO answers 0x580+id), and this node did not send it (no bus hands a node its own frames back):
        another node on the bus has the same node-ID. Counted (0x2100, ``node_id_conflicts``); said once."""
        if msg.is_remote_frame:
            self.counters["malformed_frames"] += 1
            return
        self.counters["node_id_conflicts"] += 1
        if not self.node_id_conflict_reported:
            self.node_id_conflict_reported = True
            what = "an SDO answer" if msg.arbitration_id == self.sdo.tx_cob else "a boot-up or heartbeat"
            log.warning("node %d: another node on this bus has node-ID %d (%s on COB-ID 0x%03X that this node did "
                        "not send); both answer every SDO request and NMT command for node %d, so a master gets "
                        "two answers: give each node a node-ID of its own", self.node_id, self.node_id, what,
                        msg.arbitration_id, self.node_id)

    def _on_heartbeat(self, msg: can.Message, now_s: float) -> None:
        self.heartbeat_consumer.on_heartbeat(msg.arbitration_id, msg.data, now_s)

    def arrival_s(self, msg: can.Message, now_s: float) -> float:
        """When ``msg`` arrived on the bus, on the caller's clock: its receive timestamp (python-can gives
        ``time.time()``-based ones for virtual and udp_multicast, the kernel's for socketcan), ``now_s`` when
        the frame has none or one that does not fit the wall clock."""
        stamp = msg.timestamp
        if not stamp or not self.frame_timestamps:
            return now_s
        arrival = stamp + self._wall_to_now
        if arrival > now_s or arrival < now_s - 10.0:
            return now_s
        return arrival

    def _rx_pending(self) -> bool:
        """True while frames wait in the bus's receive socket (not yet handed to :meth:`receive`)."""
        if self._rx_fd is None:
            try:
                fd = self.bus.fileno()
            except Exception:  # noqa: BLE001 - buses without a file descriptor
                fd = -1
            self._rx_fd = fd if isinstance(fd, int) and fd >= 0 else -1
        if self._rx_fd < 0:
            return False
        try:
            return bool(select.select([self._rx_fd], [], [], 0)[0])
        except (OSError, ValueError):
            return False

    def _sync_timeout(self) -> None:
        self.counters["sync_timeouts"] += 1
        self.raise_comm_error(0x8100)
        self.communication_error("sync_timeout", 0)

    def _on_sync_frame(self, msg: can.Message, now_s: float) -> None:
        counter = self.sync.check_frame(msg.data)
        if counter is None or msg.is_remote_frame:
            self.counters["sync_length_errors"] += 1
            self.counters["malformed_frames"] += 1
            self.emcy(0x8240, 0x10, bytes((len(msg.data),)), communication=True)
            return
        self.counters["sync_received"] += 1
        if 0x8100 in self._comm_errors:  # SYNC is back (a late one raised the error: the next one clears it)
            self.clear_comm_error(0x8100)
        arrival = self.arrival_s(msg, now_s)
        if self.sync.on_arrival(arrival) and self.nmt_state == NMT_STATE.OPERATIONAL:
            self._sync_timeout()          # a gap longer than 1.5 periods the timer had not caught
        self._sync_counters.append(counter)
        self._sync_in_operational.append(self.nmt_state == NMT_STATE.OPERATIONAL)
        if self.nmt_state == NMT_STATE.OPERATIONAL and self.pdo.sync_rpdos:
            self._due_sync_rpdos.append(self.pdo.latch_sync_rpdos())
        else:
            self._due_sync_rpdos.append(_NOTHING_DUE)

    def _take_sync_counters(self) -> list[int]:
        out = self._sync_counters
        if out:
            self._sync_counters = []
        else:
            out = []
        return out


def rpdo_handler(slave: CanopenSlave, rpdo) -> Callable[[can.Message, float], None]:
    pdo = slave.pdo

    def handle(msg: can.Message, now_s: float) -> None:
        if slave.nmt_state != NMT_STATE.OPERATIONAL:
            slave.counters["pdo_ignored_nmt_state"] += 1
            return
        if msg.is_remote_frame:
            slave.counters["malformed_frames"] += 1
            return
        pdo.on_rpdo(rpdo, bytes(msg.data), now_s)

    return handle
