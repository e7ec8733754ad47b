"""Profile position change on set-point, touch probe, polarity and interpolated position mode through a real
``canopen`` master (in-process on the ``virtual`` bus, SYNC lockstep)."""

from __future__ import annotations

from test_cia402_modes import _pp_rig


def test_profile_position_change_on_setpoint_passes_the_first_target_at_its_velocity():
    """Bit 9 = 1, bit 5 = 0: the buffered second set-point starts as the first target is passed; the axis passes
    it at the first set-point's profile velocity and goes on at the second one's."""
    r = _pp_rig()
    node = r.node
    try:
        node.sdo[0x607A].raw = 20_000  # 20 mm at 0.1 m/s
        node.sdo[0x6040].raw = 0x21F
        node.sdo[0x6040].raw = 0x20F
        r.sync(5)  # moving toward the first target
        node.sdo[0x607A].raw = 40_000
        node.sdo[0x6081].raw = 50_000  # the second set-point's velocity
        node.sdo[0x6040].raw = 0x21F  # buffered: bit 12 stays set until the first target is passed
        assert r.sw() & 0x1000
        node.sdo[0x6040].raw = 0x20F
        near_first, after = [], []
        for _ in range(1200):
            r.sync(1)
            x, v = node.sdo[0x6064].raw, node.sdo[0x606C].raw
            if 17_000 <= x <= 20_000:
                near_first.append(v)
            elif 30_000 <= x <= 35_000:
                after.append(v)
            if r.sw() & 0x400:
                break
        assert near_first and min(near_first) > 90_000, near_first  # no stop at the first target
        assert after and all(abs(v - 50_000) < 3_000 for v in after), after
        assert not r.sw() & 0x1000  # both set-points taken
        assert abs(node.sdo[0x6064].raw - 40_000) <= node.sdo[0x6067].raw
    finally:
        r.close()


def _ip_rig():
    from test_drive_rig import Rig

    r = Rig()
    node = r.node
    node.sdo[0x6060].raw = 7
    node.sdo[0x60C2][1].raw = 4  # 4 ms: one set-point interpolated over 4 drive cycles
    node.sdo[0x60C2][2].raw = -3
    node.nmt.state = "OPERATIONAL"
    r.enable()
    return r


def test_interpolated_position_interpolates_buffers_and_needs_enable_ip():
    """IP (7): without bit 4 a record is ignored; bit 4 -> statusword bit 12; each record 0x60C1:1 is a straight
    segment of one period 0x60C2 from the previous end; records sent early wait in the buffer."""
    r = _ip_rig()
    node = r.node
    try:
        assert node.sdo[0x6061].raw == 7
        assert node.sdo[0x6502].raw & 0x40
        node.sdo[0x60C1][1].raw = 4_000  # ip not enabled: ignored
        r.sync(8)
        assert abs(node.sdo[0x6062].raw) <= 1 and not r.sw() & 0x1000
        node.sdo[0x6040].raw = 0x1F  # enable ip mode
        assert r.sw() & 0x1000
        node.sdo[0x60C1][1].raw = 400
        demands = []
        for _ in range(4):
            r.sync(1)
            demands.append(node.sdo[0x6062].raw)
        assert demands == [100, 200, 300, 400]
        for value in (800, 1_600, 1_200):  # three at once: buffered, one period each
            node.sdo[0x60C1][1].raw = value
        demands = []
        for _ in range(12):
            r.sync(1)
            demands.append(node.sdo[0x6062].raw)
        assert demands == [500, 600, 700, 800, 1_000, 1_200, 1_400, 1_600, 1_500, 1_400, 1_300, 1_200]
        r.wait(lambda: r.sw() & 0x400, sync=True, timeout=5)  # at the last set-point: target reached
        assert abs(node.sdo[0x6064].raw - 1_200) <= node.sdo[0x6067].raw
        node.sdo[0x6040].raw = 0x0F  # ip disabled: bit 12 off, records ignored again
        assert not r.sw() & 0x1000
        node.sdo[0x60C1][1].raw = 5_000
        r.sync(8)
        assert node.sdo[0x6062].raw == 1_200
    finally:
        r.close()
