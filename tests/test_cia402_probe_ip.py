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
        for _ in range(300):
            r.sync(4)
            x, v = node.sdo[0x6064].raw, node.sdo[0x606C].raw
            if 17_000 <= x <= 20_000:
                near_first.append(v)
            elif 30_000 <= x <= 35_000:
                after.append(v)
            elif x > 35_000:
                break
        r.wait(lambda: r.sw() & 0x400, sync=True, timeout=10)
        assert near_first and min(near_first) > 90_000, near_first  # no stop at the first target
        assert after and all(abs(v - 50_000) < 3_000 for v in after), after
        assert not r.sw() & 0x1000  # both set-points taken
        assert abs(node.sdo[0x6064].raw - 40_000) <= node.sdo[0x6067].raw
    finally:
        r.close()


def test_profile_position_second_setpoint_before_the_next_cycle_is_buffered():
    """Bit 5 = 0, two set-points before the drive ran a cycle (SDOs between two SYNCs): the first is the running
    one, the second waits in the buffer (bit 12 stays set) and starts once the first target is reached -- it does
    not take the first one's place."""
    r = _pp_rig()
    node = r.node
    try:
        node.sdo[0x607A].raw = 10_000  # 10 mm
        node.sdo[0x6040].raw = 0x1F
        node.sdo[0x6040].raw = 0x0F
        node.sdo[0x607A].raw = 0  # back to the start, in the same drive cycle
        node.sdo[0x6040].raw = 0x1F
        assert r.sw() & 0x1000
        node.sdo[0x6040].raw = 0x0F
        assert r.sw() & 0x1000  # the buffer is full until the first target is reached
        peak = 0  # of the position demand: the buffered set-point starts when the profile has reached the first
        for _ in range(200):
            r.sync(4)
            peak = max(peak, node.sdo[0x6062].raw)
            if peak > 5_000 and node.sdo[0x6064].raw < 100:
                break
        r.wait(lambda: r.sw() & 0x400, sync=True, timeout=10)
        window = node.sdo[0x6067].raw
        assert abs(peak - 10_000) <= window, peak  # the first target was reached ...
        assert abs(node.sdo[0x6064].raw) <= window  # ... and then the second one
        assert not r.sw() & 0x1000
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


def test_polarity_inverts_targets_actual_values_and_limits_and_is_refused_in_operation():
    """0x607E bit 7: 0x607A, 0x6064 and 0x607D in the inverted direction (the table moves the other way); bit 6:
    0x60FF and 0x606C; other bits refused (0x06090030), a change in OPERATION ENABLED too (0x08000022)."""
    import canopen
    import pytest

    r = _pp_rig()
    node = r.node
    try:
        with pytest.raises(canopen.SdoAbortedError) as exc:
            node.sdo[0x607E].raw = 0xC0  # in operation
        assert exc.value.code == 0x08000022
        node.sdo[0x6040].raw = 0x07  # disable operation (ramp 0x605C = 1: done at rest)
        r.wait(lambda: r.sw() & 0x6F == 0x23, sync=True)
        with pytest.raises(canopen.SdoAbortedError) as exc:
            node.sdo[0x607E].raw = 0x01
        assert exc.value.code == 0x06090030
        node.sdo[0x607E].raw = 0xC0
        node.sdo[0x607D][2].raw = 20_000
        node.sdo[0x6040].raw = 0x0F
        node.sdo[0x607A].raw = 30_000  # beyond the max limit: clamped to it (in the master's direction)
        node.sdo[0x6040].raw = 0x1F
        node.sdo[0x6040].raw = 0x0F
        r.sync(60)
        assert node.sdo[0x606C].raw > 50_000  # moving toward +, as the master sees it
        assert r.drive.simulator.state.table_position_m < -2e-3  # the table moves the other way
        r.wait(lambda: r.sw() & 0x400, sync=True, timeout=10)
        assert abs(node.sdo[0x6064].raw - 20_000) <= node.sdo[0x6067].raw
        assert abs(node.sdo[0x6062].raw - 20_000) <= 1
        assert abs(r.drive.simulator.state.table_position_m + 0.020) < 1e-4
        node.sdo[0x6040].raw = 0x07
        r.wait(lambda: r.sw() & 0x6F == 0x23, sync=True)  # switched on
        node.sdo[0x607E].raw = 0x40  # velocity only: positions read as the table goes again
        assert abs(node.sdo[0x6064].raw + 20_000) < 100  # (at once: the actual values follow the write)
        r.sync(1)
        assert abs(node.sdo[0x6064].raw + 20_000) < 100  # (the axis at rest, pulses off)
        node.sdo[0x6060].raw = 3
        node.sdo[0x60FF].raw = 10_000
        node.sdo[0x6040].raw = 0x0F
        r.sync(150)
        assert abs(node.sdo[0x606C].raw - 10_000) < 1_000  # +10 mm/s as the master sees it ...
        assert node.sdo[0x6064].raw < -21_000  # ... is toward - in position
    finally:
        r.close()


def _move_to(r, node, target: int) -> None:
    node.sdo[0x607A].raw = target
    node.sdo[0x6040].raw = 0x1F
    node.sdo[0x6040].raw = 0x0F
    r.sync(2)
    r.wait(lambda: r.sw() & 0x400, sync=True, timeout=10)


def test_touch_probe_latches_between_drive_cycles_single_and_continuous():
    """Probe 1 on its input (switching at 10 mm, both edges, first edge only), probe 2 on the index pulse
    (continuous, positive edge): positions latched within one inner (current-loop) sample of the edge, not at the
    1 ms drive cycle (0.1 mm apart at 0.1 m/s); status bits and toggles of 0x60B9; re-armed by bit 4; an input
    forced by the master (0x2014:3, 0x60FD bit 16)."""
    r = _pp_rig()
    node = r.node
    try:
        inner_m = 0.1 * r.drive.cycle_s / r.drive.simulator.current_cycles_per_cycle  # travel per inner sample
        tol = inner_m / 1e-6 + 1
        node.sdo[0x2014][1].raw = 10_000
        node.sdo[0x60B8].raw = 0x1731  # probe 2: enable, continuous, index, positive; probe 1: enable, both edges
        assert node.sdo[0x60B9].raw == 0x0101
        _move_to(r, node, 20_000)
        status = node.sdo[0x60B9].raw
        assert status == 0x0101 | 0x2 | 0x200 | 0x4000, hex(status)  # positive edge stored; probe 2 toggled once
        assert abs(node.sdo[0x60BA].raw - 10_000) <= tol, node.sdo[0x60BA].raw
        assert abs(node.sdo[0x60BC].raw - 16_000) <= tol, node.sdo[0x60BC].raw  # one motor revolution = 16 mm
        _move_to(r, node, 5_000)
        status = node.sdo[0x60B9].raw
        assert status == 0x0101 | 0x2 | 0x4 | 0x200, hex(status)  # negative edge stored; probe 2 toggled back
        assert abs(node.sdo[0x60BB].raw - 10_000) <= tol, node.sdo[0x60BB].raw
        assert abs(node.sdo[0x60BC].raw - 16_000) <= tol
        # first edge only: a forced edge is not latched until bit 4 re-arms the positive edge
        node.sdo[0x2014][3].raw = 1
        r.sync(2)
        assert node.sdo[0x60FD].raw & 0x10000
        assert abs(node.sdo[0x60BA].raw - 10_000) <= tol
        node.sdo[0x2014][3].raw = 0
        node.sdo[0x60B8].raw = 0x1721
        node.sdo[0x60B8].raw = 0x1731
        assert not node.sdo[0x60B9].raw & 0x2
        r.sync(2)
        node.sdo[0x2014][3].raw = 1
        r.sync(2)
        assert node.sdo[0x60B9].raw & 0x2
        assert abs(node.sdo[0x60BA].raw - node.sdo[0x6064].raw) <= 2  # at rest at 5 mm
        node.sdo[0x60B8].raw = 0  # disabled: status cleared
        assert node.sdo[0x60B9].raw == 0
    finally:
        r.close()


def test_interpolated_position_full_buffer_is_refused_and_halt_brakes():
    """IP: a record beyond the buffer (16 after the running segment) aborts 0x08000022 and nothing buffered is
    lost; halt (bit 8) drops the buffer and brakes to rest (bit 10 once at rest, bit 12 off while halted)."""
    import canopen
    import pytest

    r = _ip_rig()
    node = r.node
    try:
        node.sdo[0x6084].raw = 10_000_000  # the halt's deceleration (0x605D = 1): 10 m/s^2
        node.sdo[0x6040].raw = 0x1F
        for k in range(1, 18):  # the running segment + 16 buffered: 1 mm per period
            node.sdo[0x60C1][1].raw = 1_000 * k
        with pytest.raises(canopen.SdoAbortedError) as exc:
            node.sdo[0x60C1][1].raw = 18_000
        assert exc.value.code == 0x08000022
        r.sync(4 * 17)
        assert abs(node.sdo[0x6062].raw - 17_000) <= 1  # every accepted record interpolated
        for k in range(18, 30):
            node.sdo[0x60C1][1].raw = 1_000 * k
        r.sync(8)  # at 0.25 m/s
        assert node.sdo[0x606C].raw > 100_000
        node.sdo[0x6040].raw = 0x11F  # halt
        assert not r.sw() & 0x1000
        r.wait(lambda: r.sw() & 0x400, sync=True, timeout=5)
        assert abs(node.sdo[0x606C].raw) < 2_000
        assert node.sdo[0x6062].raw < 25_000  # 3 mm of braking, short of the records buffered (29 mm)
    finally:
        r.close()


def test_polarity_applies_to_the_home_offset_and_torque():
    """0x607E = 0xC0: homing on the current position reads 0x607C there; in CST a positive 0x6071 drives the table
    toward - while 0x6077 and 0x606C read positive."""
    from test_drive_rig import Rig

    r = Rig()
    node = r.node
    try:
        node.sdo[0x607E].raw = 0xC0
        node.sdo[0x6098].raw = 37
        node.sdo[0x607C].raw = 1_000
        node.sdo[0x6060].raw = 6
        node.nmt.state = "OPERATIONAL"
        r.enable()
        node.sdo[0x6040].raw = 0x1F
        r.wait(lambda: r.sw() & 0x1400 == 0x1400, sync=True)
        r.sync(1)  # (method 37 is done at the write; the actual values are published by the next cycle)
        assert abs(node.sdo[0x6064].raw - 1_000) <= 2
        node.sdo[0x6040].raw = 0x0F
        node.sdo[0x6060].raw = 10
        x0 = r.drive.simulator.state.table_position_m
        node.sdo[0x6071].raw = 100  # 10 % of the rated torque
        r.sync(30)
        assert node.sdo[0x6077].raw > 50 and node.sdo[0x6074].raw == 100
        assert node.sdo[0x606C].raw > 0 and node.sdo[0x6064].raw > 1_000
        assert r.drive.simulator.state.table_position_m < x0  # the other way
    finally:
        r.close()


def _emcy_codes_after(r, code: int) -> list[int]:
    """The EMCY codes the master received after the last EMCY ``code``."""
    codes = r.emcy.codes()
    last = len(codes) - 1 - codes[::-1].index(code)
    return codes[last + 1:]


def test_interpolated_position_refused_record_warning_clears_on_the_next_accepted_record():
    """IP: a record refused by the full buffer raises the warning 0x6320 (EMCY, statusword bit 7, 0x2031 = 7470,
    0x603F = 0x6320, 0x1001 = 0x81); the next record accepted clears it, as an accepted PP set-point does: EMCY
    0x0000, 0x603F = 0, 0x1001 = 0, bit 7 off, 0x2031 = 0."""
    import time

    import canopen
    import pytest

    r = _ip_rig()
    node = r.node
    try:
        node.sdo[0x6040].raw = 0x1F
        for k in range(1, 18):  # the running segment + 16 buffered
            node.sdo[0x60C1][1].raw = 100 * k
        for k in (18, 19):
            with pytest.raises(canopen.SdoAbortedError) as exc:
                node.sdo[0x60C1][1].raw = 100 * k
            assert exc.value.code == 0x08000022
        r.emcy.wait_for(0x6320)
        r.sync(1)
        assert r.sw() & 0x80 and node.sdo[0x2031].raw == 7470
        assert node.sdo[0x603F].raw == 0x6320 and node.sdo[0x1001].raw == 0x81
        r.sync(4)  # a segment done: room in the buffer
        node.sdo[0x60C1][1].raw = 1_800
        r.sync(1)
        assert not r.sw() & 0x80 and node.sdo[0x2031].raw == 0
        assert node.sdo[0x603F].raw == 0 and node.sdo[0x1001].raw == 0
        end = time.monotonic() + 2
        while 0 not in _emcy_codes_after(r, 0x6320):
            assert time.monotonic() < end, r.emcy.codes()
            time.sleep(0.005)
        r.sync(4 * 18)
        assert node.sdo[0x6062].raw == 1_800  # every accepted record interpolated
    finally:
        r.close()


def test_interpolated_position_refused_record_warning_goes_with_the_mode():
    """IP: the warning of a record refused by the full buffer (statusword bit 7, 0x2031 = 7470) belongs to IP; a
    change to PP, where no record can clear it, clears it (EMCY 0x0000), and the drive enables in PP with bit 7
    off."""
    import canopen
    import pytest

    r = _ip_rig()
    node = r.node
    try:
        node.sdo[0x6040].raw = 0x1F
        for k in range(1, 18):
            node.sdo[0x60C1][1].raw = 100 * k
        with pytest.raises(canopen.SdoAbortedError):
            node.sdo[0x60C1][1].raw = 1_800
        r.emcy.wait_for(0x6320)
        r.sync(1)
        assert r.sw() & 0x80 and node.sdo[0x2031].raw == 7470
        node.sdo[0x6040].raw = 0x07  # disable operation, then PP
        r.sync(20)
        node.sdo[0x6060].raw = 1
        r.sync(1)
        assert not r.sw() & 0x80 and node.sdo[0x2031].raw == 0 and node.sdo[0x603F].raw == 0
        node.sdo[0x6040].raw = 0x0F
        r.sync(20)
        assert r.sw() & 0x6F == 0x27 and not r.sw() & 0x80
        assert 0 in _emcy_codes_after(r, 0x6320)
    finally:
        r.close()


def test_interpolated_position_record_in_the_frame_that_enables_ip_is_the_first_point():
    """IP with RPDO1 = controlword + 0x60C1:1 (synchronous): the record of the frame whose controlword raises bit 4
    is the first interpolation point (one period 0x60C2 from the demand), not dropped; the next record is one
    period further, not a segment twice as long. A record in a frame without bit 4 stays ignored."""
    r = _ip_rig()
    node = r.node
    try:
        cob = 0x200 + node.id
        node.sdo[0x1400][1].raw = cob | 0x80000000  # RPDO1: controlword + 0x60C1:1, synchronous
        node.sdo[0x1600][0].raw = 0
        node.sdo[0x1600][1].raw = 0x60400010
        node.sdo[0x1600][2].raw = 0x60C10120
        node.sdo[0x1600][0].raw = 2
        node.sdo[0x1400][2].raw = 1
        node.sdo[0x1400][1].raw = cob

        def frame(cw: int, record: int) -> int:
            r.net.send_message(cob, cw.to_bytes(2, "little") + record.to_bytes(4, "little", signed=True))
            r.sync(1)
            return node.sdo[0x6062].raw

        node.sdo[0x60C2][1].raw = 1  # 1 ms: one record per SYNC, each interpolated over one drive cycle
        assert frame(0x0F, 4_000) == 0  # bit 4 not set: ignored
        demands = [frame(0x1F, 100 * k) for k in range(1, 6)]  # bit 4 rises with the first record
        assert demands == [100, 200, 300, 400, 500], demands
    finally:
        r.close()


def test_interpolation_period_zero_is_refused():
    """0x60C2:1 = 0 (no interpolation period: every record a step) is refused with SDO abort 0x06090032 (value
    too low); the period stays as it was."""
    import canopen
    import pytest

    from virtualaxis.drive import ObjectAccessError

    r = _ip_rig()
    node = r.node
    try:
        with pytest.raises(canopen.SdoAbortedError) as exc:
            node.sdo[0x60C2][1].raw = 0
        assert exc.value.code == 0x06090032
        assert node.sdo[0x60C2][1].raw == 4
        with pytest.raises(ObjectAccessError, match="0x60C2:1") as err:
            r.drive.write_object(0x60C2, 1, 0)  # the drive API refuses it as the SDO does
        assert err.value.code == 0x06090032
        node.sdo[0x60C2][1].raw = 1
        assert node.sdo[0x60C2][1].raw == 1
    finally:
        r.close()


def test_touch_probe_disabling_an_edge_clears_its_status_and_keeps_its_value():
    """0x60B8: clearing an edge's enable bit (probe 1 bits 4 / 5, probe 2 bits 12 / 13) clears that edge's stored
    bit (and its toggle bit) in 0x60B9; the other edge's status and the latched positions 0x60BA-0x60BD stay."""
    r = _pp_rig()
    node = r.node
    try:
        node.sdo[0x60B8].raw = 0x0031  # probe 1: enable, both edges, first edge only
        node.sdo[0x2014][3].raw = 1  # input 1 forced on: positive edge
        r.sync(2)
        node.sdo[0x2014][3].raw = 0  # ... and off: negative edge
        r.sync(2)
        assert node.sdo[0x60B9].raw == 0x7
        positive, negative = node.sdo[0x60BA].raw, node.sdo[0x60BB].raw
        node.sdo[0x60B8].raw = 0x0021  # positive edge disabled
        assert node.sdo[0x60B9].raw == 0x5
        node.sdo[0x60B8].raw = 0x0001  # negative edge disabled
        assert node.sdo[0x60B9].raw == 0x1
        assert (node.sdo[0x60BA].raw, node.sdo[0x60BB].raw) == (positive, negative)
        node.sdo[0x60B8].raw = 0x1300  # probe 2: enable, continuous, positive edge
        node.sdo[0x2014][3].raw = 2
        r.sync(2)
        assert node.sdo[0x60B9].raw == 0x4300  # enabled, positive edge stored, its toggle bit
        latched = node.sdo[0x60BC].raw
        node.sdo[0x60B8].raw = 0x0300  # positive edge disabled
        assert node.sdo[0x60B9].raw == 0x0100
        assert node.sdo[0x60BC].raw == latched
    finally:
        r.close()


def test_latched_probe_positions_follow_a_polarity_change_as_the_actual_position_does():
    """0x60BA-0x60BD read as 0x6064 does: a latch taken at the actual position reads the same value as 0x6064
    after 0x607E bit 7 changes too (a docs-only master found the latch keeping its old sign)."""
    r = _pp_rig()
    node = r.node
    try:
        node.sdo[0x607A].raw = 10_000  # to 10 mm, then switched on (0x607E is refused in operation)
        node.sdo[0x6040].raw = 0x1F
        node.sdo[0x6040].raw = 0x0F
        r.wait(lambda: r.sw() & 0x400, sync=True, timeout=10)
        node.sdo[0x6040].raw = 0x07
        r.wait(lambda: r.sw() & 0x6F == 0x23, sync=True)
        node.sdo[0x60B8].raw = 0x0031  # probe 1: enable, both edges, first edge only
        node.sdo[0x2014][3].raw = 1  # input 1 forced on: positive edge at the actual position
        r.sync(2)
        at = node.sdo[0x6064].raw
        assert abs(at - 10_000) < 100 and abs(node.sdo[0x60BA].raw - at) <= 1
        node.sdo[0x607E].raw = 0x80
        assert node.sdo[0x6064].raw == -at
        assert abs(node.sdo[0x60BA].raw + at) <= 1, (node.sdo[0x60BA].raw, at)
        node.sdo[0x607E].raw = 0xC0  # bit 7 unchanged: the latch stays
        assert abs(node.sdo[0x60BA].raw + at) <= 1
        node.sdo[0x607E].raw = 0x00
        assert abs(node.sdo[0x60BA].raw - at) <= 1
    finally:
        r.close()
