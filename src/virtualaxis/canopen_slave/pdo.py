"""PDO engine: 4 RPDO + 4 TPDO with dynamic mapping, transmission types 0-240/254/255, inhibit time,
event timer, SYNC start value, RPDO deadline monitoring and NMT-state gating.

Each PDO keeps a precompiled :class:`struct.Struct` for its current mapping (byte granularity, the
EDS says ``Granularity=8``), rebuilt only when its communication or mapping parameters change.
"""

from __future__ import annotations

import struct
import time
from typing import TYPE_CHECKING

from virtualaxis.canopen_slave import errors as ab
from virtualaxis.canopen_slave.cobid import restricted
from virtualaxis.canopen_slave.errors import SdoAbort
from virtualaxis.canopen_slave.od import Entry

if TYPE_CHECKING:
    from virtualaxis.canopen_slave.context import PdoNode

N_PDO = 4
RPDO_COMM, RPDO_MAP, TPDO_COMM, TPDO_MAP = 0x1400, 0x1600, 0x1800, 0x1A00
COB_INVALID = 0x80000000
COB_NO_RTR = 0x40000000
COB_EXTENDED = 0x20000000

cob_restricted = restricted   # (the restricted list lives in cobid.py, shared by every COB-ID object)


class Pdo:
    """State common to RPDOs and TPDOs."""

    def __init__(self, number: int, comm_index: int, map_index: int):
        self.number = number               # 1..4
        self.comm_index = comm_index
        self.map_index = map_index
        self.valid = False
        self.cob_id = 0
        self.trans_type = 255
        self.inhibit_s = 0.0
        self.event_s = 0.0
        self.sync_start = 0
        self.entries: list[Entry] = []
        self.packer = struct.Struct("<")
        self.length = 0

    @property
    def synchronous(self) -> bool:
        return self.trans_type <= 240


class Rpdo(Pdo):
    def __init__(self, number: int):
        super().__init__(number, RPDO_COMM + number - 1, RPDO_MAP + number - 1)
        self.pending: bytes | None = None   # synchronous RPDO data waiting for the next SYNC
        #: byte ranges (start, end) of the mapped objects that are not set-points (slave.setpoint_objects)
        self.held_bytes: tuple[tuple[int, int], ...] = ()
        self.last_rx_s: float | None = None
        self.timed_out = False


class Tpdo(Pdo):
    def __init__(self, number: int):
        super().__init__(number, TPDO_COMM + number - 1, TPDO_MAP + number - 1)
        self.dirty = False                  # a mapped value changed since the last transmission
        self.last_tx_s = -1e30
        self.held_since_wall_s: float | None = None  # (monotonic) when a change was first held by the inhibit time
        self.sync_count = 0
        self.started = False


class PdoEngine:
    """Configuration (from the OD), validation of writes to 0x1400-0x1BFF, reception and transmission."""

    def __init__(self, slave: PdoNode):
        self.slave = slave
        self.rpdos = [Rpdo(n) for n in range(1, N_PDO + 1)]
        self.tpdos = [Tpdo(n) for n in range(1, N_PDO + 1)]
        self.rpdo_by_cob: dict[int, Rpdo] = {}
        self.sync_tpdos: list[Tpdo] = []
        self.event_tpdos: list[Tpdo] = []
        self.deadline_rpdos: list[Rpdo] = []
        self.sync_rpdos: list[Rpdo] = []
        self.configure_all()

    # ------------------------------------------------------------------ configuration
    def configure_all(self) -> None:
        for pdo in self.rpdos + self.tpdos:
            self._configure(pdo)
        self._rebuild_lists()

    def _configure(self, pdo: Pdo) -> None:
        od = self.slave.od
        cob = od.value(pdo.comm_index, 1)
        pdo.valid = not cob & COB_INVALID
        pdo.cob_id = cob & 0x7FF
        pdo.trans_type = od.value(pdo.comm_index, 2)
        pdo.inhibit_s = od.value(pdo.comm_index, 3) * 100e-6 if (pdo.comm_index, 3) in od else 0.0
        pdo.event_s = od.value(pdo.comm_index, 5) * 1e-3 if (pdo.comm_index, 5) in od else 0.0
        pdo.sync_start = od.value(pdo.comm_index, 6) if (pdo.comm_index, 6) in od else 0
        for entry in pdo.entries:
            if pdo in entry.tpdos:
                entry.tpdos.remove(pdo)
        entries = []
        for sub in range(1, od.value(pdo.map_index, 0) + 1):
            entry = self._mapped_entry(od.value(pdo.map_index, sub), isinstance(pdo, Rpdo))
            if entry is not None:
                entries.append(entry)
        pdo.entries = entries
        pdo.packer = struct.Struct("<" + "".join(e.fmt or "" for e in entries))
        pdo.length = pdo.packer.size
        if isinstance(pdo, Tpdo):
            for entry in entries:
                entry.tpdos.append(pdo)
            pdo.sync_count = 0
            pdo.started = False
            pdo.dirty = True
        else:
            assert isinstance(pdo, Rpdo)
            held, offset, setpoints = [], 0, self.slave.setpoint_objects
            for entry in entries:
                size = entry.size or 0  # (what the packer takes of it: entries without a format take none)
                if (entry.index, entry.sub) not in setpoints:
                    held.append((offset, offset + size))
                offset += size
            pdo.held_bytes = tuple(held)
            pdo.pending = None
            pdo.last_rx_s = None
            pdo.timed_out = False

    def _mapped_entry(self, mapping: int, receive: bool) -> Entry | None:
        """The entry a mapping value designates, or None if it is empty or invalid (EDS defaults only)."""
        try:
            return self.check_mapping(mapping, receive)
        except SdoAbort:
            return None

    def check_mapping(self, mapping: int, receive: bool) -> Entry | None:
        """Validate one mapping entry (index << 16 | sub << 8 | bits); 0 = empty."""
        if mapping == 0:
            return None
        index, sub, bits = mapping >> 16, (mapping >> 8) & 0xFF, mapping & 0xFF
        entry = self.slave.od.entries.get((index, sub))
        if entry is None or not entry.pdo_mappable or entry.fmt is None:
            raise SdoAbort(ab.NOT_MAPPABLE, f"0x{index:04X}:{sub} cannot be mapped")
        if receive and not entry.writable or not receive and not entry.readable:
            raise SdoAbort(ab.NOT_MAPPABLE, f"0x{index:04X}:{sub} has the wrong access type for this PDO")
        if bits != entry.size * 8:
            raise SdoAbort(ab.PARAMETER_INCOMPATIBLE,
                           f"0x{index:04X}:{sub} is {entry.size * 8} bits, not {bits}")
        return entry

    def _rebuild_lists(self) -> None:
        self.rpdo_by_cob = {p.cob_id: p for p in self.rpdos if p.valid}
        self.sync_rpdos = [p for p in self.rpdos if p.valid and p.synchronous]
        self.deadline_rpdos = [p for p in self.rpdos if p.valid and p.event_s > 0]
        self.sync_tpdos = [p for p in self.tpdos if p.valid and p.synchronous]
        self.event_tpdos = [p for p in self.tpdos if p.valid and p.trans_type >= 254]
        self.slave.rebuild_dispatch()

    def owns(self, index: int) -> bool:
        return RPDO_COMM <= index < RPDO_COMM + N_PDO or RPDO_MAP <= index < RPDO_MAP + N_PDO or \
            TPDO_COMM <= index < TPDO_COMM + N_PDO or TPDO_MAP <= index < TPDO_MAP + N_PDO

    def _pdo_of(self, index: int) -> tuple[Pdo, bool]:
        """(pdo, is_mapping_object) for an index in 0x1400-0x1BFF."""
        if index < RPDO_MAP:
            return self.rpdos[index - RPDO_COMM], False
        if index < TPDO_COMM:
            return self.rpdos[index - RPDO_MAP], True
        if index < TPDO_MAP:
            return self.tpdos[index - TPDO_COMM], False
        return self.tpdos[index - TPDO_MAP], True

    # ------------------------------------------------------------------ SDO write validation
    def validate_write(self, index: int, sub: int, value: int) -> None:
        pdo, is_map = self._pdo_of(index)
        od = self.slave.od
        receive = isinstance(pdo, Rpdo)
        if is_map:
            if pdo.valid:
                raise SdoAbort(ab.DEVICE_STATE, "clear COB-ID bit 31 before changing the mapping")
            if sub == 0:
                total_bits = 0
                for s in range(1, value + 1):
                    entry = self.check_mapping(od.value(index, s), receive)
                    total_bits += entry.size * 8 if entry is not None else 0
                if total_bits > 64:
                    raise SdoAbort(ab.MAPPING_TOO_LONG, f"{total_bits} bits mapped")
            else:
                if od.value(index, 0) != 0:
                    raise SdoAbort(ab.DEVICE_STATE, "write 0 to sub-index 0 before changing entries")
                self.check_mapping(value, receive)
            return
        if sub == 1:
            if value & COB_EXTENDED:
                raise SdoAbort(ab.INVALID_VALUE, "29-bit COB-IDs are not supported")
            new_valid = not value & COB_INVALID
            cob = value & 0x7FF
            if new_valid and pdo.valid and cob != pdo.cob_id:
                raise SdoAbort(ab.INVALID_VALUE, "COB-ID change while the PDO is valid")
            if new_valid and cob_restricted(cob):
                raise SdoAbort(ab.INVALID_VALUE, f"COB-ID 0x{cob:03X} is restricted")
            if new_valid and receive and any(p.valid and p.cob_id == cob for p in self.rpdos if p is not pdo):
                raise SdoAbort(ab.INVALID_VALUE, f"COB-ID 0x{cob:03X} already used by another RPDO")
        elif sub == 2:
            if not (value <= 240 or value >= 254):
                raise SdoAbort(ab.INVALID_VALUE, f"transmission type {value} not supported")
        elif sub == 3:
            if not receive and pdo.valid and value != od.value(index, 3):
                raise SdoAbort(ab.INVALID_VALUE, "inhibit time change while the TPDO is valid")

    def after_write(self, index: int, _sub: int) -> None:
        pdo, _is_map = self._pdo_of(index)
        self._configure(pdo)
        self._rebuild_lists()

    # ------------------------------------------------------------------ reception
    def on_rpdo(self, rpdo: Rpdo, data: bytes, now_s: float) -> None:
        slave = self.slave
        counters = slave.counters
        counters["rpdo_received"] += 1
        n = len(data)
        if n < rpdo.length:
            counters["rpdo_length_errors"] += 1
            slave.communication_error("rpdo_length", rpdo.number)
            slave.emcy(0x8210, 0x10, bytes((rpdo.number,)), communication=True)
            return
        if n > rpdo.length:
            counters["rpdo_length_errors"] += 1
            slave.emcy(0x8220, 0x10, bytes((rpdo.number,)), communication=True)
            data = data[:rpdo.length]
        rpdo.last_rx_s = now_s
        if rpdo.timed_out:  # the RPDO is back: its deadline error clears (EMCY 0x0000 when none is left)
            rpdo.timed_out = False
            slave.clear_comm_error(0x8250, rpdo.number)
        if rpdo.trans_type <= 240:
            rpdo.pending = data
            return
        self.apply(rpdo, data)

    def apply(self, rpdo: Rpdo, data: bytes) -> None:
        """Store every entry of the PDO, then let the application react (its ``begin_pdo`` / ``end_pdo`` hooks
        bracket the stores: CiA 402 needs controlword + target of one RPDO together)."""
        values = rpdo.packer.unpack(data)
        slave = self.slave
        slave.hook_begin_pdo()
        try:
            slave.store_all_from_pdo(rpdo.entries, values)
        finally:
            slave.hook_end_pdo()

    def latch_sync_rpdos(self) -> list[tuple[Rpdo, bytes]]:
        """At a SYNC: take the synchronous RPDO data received before it (applied by ``on_sync``)."""
        due = []
        for rpdo in self.sync_rpdos:
            if rpdo.pending is not None:
                due.append((rpdo, rpdo.pending))
                rpdo.pending = None
        return due

    # ------------------------------------------------------------------ transmission
    def _transmit(self, tpdo: Tpdo, now_s: float) -> None:
        try:
            data = tpdo.packer.pack(*[e.value for e in tpdo.entries])
        except (struct.error, TypeError):
            data = b"".join(e.encode(_clamp(e)) for e in tpdo.entries)
            self.slave.counters["internal_errors"] += 1
        self.slave.send(tpdo.cob_id, data)
        self.slave.counters["tpdo_sent"] += 1
        tpdo.last_tx_s = now_s
        tpdo.dirty = False
        tpdo.held_since_wall_s = None

    @staticmethod
    def _cyclic_due(tpdo, counter: int, counter_enabled: bool) -> bool:
        """Count this SYNC for a cyclic TPDO (transmission type 1..240, started at its SYNC start value when
        the counter is enabled); True when its transmission falls on this SYNC."""
        if tpdo.sync_start and counter_enabled and not tpdo.started:
            if counter != tpdo.sync_start:
                return False
            tpdo.started = True
            tpdo.sync_count = 0
        tpdo.sync_count += 1
        if tpdo.sync_count >= tpdo.trans_type:
            tpdo.sync_count = 0
            return True
        return False

    def on_sync(self, counter: int, counter_enabled: bool, now_s: float) -> None:
        for tpdo in self.sync_tpdos:
            if tpdo.trans_type == 0:
                if tpdo.dirty:
                    self._transmit(tpdo, now_s)
            elif self._cyclic_due(tpdo, counter, counter_enabled):
                self._transmit(tpdo, now_s)

    def poll(self, now_s: float) -> None:
        """Event-driven TPDOs (change + inhibit time, event timer) and RPDO deadlines; OPERATIONAL only."""
        for tpdo in self.event_tpdos:
            if tpdo.dirty:
                if now_s - tpdo.last_tx_s >= tpdo.inhibit_s or self._inhibit_passed_on_the_wall(tpdo):
                    self._transmit(tpdo, now_s)
            elif tpdo.event_s > 0.0 and now_s - tpdo.last_tx_s >= tpdo.event_s:
                self._transmit(tpdo, now_s)
        for rpdo in self.deadline_rpdos:
            if rpdo.last_rx_s is not None and not rpdo.timed_out and now_s - rpdo.last_rx_s > rpdo.event_s:
                rpdo.timed_out = True
                self.slave.counters["rpdo_timeouts"] += 1
                self.slave.raise_comm_error(0x8250, rpdo.number, bytes((rpdo.number,)))
                self.slave.communication_error("rpdo_timeout", rpdo.number)

    @staticmethod
    def _inhibit_passed_on_the_wall(tpdo: Tpdo) -> bool:
        """The inhibit time is a minimum gap between frames on the bus: a change it holds goes out once the
        inhibit time has passed since the change was first held, on the wall clock too. (In SYNC lockstep the
        node's clock is the drive's, which stands still between SYNCs: a statusword change made by an SDO write
        between two SYNCs would otherwise wait for the next SYNC.)"""
        held = tpdo.held_since_wall_s
        now = time.monotonic()
        if held is None:
            tpdo.held_since_wall_s = now
            return False
        return now - held >= tpdo.inhibit_s

    def on_operational(self) -> None:
        """Entering OPERATIONAL: every event-driven TPDO is sent once, SYNC counting restarts."""
        for tpdo in self.tpdos:
            tpdo.dirty = True
            tpdo.sync_count = 0
            tpdo.started = False
            tpdo.last_tx_s = -1e30
        for rpdo in self.rpdos:  # (a deadline error still active stays so until its RPDO comes: ``timed_out``)
            rpdo.pending = None
            rpdo.last_rx_s = None


def _clamp(entry: Entry):
    """A value the entry's type can encode (used only when the application stored a wrong type)."""
    value = entry.value
    if entry.fmt in ("f", "d"):
        try:
            return float(value)
        except (TypeError, ValueError):
            return 0.0
    try:
        value = int(value)
    except (TypeError, ValueError):
        return 0
    bits = entry.size * 8
    if entry.fmt.islower():
        return max(-(1 << (bits - 1)), min((1 << (bits - 1)) - 1, value))
    return max(0, min((1 << bits) - 1, value))
