"""Fault injection details a master sees on the bus (in-process ``virtual`` bus, real ``canopen`` master):
a permanent bus-off injected over CAN ends by itself (the node hears no request to clear it) with EMCY 0x8140
and the 0x6007 reaction; an over-current whose cause persists trips again every time the drive is enabled."""

from __future__ import annotations

import time

from virtualaxis.testing import start_virtual_axis


def _sw(node) -> int:
    return node.sdo[0x6041].raw


def _enable(node) -> None:
    node.sdo[0x6040].raw = 0
    node.sdo[0x6040].raw = 0x80
    for cw in (0x06, 0x07, 0x0F):
        node.sdo[0x6040].raw = cw
    time.sleep(0.05)


def test_bus_off_over_can_recovers_by_itself_and_over_current_trips_again():
    with start_virtual_axis(heartbeat_ms=20) as axis:
        node = axis.node
        beats: list[float] = []
        emcy: list[tuple[float, int, int]] = []
        axis.network.subscribe(0x700 + axis.node_id, lambda c, d, t: beats.append(time.monotonic()))
        axis.network.subscribe(0x80 + axis.node_id, lambda c, d, t: emcy.append(
            (time.monotonic(), int.from_bytes(d[0:2], "little"), d[2])))
        node.nmt.state = "OPERATIONAL"
        node.sdo[0x6007].raw = 1
        node.sdo[0x6060].raw = 3
        _enable(node)
        assert _sw(node) & 0x6F == 0x27
        time.sleep(0.1)
        node.sdo[0x5FF4].raw = 300  # bus-off for 300 ms
        node.sdo[0x5FF0].raw = 10  # confirmed: bus-off begins at the next cycle
        t0 = time.monotonic()
        time.sleep(0.8)
        gaps = [b - a for a, b in zip(beats, beats[1:], strict=False) if a >= t0 - 0.05]
        assert 0.25 < max(gaps) < 0.5, gaps
        recovered = [(t, reg) for t, code, reg in emcy if code == 0x8140 and t > t0]
        assert recovered and recovered[0][1] == 0x11, emcy
        assert _sw(node) & 0x4F == 0x08 and node.sdo[0x603F].raw == 0x8140  # 0x6007 = 1: fault
        assert node.sdo[0x5FF5].raw == 0  # no longer injected

        axis.inject("over_current")  # the Python API of the fixture; the cause stays until cleared
        time.sleep(0.1)
        trips = [code for _, code, _ in emcy].count(0x2310)
        for _ in range(2):
            _enable(node)  # the reset is accepted, the power stage trips again as soon as it is enabled
            time.sleep(0.05)
            assert _sw(node) & 0x4F == 0x08
        assert [code for _, code, _ in emcy].count(0x2310) >= trips + 2
        axis.clear("over_current")
        _enable(node)
        time.sleep(0.1)
        assert _sw(node) & 0x6F == 0x27
