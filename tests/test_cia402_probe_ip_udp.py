"""Change on set-point, interpolated position, polarity and the touch probe with the drive served by
``virtualaxis serve --lockstep`` in another process and a ``canopen`` master here (udp_multicast, hop_limit 0)."""

from __future__ import annotations

import time
from collections.abc import Iterator

import canopen
import pytest
from nmt_wait import reset_and_wait_for_bootup
from served_drive import served

from virtualaxis.drive.core import DEFAULT_EDS
from virtualaxis.master import connect

NODE = 1


class Master:
    """A master on the served drive's bus: SDO access and SYNCs (each handled before the next read)."""

    def __init__(self, spec: str) -> None:
        self.net = connect(spec)
        self.node = canopen.BaseNode402(NODE, str(DEFAULT_EDS))
        self.node.sdo.RESPONSE_TIMEOUT = 2.0
        self.net.add_node(self.node)

    def sync(self, n: int = 1) -> None:
        """``n`` SYNCs, each sent once the drive has run the one before (its cycle counter 0x2110:5: a lockstep
        drive skips a SYNC that comes while it still runs the last one)."""
        count = self.node.sdo[0x2110][5].raw
        for _ in range(n):
            self.net.sync.transmit()
            end = time.monotonic() + 10
            while self.node.sdo[0x2110][5].raw < count + 1:
                assert time.monotonic() < end, "the served drive did not run the SYNC"
            count += 1

    def sw(self) -> int:
        return self.node.sdo[0x6041].raw

    def wait_sync(self, predicate, max_syncs: int = 3000, step: int = 5) -> None:
        for _ in range(0, max_syncs, step):
            if predicate():
                return
            self.sync(step)
        raise AssertionError("condition not reached")

    def enable(self, mode: int) -> None:
        sdo = self.node.sdo
        reset_and_wait_for_bootup(self.node, 10.0)  # the drive's power-on state: every test starts from the defaults
        self.node.nmt.state = "OPERATIONAL"
        sdo[0x6060].raw = mode
        for cw, expect in ((0x06, 0x21), (0x07, 0x23), (0x0F, 0x27)):
            sdo[0x6040].raw = cw
            assert sdo[0x6041].raw & 0x6F == expect


@pytest.fixture(scope="module")
def master() -> Iterator[Master]:
    with served("--lockstep") as s:
        m = Master(s.spec)
        try:
            yield m
        finally:
            m.net.disconnect()


def test_change_on_setpoint_across_processes(master):
    """PP bit 9: the axis passes the first target (20 mm) at its profile velocity and stops at the second."""
    sdo = master.node.sdo
    master.enable(1)
    sdo[0x6081].raw = 100_000
    sdo[0x607A].raw = 20_000
    sdo[0x6040].raw = 0x21F
    sdo[0x6040].raw = 0x20F
    master.sync(5)
    sdo[0x607A].raw = 30_000
    sdo[0x6040].raw = 0x21F
    sdo[0x6040].raw = 0x20F
    speeds = []
    for _ in range(400):
        master.sync(5)
        x = sdo[0x6064].raw
        if 15_000 <= x <= 20_000:
            speeds.append(sdo[0x606C].raw)
        if x > 20_000:
            break
    assert speeds and min(speeds) > 90_000, speeds
    master.wait_sync(lambda: master.sw() & 0x400)
    assert abs(sdo[0x6064].raw - 30_000) <= sdo[0x6067].raw


def test_interpolated_position_across_processes(master):
    """IP: controlword + 0x60C1:1 in a synchronous RPDO, one record per 1 ms SYNC, 0x60C2 = 2 ms: a record sent
    before bit 4 is ignored; bit 12 once bit 4 is set, and the record of that frame is the first point; each
    record is a 2 ms straight segment from the previous one (100 units per cycle for records 200 apart); records
    that come faster than that wait in the buffer."""
    sdo, net = master.node.sdo, master.net
    master.enable(7)
    sdo[0x6040].raw = 0x0F
    cob = 0x200 + NODE
    sdo[0x1400][1].raw = cob | 0x80000000  # RPDO1: controlword + 0x60C1:1, synchronous
    sdo[0x1600][0].raw = 0
    sdo[0x1600][1].raw = 0x60400010
    sdo[0x1600][2].raw = 0x60C10120
    sdo[0x1600][0].raw = 2
    sdo[0x1400][2].raw = 1
    sdo[0x1400][1].raw = cob
    sdo[0x60C2][1].raw = 2  # 2 ms: each record is interpolated over two SYNC periods
    p0 = sdo[0x6062].raw  # (the axis stays where the last test left it)

    def cycle(cw: int, record: int) -> int:
        net.send_message(cob, cw.to_bytes(2, "little") + (p0 + record).to_bytes(4, "little", signed=True))
        master.sync(1)
        return sdo[0x6062].raw - p0

    assert cycle(0x0F, 500) == 0  # bit 4 not set: ignored
    assert not master.sw() & 0x1000
    demands = [cycle(0x1F, 200)]  # the record of the frame that sets bit 4: the first point
    assert master.sw() & 0x1000
    demands += [cycle(0x1F, r) for r in (400, 600, 800)] + [cycle(0x1F, 800) for _ in range(4)]
    assert demands == [100, 200, 300, 400, 500, 600, 700, 800], demands


def test_polarity_across_processes(master):
    """0x607E bit 7: 0x6064 reaches the target while the drive's own increments 0x6063 go the other way."""
    sdo = master.node.sdo
    master.enable(1)
    sdo[0x6040].raw = 0x07
    master.wait_sync(lambda: master.sw() & 0x6F == 0x23, step=1)
    sdo[0x607E].raw = 0x80
    sdo[0x6040].raw = 0x0F
    x0 = sdo[0x6064].raw
    sdo[0x607A].raw = x0 + 10_000
    inc0 = sdo[0x6063].raw
    sdo[0x6040].raw = 0x1F
    sdo[0x6040].raw = 0x0F
    master.sync(5)
    master.wait_sync(lambda: master.sw() & 0x400)
    assert abs(sdo[0x6064].raw - x0 - 10_000) <= sdo[0x6067].raw
    assert sdo[0x6063].raw - inc0 < -50_000  # the drive's own increments went the other way


def test_touch_probe_across_processes(master):
    """Probe 1 switching at 10 mm, positive edge: 0x60BA within one inner sample of 10 mm after a move past it."""
    sdo = master.node.sdo
    master.enable(1)
    x0 = sdo[0x6064].raw  # (the axis stays where the last test left it; no homing: machine coordinate)
    sdo[0x2014][1].raw = x0 + 10_000
    sdo[0x60B8].raw = 0x11
    sdo[0x607A].raw = x0 + 15_000
    sdo[0x6040].raw = 0x1F
    sdo[0x6040].raw = 0x0F
    master.sync(5)
    master.wait_sync(lambda: master.sw() & 0x400)
    assert sdo[0x60B9].raw == 0x3
    assert abs(sdo[0x60BA].raw - x0 - 10_000) <= 5, (sdo[0x60BA].raw, x0)  # 0.1 m/s: 3.1 um per inner sample
