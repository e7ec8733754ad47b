"""EMCY producer: COB-ID 0x1014, inhibit time 0x1015 (delayed, never dropped up to a queue limit),
error register 0x1001, pre-defined error field 0x1003 (newest first, sub 0 = count, write 0 to clear)."""

from __future__ import annotations

import struct
from collections import deque
from typing import TYPE_CHECKING

from virtualaxis.canopen_slave import errors as ab
from virtualaxis.canopen_slave.errors import SdoAbort

if TYPE_CHECKING:
    from virtualaxis.canopen_slave.context import NodeContext

ERROR_FIELD = 0x1003
HISTORY_LENGTH = 8
PENDING_LIMIT = 16
COB_INVALID = 0x80000000


class EmcyProducer:
    def __init__(self, slave: NodeContext):
        self.slave = slave
        self.pending: deque[bytes] = deque()
        self.last_tx_s = -1e30

    def reset(self) -> None:
        self.pending.clear()
        self.last_tx_s = -1e30

    def validate_write(self, index: int, sub: int, value: int) -> None:
        od = self.slave.od
        if index == ERROR_FIELD and sub == 0 and value != 0:
            raise SdoAbort(ab.INVALID_VALUE, "only 0 may be written to 0x1003:0 (clears the history)")
        if index == 0x1014 and sub == 0:
            current = od.value(0x1014)
            if value & 0x20000000:
                raise SdoAbort(ab.INVALID_VALUE, "29-bit COB-IDs are not supported")
            if not current & COB_INVALID and not value & COB_INVALID and (value & 0x7FF) != (current & 0x7FF):
                raise SdoAbort(ab.INVALID_VALUE, "EMCY COB-ID change while valid")

    def after_write(self, index: int, sub: int) -> None:
        if index == ERROR_FIELD and sub == 0:
            for s in range(1, HISTORY_LENGTH + 1):
                self.slave.od.entries[(ERROR_FIELD, s)].value = 0

    def push_history(self, code: int, info: int = 0) -> None:
        entries = self.slave.od.entries
        if (ERROR_FIELD, 1) not in entries:
            return
        for s in range(HISTORY_LENGTH, 1, -1):
            entries[(ERROR_FIELD, s)].value = entries[(ERROR_FIELD, s - 1)].value
        entries[(ERROR_FIELD, 1)].value = (code & 0xFFFF) | ((info & 0xFFFF) << 16)
        count = entries[(ERROR_FIELD, 0)]
        count.value = min(count.value + 1, HISTORY_LENGTH)

    def produce(self, code: int, register: int, data: bytes, now_s: float) -> None:
        frame = struct.pack("<HB", code & 0xFFFF, register & 0xFF) + bytes(data[:5]).ljust(5, b"\x00")
        inhibit_s = self.slave.od.value(0x1015) * 100e-6
        if self.pending or now_s - self.last_tx_s < inhibit_s:
            self.slave.counters["emcy_inhibited"] += 1
            if len(self.pending) < PENDING_LIMIT:
                self.pending.append(frame)
            return
        self._send(frame, now_s)

    def poll(self, now_s: float) -> None:
        if self.pending and now_s - self.last_tx_s >= self.slave.od.value(0x1015) * 100e-6:
            self._send(self.pending.popleft(), now_s)

    def _send(self, frame: bytes, now_s: float) -> None:
        cob = self.slave.od.value(0x1014)
        self.last_tx_s = now_s
        if cob & COB_INVALID:
            return
        self.slave.send(cob & 0x7FF, frame)
        self.slave.counters["emcy_sent"] += 1
