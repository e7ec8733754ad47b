"""The last EMCY frames and SDO aborts the served nodes sent, for the live page (a bus wrapper notes them)."""

from __future__ import annotations

import collections
import time

import can

from virtualaxis.services.wrapped_bus import WrappedBus

EMCY_COBS = range(0x81, 0x100)
SDO_TX_COBS = range(0x581, 0x600)
SDO_ABORT_CCS = 0x80


class FrameLog:
    """The newest ``size`` EMCY frames and SDO aborts (a deque: appended by the runtime thread, read by the page)."""

    def __init__(self, size: int = 32):
        self.events: collections.deque = collections.deque(maxlen=size)
        self.t0 = time.monotonic()

    def note(self, cob_id: int, data: bytes) -> None:
        """A frame sent by a served node: kept if it is an EMCY or an SDO abort."""
        if cob_id in EMCY_COBS:
            self.events.append(("emcy", cob_id - 0x80, time.monotonic(), bytes(data)))
        elif cob_id in SDO_TX_COBS and data and data[0] == SDO_ABORT_CCS:
            self.events.append(("sdo_abort", cob_id - 0x580, time.monotonic(), bytes(data)))

    def for_node(self, node_id: int) -> list[dict]:
        """The events of ``node_id``, newest first, decoded (JSON-ready)."""
        from virtualaxis.drive.faults import fault_info

        now = time.monotonic()
        out = []
        for kind, node, t, data in reversed(tuple(self.events)):
            if node != node_id:
                continue
            ev: dict = {"kind": kind, "age_s": round(now - t, 3), "data": data.hex(" ")}
            if kind == "emcy" and len(data) >= 3:
                code = int.from_bytes(data[:2], "little")
                ev |= {"emcy_code": f"0x{code:04X}", "error_register": f"0x{data[2]:02X}",
                       "text": "error reset / no error" if code == 0 else fault_info(code).text}
            elif kind == "sdo_abort" and len(data) >= 8:
                ev |= {"object": f"0x{int.from_bytes(data[1:3], 'little'):04X}:{data[3]}",
                       "abort_code": f"0x{int.from_bytes(data[4:8], 'little'):08X}"}
            out.append(ev)
        return out


class FrameLogBus(WrappedBus):
    """A bus wrapper that notes the EMCY frames and SDO aborts sent through it (everything passes through)."""

    def __init__(self, inner: can.BusABC, log: FrameLog):
        self.log = log
        super().__init__(inner)

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        self.inner.send(msg, timeout)
        cob = msg.arbitration_id
        if 0x80 < cob < 0x600 and not msg.is_extended_id and (cob < 0x100 or cob > 0x580):
            self.log.note(cob, msg.data)
