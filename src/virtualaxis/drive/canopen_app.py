"""The CiA 402 device application: plugs a :class:`~virtualaxis.drive.core.Drive` into a CiA 301
:class:`~virtualaxis.canopen_slave.CanopenSlave` (the ``DeviceApplication`` hooks of docs/canopen-slave-api.md).

- ``validate_write`` -> :meth:`Drive.check_object_write`; a refusal becomes the SDO abort code (an RPDO value
  refused is dropped and counted by the stack).
- ``after_write`` -> :meth:`Drive.write_object` (controlword, mode, targets, parameters take effect at once).
- The drive's changed objects (statusword, actual values, ...) are copied into the slave's dictionary by
  :meth:`Cia402Application.flush`, which the runtime calls after every drive cycle and every poll, and which
  the hooks call before an SDO upload and after a write.
- EMCY: the drive's faults go out through ``slave.emcy`` (0x1001, 0x1003, 0x603F kept by the stack), a
  fault reset through ``slave.emcy_reset``.
- NMT reset node: the drive restarts (application objects to defaults, state machine to switch on disabled).
"""

from __future__ import annotations

from virtualaxis.canopen_slave import CanopenSlave, NmtState, SdoAbort
from virtualaxis.drive.core import ALIASES, Drive, ObjectAccessError
from virtualaxis.drive.objects import SPECS


class Cia402Application:
    """The bridge between one :class:`Drive` and one :class:`CanopenSlave`."""

    def __init__(self, drive: Drive):
        self.drive = drive
        self.slave: CanopenSlave | None = None
        self._entries: dict = {}
        self.nmt_state: NmtState | None = None

    def attach(self, slave: CanopenSlave) -> None:
        """Connect to the slave (call before ``slave.boot``)."""
        self.slave = slave
        self.drive.emcy_sink = slave.emcy
        self.drive.emcy_reset_sink = slave.emcy_reset
        self._entries = {key: slave.entry(*key) for key in list(SPECS) + list(ALIASES) if key in slave.od.entries}
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
        for key, value in derived.items():
            drive._store(key, value)
        self.flush(everything=True)

    def flush(self, everything: bool = False) -> None:
        """Copy the drive's changed objects into the slave's dictionary (marks event-driven TPDOs)."""
        slave = self.slave
        if slave is None:
            return
        changes = self.drive.take_changes()
        if everything:
            changes = [(k[0], k[1], v) for k, v in self.drive.objects.items()]
            for alias, target in ALIASES.items():
                changes.append((alias[0], alias[1], self.drive.objects[target]))
        entries = self._entries
        for index, sub, value in changes:
            entry = entries.get((index, sub))
            if entry is not None:
                slave.write_entry(entry, float(value) if entry.fmt in ("f", "d") else value)

    # ------------------------------------------------------------------ DeviceApplication hooks
    def validate_write(self, index: int, sub: int, value) -> None:
        if (index, sub) in SPECS or (index, sub) in ALIASES:
            try:
                self.drive.check_object_write(index, sub, value)
            except ObjectAccessError as exc:
                raise SdoAbort(exc.code, str(exc)) from None

    def after_write(self, index: int, sub: int, value) -> None:
        if (index, sub) in SPECS or (index, sub) in ALIASES:
            self.drive.write_object(index, sub, value, checked=True)
            self.flush()

    def before_read(self, index: int, sub: int) -> None:
        self.flush()

    def on_nmt_state(self, state: NmtState) -> None:
        self.nmt_state = state

    def on_communication_error(self, kind: str, detail: int) -> None:
        self.drive.communication_error(kind, detail)
        self.flush()

    def on_reset(self, application: bool) -> None:
        if application:
            self.drive.power_on_reset()
            self._sync_from_slave()
