"""The CiA 402 device application: plugs a :class:`~virtualaxis.drive.core.Drive` into a CiA 301
:class:`~virtualaxis.canopen_slave.CanopenSlave` (the ``CanopenApplication`` hooks of docs/canopen-slave-api.md).

- ``validate_write`` -> :meth:`Drive.check_object_write`; a refusal becomes the SDO abort code (an RPDO value
  refused is dropped and counted by the stack).
- ``after_write`` -> :meth:`Drive.write_object` (controlword, mode, targets, parameters take effect at once).
- The drive's per-cycle actual values go into the slave's dictionary as the cycle publishes them
  (:meth:`ObjectTable.mirror_outputs <virtualaxis.drive.object_table.ObjectTable.mirror_outputs>`); its other
  changed objects (statusword, parameters, ...) are copied by :meth:`Cia402Application.flush`, which the
  runtime calls after every drive cycle and every poll, and which the hooks call before an SDO upload and after
  a write.
- EMCY: the drive's faults go out through ``slave.emcy`` (0x1001, 0x1003, 0x603F kept by the stack), the
  error reset through ``slave.emcy_reset``; when an error goes while others remain, the drive sets 0x603F
  (an object of its own) and the application's bits of 0x1001 (:meth:`Cia402Application.set_error_register`).
- NMT reset node: the drive restarts (application objects to defaults, state machine to switch on disabled).
"""

from __future__ import annotations

from virtualaxis.canopen_slave import BaseApplication, CanopenSlave, NmtState, SdoAbort
from virtualaxis.canopen_slave.nmt import NMT_STATE
from virtualaxis.drive.core import ALIASES, OUTPUT_KEYS, Drive, ObjectAccessError
from virtualaxis.drive.objects import SPECS

#: SYNC loss = this many communication cycles (0x1006) of drive time without SYNC ...
SYNC_LOSS_PERIODS = 5
#: ... and at least this long [s] (chosen: a busy host delays a SYNC by a few ms, rarely by tens of ms)
SYNC_LOSS_MIN_S = 0.050
#: the error code object: the drive's newest error, which the stack completes with its communication errors
ERROR_CODE_KEY = (0x603F, 0)
#: the objects the drive serves (its own and the manufacturer aliases)
_DRIVE_KEYS = frozenset(SPECS) | frozenset(ALIASES)


class Cia402Application(BaseApplication):
    """The bridge between one :class:`Drive` and one :class:`CanopenSlave`."""

    #: objects whose write only sets a value that the next write replaces (targets and offsets, no edge
    #: semantics): a SYNC's RPDO that changes nothing else may be left out when the next SYNC's replaces it
    #: (``CanopenSlave.skip_sync``, a lockstep host that gives up cycles)
    setpoint_objects = frozenset({(0x607A, 0), (0x60FF, 0), (0x6071, 0), (0x60B0, 0), (0x60B1, 0), (0x60B2, 0)})

    def __init__(self, drive: Drive):
        self.drive = drive
        self._table = drive.object_table  # (the drive's for its life: read by every flush)
        self._counters = drive.counters
        self.slave: CanopenSlave | None = None
        self._entries: dict = {}
        self._float_keys: frozenset = frozenset()
        self.nmt_state: NmtState | None = None
        self._batch: list[tuple[int, int, int | float]] | None = None  # RPDO entries being stored
        self._syncs_seen = 0
        self._cycles_at_sync = 0
        self._cycles_watched = -1
        self._sync_loss_reported = False
        #: (SYNC timeout, drive cycle) -> drive cycles without SYNC that make a SYNC loss (see :func:`sync_loss_cycles`)
        self._loss_key: tuple[float, float] | None = None
        self._loss_cycles: int | None = None

    def attach(self, slave: CanopenSlave) -> None:
        """Connect to the slave (call before ``slave.boot``)."""
        self.slave = slave
        self.drive.emcy_sink = slave.emcy
        self.drive.emcy_reset_sink = slave.emcy_reset
        self.drive.error_register_sink = self.set_error_register
        self._entries = {key: slave.entry(*key) for key in list(SPECS) + list(ALIASES) if key in slave.od.entries}
        #: keys whose OD entry is a REAL32/REAL64 (the drive may hold an int there)
        self._float_keys = frozenset(key for key, entry in self._entries.items() if entry.fmt in ("f", "d"))
        # the drive's per-cycle outputs go into their OD entries (None: not in the EDS) as the cycle publishes them
        self._table.mirror_outputs([self._entries.get(key) for key in OUTPUT_KEYS],
                                   [key in self._float_keys for key in OUTPUT_KEYS])
        self._sync_from_slave()

    def missing_objects(self) -> list[tuple[int, int]]:
        """Drive objects the slave's dictionary (the EDS) does not serve."""
        return [key for key in SPECS if key not in self._entries]

    def _sync_from_slave(self) -> None:
        """After boot / reset: parameters from the OD (EDS defaults or restored), config-derived ones back."""
        drive = self.drive
        derived = drive.derived_objects()
        values = {key: entry.value for key, entry in self._entries.items() if key not in derived}
        drive.load_objects(values)
        drive.store_objects(derived)
        self.flush(everything=True)

    def flush(self, everything: bool = False) -> None:
        """Copy the drive's changed objects into the slave's dictionary (marks event-driven TPDOs)."""
        slave = self.slave
        if slave is None:
            return
        table = self._table
        cycles = self._counters["cycles"]
        if cycles != self._cycles_watched or slave.counters["sync_received"] != self._syncs_seen:
            self._cycles_watched = cycles  # (nothing to watch while neither the drive nor the SYNCs moved)
            self._watch_sync(slave)
        drive = self.drive
        if everything:
            drive.take_changed()
            objects = drive.objects
            changes = [(key, objects[ALIASES.get(key, key)]) for key in self._entries]
        elif not table.changed():  # the common case of the several flushes per cycle
            return
        else:
            changes = drive.take_changed()
        float_keys = self._float_keys
        for key, value in changes:  # (few per cycle: the outputs went in as the cycle published them)
            entry = self._entries.get(key)
            if entry is None:
                continue
            if key == ERROR_CODE_KEY:  # (0 with a communication error active: the stack shows that one's code)
                slave.set_application_error_code(int(value))
                continue
            slave.write_entry(entry, float(value) if key in float_keys else value)

    # ------------------------------------------------------------------ CanopenApplication hooks
    def validate_write(self, index: int, sub: int, value) -> None:
        if (index, sub) in _DRIVE_KEYS:
            try:
                self.drive.check_object_write(index, sub, value)
            except ObjectAccessError as exc:
                raise SdoAbort(exc.code, str(exc)) from None

    def begin_pdo(self) -> None:
        """An RPDO is being stored: collect its drive objects (see :meth:`end_pdo`)."""
        self._batch = []

    def end_pdo(self) -> None:
        """All entries of the RPDO are stored: the drive reacts to them together (controlword + target)."""
        batch, self._batch = self._batch, None
        if batch:
            self.drive.write_objects(batch, checked=True)
            self.flush()

    def after_write(self, index: int, sub: int, value) -> None:
        if (index, sub) in _DRIVE_KEYS:
            if self._batch is not None:
                self._batch.append((index, sub, value))
                return
            try:
                self.drive.write_object(index, sub, value, checked=True)
            except ObjectAccessError as exc:  # stored, but what it carried was refused (e.g. a set-point)
                self.flush()
                raise SdoAbort(exc.code, str(exc)) from None
            self.flush()

    def before_read(self, index: int, sub: int) -> None:
        self.flush()

    def on_nmt_state(self, state: NmtState) -> None:
        """NMT Stopped while the drive is enabled is a loss of control (0x6007, CiA 402)."""
        self.nmt_state = state
        if state == NMT_STATE.STOPPED:
            self.drive.communication_error("nmt_stopped", 0)
            self.flush()

    def _watch_sync(self, slave: CanopenSlave) -> None:
        """SYNC loss as the drive sees it: after a SYNC has been seen in OPERATIONAL with 0x1006 set, the
        drive ran :data:`SYNC_LOSS_PERIODS` communication cycles (at least :data:`SYNC_LOSS_MIN_S`) of its
        own time without one -> ``communication_error("sync_loss")`` once (0x6007 in the CS modes). In SYNC
        lockstep the drive never runs more than one period without SYNC; a late SYNC on a busy machine (the
        stack's 1.5-period EMCY 0x8100) is not yet a loss of control."""
        cycles = self.drive.counters["cycles"]
        syncs = slave.counters["sync_received"]
        if syncs != self._syncs_seen:
            self._syncs_seen = syncs
            self._cycles_at_sync = cycles
            self._sync_loss_reported = False
            return
        if self._sync_loss_reported or slave.nmt_state != NMT_STATE.OPERATIONAL or not syncs:
            return
        timeout_s, cycle_s = slave.sync.timeout_s, self.drive.cycle_s
        if (timeout_s, cycle_s) != self._loss_key:
            self._loss_key = (timeout_s, cycle_s)
            self._loss_cycles = sync_loss_cycles(timeout_s, cycle_s)
        if self._loss_cycles is not None and cycles - self._cycles_at_sync >= self._loss_cycles:
            self._sync_loss_reported = True
            self.drive.communication_error("sync_loss", 0)

    def set_error_register(self, register_bits: int) -> None:
        """0x1001 = ``register_bits`` (the generic and class bits of the drive's errors still active) and the
        communication bit the stack keeps for its own errors; no EMCY (errors remain)."""
        slave = self.slave
        if slave is not None:
            slave.write(0x1001, 0, (register_bits | (int(slave.read(0x1001)) & 0x10)) & 0xFF)

    def has_error(self) -> bool:
        """The drive is in FAULT / FAULT REACTION ACTIVE or has a warning (the stack keeps 0x1001 set)."""
        return self.drive.cia402_state.name.startswith("FAULT") or bool(self.drive.warnings)

    def on_communication_error(self, kind: str, detail: int) -> None:
        self.drive.communication_error(kind, detail)
        self.flush()

    def on_reset(self, application: bool) -> None:
        """NMT Reset Node: the drive restarts (power-on reset, plant back inside the stroke); Reset
        Communication while enabled: loss of control (0x6007)."""
        if not application:
            self.drive.communication_error("nmt_reset_communication", 0)
            self.flush()
        if application:
            self.drive.power_on_reset()
            self._sync_from_slave()


def sync_loss_cycles(timeout_s: float, cycle_s: float) -> int | None:
    """The fewest drive cycles ``k`` whose run time ``k * cycle_s`` exceeds the SYNC-loss time (the larger of
    :data:`SYNC_LOSS_PERIODS` communication cycles, 0x1006 = ``timeout_s`` / 1.5, and :data:`SYNC_LOSS_MIN_S`),
    with the same floating-point comparison as ``k * cycle_s > limit`` (monotone in ``k``); ``None`` without
    SYNC monitoring (``timeout_s`` 0) or without a drive cycle."""
    period_s = timeout_s / 1.5
    if period_s <= 0.0 or not cycle_s > 0.0:
        return None
    limit_s = max(SYNC_LOSS_PERIODS * period_s, SYNC_LOSS_MIN_S)
    k = max(0, int(limit_s / cycle_s) - 1)
    while not k * cycle_s > limit_s:
        k += 1
    while k > 0 and (k - 1) * cycle_s > limit_s:
        k -= 1
    return k
