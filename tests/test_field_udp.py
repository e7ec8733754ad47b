"""Issue #15 across processes: ``virtualaxis serve`` in a child process, a ``canopen`` master here, on
python-can ``udp_multicast`` (hop_limit 0, loopback only; the master's bus filters out its own frames, see
virtualaxis.master.connect). Controlword + target in one RPDO, a fault reaction from the actual speed with its
statusword sequence on the TPDO, and NMT Stop as a loss of control (0x6007).

The frame log of these runs (``VA_FRAME_LOG=path``) is the excerpt shown in docs/drive.md."""

from __future__ import annotations

import os
import threading
import time

import can
import canopen
import pytest
from served_drive import served

from virtualaxis.drive.core import DEFAULT_EDS
from virtualaxis.master import connect

pytestmark = pytest.mark.exclusive  # timing-sensitive: background jobs stopped meanwhile

NODE = 1
UNIT_M = 1e-6


class FrameLog(can.Listener):
    """Every frame the master sees, candump style (time relative to the first)."""

    def __init__(self) -> None:
        self.frames: list[can.Message] = []
        self._lock = threading.Lock()

    def on_message_received(self, msg: can.Message) -> None:
        with self._lock:
            self.frames.append(msg)

    def send(self, net: canopen.Network, cob_id: int, data: bytes) -> None:
        """Send a frame and log it (the master's bus does not hand its own frames back)."""
        self.on_message_received(can.Message(timestamp=time.time(), arbitration_id=cob_id, data=data,
                                             is_extended_id=False))
        net.send_message(cob_id, data)

    def of(self, cob_id: int) -> list[can.Message]:
        with self._lock:
            return [m for m in self.frames if m.arbitration_id == cob_id]

    def text(self, since: float, cob_ids: set[int]) -> str:
        with self._lock:
            lines = [
                f"({m.timestamp - since:9.4f})  {m.arbitration_id:03X}   [{len(m.data)}]  {m.data.hex(' ')}"
                for m in self.frames
                if m.timestamp >= since and m.arbitration_id in cob_ids
            ]
        return "\n".join(lines)


def _master(spec: str) -> tuple[canopen.Network, canopen.BaseNode402, FrameLog]:
    net = connect(spec)
    log = FrameLog()
    net.notifier.add_listener(log)
    node = canopen.BaseNode402(NODE, str(DEFAULT_EDS))
    node.sdo.RESPONSE_TIMEOUT = 2.0
    net.add_node(node)
    return net, node, log


def _enable(node: canopen.BaseNode402) -> None:
    for cw, expect in ((0x06, 0x21), (0x07, 0x23), (0x0F, 0x27)):
        node.sdo[0x6040].raw = cw
        end = time.monotonic() + 2
        while node.sdo[0x6041].raw & 0x6F != expect:
            assert time.monotonic() < end, hex(node.sdo[0x6041].raw)
            time.sleep(0.005)


def _wait(predicate, timeout: float = 5.0):
    end = time.monotonic() + timeout
    while not (value := predicate()):
        assert time.monotonic() < end, "condition not reached in time"
        time.sleep(0.01)
    return value


def test_rpdo_target_and_fault_reaction_across_processes():
    """CW new-set-point + 0x607A = 35000 in the default RPDO2 moves to 35000; then PV at 100 mm/s and an
    injected 0x4210 (0x605E = 2, 0x6085 = 10 m/s^2): TPDO1 shows 0x0237 -> 0x023F (fault reaction active)
    -> 0x0238 (fault), EMCY 0x4210, and the axis brakes in ~v^2/2a (0.5 mm; before: 11 mm of coasting)."""
    with served("--duration", "60", "--allow-fault-injection") as s:
        net, node, log = _master(s.spec)
        try:
            node.nmt.state = "OPERATIONAL"
            node.sdo[0x6060].raw = 1
            node.sdo[0x6081].raw = 200_000
            node.sdo[0x6083].raw = 2_000_000
            node.sdo[0x6084].raw = 2_000_000
            node.sdo[0x6085].raw = 10_000_000
            node.sdo[0x605E].raw = 2
            _enable(node)
            t0 = time.time()
            log.send(net, 0x300 + NODE, bytes([0x1F, 0x00, 0xB8, 0x88, 0x00, 0x00]))
            time.sleep(0.05)
            log.send(net, 0x300 + NODE, bytes([0x0F, 0x00, 0xB8, 0x88, 0x00, 0x00]))
            _wait(lambda: node.sdo[0x6041].raw & 0x400 and abs(node.sdo[0x6064].raw - 35_000) < 50)
            move_log = log.text(t0 - 0.001, {0x300 + NODE, 0x180 + NODE})
            # fault reaction from 100 mm/s
            node.sdo[0x6060].raw = 3
            node.sdo[0x60FF].raw = 100_000
            _wait(lambda: abs(node.sdo[0x606C].raw - 100_000) < 2_000)
            t1 = time.time()
            x0 = node.sdo[0x6064].raw
            node.sdo[0x2010].raw = 0x4210
            _wait(lambda: node.sdo[0x6041].raw & 0x6F == 0x28)
            time.sleep(0.2)
            travel_mm = (node.sdo[0x6064].raw - x0) * UNIT_M * 1e3
            assert travel_mm < 2.0, travel_mm  # 0.5 mm ramp + SDO round trips at 100 mm/s
            sws = [int.from_bytes(m.data[0:2], "little") for m in log.of(0x180 + NODE) if m.timestamp >= t1]
            seq = [sw & 0x6F for i, sw in enumerate(sws) if i == 0 or sw != sws[i - 1]]
            assert 0x2F in seq and seq.index(0x2F) < seq.index(0x28), [hex(x) for x in seq]
            emcy = [m for m in log.of(0x80 + NODE) if m.timestamp >= t1]
            assert any(int.from_bytes(m.data[0:2], "little") == 0x4210 for m in emcy)
            fault_log = log.text(t1 - 0.001, {0x80 + NODE, 0x180 + NODE})
            path = os.environ.get("VA_FRAME_LOG")
            if path:
                with open(path, "w") as f:
                    f.write(move_log + "\n----\n" + fault_log + "\n")
        finally:
            net.disconnect()
    assert s.returncode == 0, s.stderr[-2000:]


def test_nmt_stop_while_moving_is_a_loss_of_control_across_processes():
    """0x6007 = 1, PV at 50 mm/s, NMT Stop: the drive faults (0x8131) and brakes; after NMT Start the master
    reads FAULT and the axis at rest (before: kept moving, 26 mm in 0.5 s)."""
    with served("--duration", "60", "--allow-fault-injection") as s:
        net, node, _log = _master(s.spec)
        try:
            node.nmt.state = "OPERATIONAL"
            node.sdo[0x6060].raw = 3
            node.sdo[0x6007].raw = 1
            node.sdo[0x6083].raw = 2_000_000
            node.sdo[0x6085].raw = 2_000_000
            _enable(node)
            node.sdo[0x60FF].raw = 50_000
            _wait(lambda: abs(node.sdo[0x606C].raw - 50_000) < 2_000)
            x0 = node.sdo[0x6064].raw
            node.nmt.state = "STOPPED"
            time.sleep(0.5)
            node.nmt.state = "OPERATIONAL"
            time.sleep(0.05)
            assert node.sdo[0x6041].raw & 0x6F == 0x28
            assert node.sdo[0x603F].raw == 0x8131
            x1 = node.sdo[0x6064].raw
            time.sleep(0.1)
            # at rest: within 2 units (2 um) in 0.1 s, i.e. below 0.02 mm/s. Not "equal": at rest the measured
            # position dithers by +/-0.4 um in encoder steps of 0.12 um (seen in process: 15035.77..15036.62 um
            # over 0.4 s after the same stop), which can flip the rounding of 0x6064 by one unit (CI10: 1840 -> 1841)
            assert abs(node.sdo[0x6064].raw - x1) <= 2, (x1, node.sdo[0x6064].raw)
            # ramp 0.6 mm + the time between the SDO read of x0 and the NMT frame (a loaded host: tens of ms)
            assert (x1 - x0) * UNIT_M * 1e3 < 10.0
        finally:
            net.disconnect()
    assert s.returncode == 0, s.stderr[-2000:]
