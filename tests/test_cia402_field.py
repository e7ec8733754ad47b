"""Issue #15 / #18 (drive side) through a real ``canopen`` master on a python-can ``virtual`` bus: fault
reactions from the actual motion, controlword + target in one RPDO, loss of control (NMT), limit switches and
end stops, defaults that do not fault, mode change while moving, drive-cycle exceptions and the
fault-injection contract. The cross-process versions are in tests/test_field_udp.py."""

from __future__ import annotations

import math
import time

import canopen
import pytest
from nmt_wait import reset_and_wait_for_bootup
from test_drive_rig import Rig, seed_config

from virtualaxis.sim.simulator import end_stops

UNIT_M = 1e-6  # one position unit (default feed constant)


def _raw_rpdo2(rig: Rig, cw: int, target: int) -> None:
    """The drive's default RPDO2 (0x300 + node id): controlword u16 + target position i32."""
    rig.net.send_message(0x300 + rig.node.id, cw.to_bytes(2, "little") + target.to_bytes(4, "little", signed=True))


def _start(rig: Rig, mode: int, **objects: int) -> None:
    node = rig.node
    for index, value in objects.items():
        node.sdo[int(index, 16)].raw = value
    node.sdo[0x6060].raw = mode
    node.nmt.state = "OPERATIONAL"
    time.sleep(0.01)
    rig.enable()


def test_csp_following_error_fault_brakes_from_the_actual_speed():
    """Item 1: CSP at 183 mm/s, following-error fault with 0x605E = 2 and 0x6085 = 10 m/s^2: the axis stops
    in about v^2/2a (1.7 mm; before: coasted 44 mm), FAULT REACTION ACTIVE -> FAULT, EMCY 0x8611."""
    r = Rig()
    try:
        _start(r, 8, **{"0x605E": 2, "0x6085": 10_000_000})
        node = r.node
        x = 0
        for i in range(260):
            x += round(183 * min(1.0, (i + 1) / 50))  # 183 mm/s after a 50 ms ramp
            _raw_rpdo2(r, 0x0F, x)
            r.sync(1)
        v0 = node.sdo[0x606C].raw * UNIT_M
        assert abs(v0 - 0.183) < 0.01
        node.sdo[0x6065].raw = 100  # tighten the window: the following error (~2 mm without feed-forward) faults
        seen = []
        for _ in range(20):
            x += 183
            _raw_rpdo2(r, 0x0F, x)
            r.sync(1)
            sw = r.sw()
            seen.append(sw & 0x6F)
            if sw & 0x6F == 0x2F:
                break
        assert seen[-1] == 0x2F, [hex(s) for s in seen]  # fault reaction active
        assert sw & 0x2000  # bit 13 following error from the timeout on (before: only once in FAULT)
        p0 = node.sdo[0x6064].raw
        r.emcy.wait_for(0x8611)
        states = []
        for _ in range(60):  # the master sends nothing more
            r.sync(5)
            states.append(r.sw() & 0x6F)
            if states[-1] == 0x28:
                break
        assert states[-1] == 0x28  # FAULT once stopped and held
        r.sync(100)
        travel_mm = (node.sdo[0x6064].raw - p0) * UNIT_M * 1e3
        ideal_mm = v0 * v0 / (2 * 10.0) * 1e3
        assert 0.5 * ideal_mm < travel_mm < 2.0 * ideal_mm, (travel_mm, ideal_mm)
        assert abs(node.sdo[0x606C].raw) < 200  # at rest (< 0.2 mm/s)
    finally:
        r.close()


def test_controlword_and_target_in_one_rpdo_start_the_move_to_the_new_target():
    """Item 2: ``0x301+n [1f 00 b8 88 00 00]`` (default RPDO2: CW with new set-point + 0x607A = 35000) moves
    the axis to 35000, not to the old target."""
    r = Rig()
    try:
        _start(r, 1, **{"0x6081": 200_000, "0x6083": 2_000_000, "0x6084": 2_000_000})
        node = r.node
        node.sdo[0x607A].raw = 5_000  # an old target, not started
        r.net.send_message(0x300 + node.id, bytes([0x1F, 0x00, 0xB8, 0x88, 0x00, 0x00]))
        r.sync(2)
        assert node.sdo[0x607A].raw == 35_000
        assert r.sw() & 0x1000  # set-point acknowledged
        _raw_rpdo2(r, 0x0F, 35_000)
        r.wait(lambda: r.sw() & 0x400, sync=True, timeout=10)
        assert abs(node.sdo[0x6064].raw - 35_000) <= node.sdo[0x6067].raw
    finally:
        r.close()


@pytest.mark.parametrize("command", ["stop", "reset_communication"])
def test_nmt_stop_or_reset_communication_while_moving_is_a_loss_of_control(command):
    """Item 3: PV at 50 mm/s, 0x6007 = 1: NMT Stopped / Reset Communication -> fault, the axis brakes
    (0x605E = 2, quick stop 0x6085) instead of running on (before: 26 mm in 0.5 s and still moving)."""
    r = Rig(lockstep=False)
    try:
        _start(r, 3, **{"0x6007": 1, "0x6083": 2_000_000, "0x6085": 2_000_000})
        node = r.node
        node.sdo[0x60FF].raw = 50_000
        r.wait(lambda: abs(r.drive.state.velocity_actual_m_s - 0.05) < 0.002, timeout=3)
        x0 = r.drive.state.position_actual_m
        if command == "stop":
            node.nmt.state = "STOPPED"
        else:
            node.nmt.send_command(0x82)
        time.sleep(0.5)
        s = r.drive.state
        assert s.cia402_state == "FAULT"
        assert s.faults[0].emcy_code == 0x8131
        if command == "reset_communication":  # CiA 301: the fault's EMCY, once the node is PRE-OPERATIONAL
            r.emcy.wait_for(0x8131)           # after its boot-up (before: never sent)
        else:                                 # in STOPPED no EMCY is sent
            assert 0x8131 not in r.emcy.codes()
        travel_mm = (s.position_actual_m - x0) * 1e3
        assert travel_mm < 0.05**2 / (2 * 2.0) * 1e3 + 2.0, travel_mm  # ~0.6 mm ramp + reaction time
        assert abs(s.velocity_actual_m_s) < 1e-3
    finally:
        r.close()


def test_limit_switch_stops_every_mode_and_allows_motion_only_away():
    """Item 4: PV toward the positive limit switch (software limits widened) stops with 0x6085 and faults
    0xFF11 (0x2013 = 1); after a fault reset the axis may move away from the switch, not further toward it;
    0x2013 = 0 gives warning + stop and stays enabled."""
    r = Rig()
    try:
        _start(r, 3, **{"0x607D": 0, "0x6085": 5_000_000, "0x6083": 5_000_000})
        node = r.node
        node.sdo[0x607D][1].raw = -2_000_000
        node.sdo[0x607D][2].raw = 2_000_000
        node.sdo[0x60FF].raw = 200_000
        r.wait(lambda: r.sw() & 0x08, sync=True, timeout=30)
        r.emcy.wait_for(0xFF11)
        r.sync(100)
        half = r.drive.cfg.axis.stroke_m / 2
        x = node.sdo[0x6064].raw * UNIT_M
        assert half - 0.002 <= x < half - 0.002 + 0.2**2 / (2 * 5.0) + 0.002  # stopped just past the switch
        assert node.sdo[0x60FD].raw & 0x2
        # fault reset on the switch is allowed; toward the switch nothing moves
        node.sdo[0x6040].raw = 0x80
        r.enable()
        r.sync(200)
        assert abs(node.sdo[0x6064].raw * UNIT_M - x) < 1e-4
        assert r.sw() & 0x800  # internal limit active
        node.sdo[0x60FF].raw = -50_000  # away: allowed
        r.sync(300)
        assert node.sdo[0x6064].raw * UNIT_M < x - 0.005
        assert r.sw() & 0x6F == 0x27
        # warning variant: back toward the switch with 0x2013 = 0
        node.sdo[0x2013].raw = 0
        node.sdo[0x60FF].raw = 100_000
        r.wait(lambda: node.sdo[0x2031].raw == 7492, sync=True, timeout=30)
        r.sync(100)
        assert r.sw() & 0x6F == 0x27 and r.sw() & 0x80  # enabled, warning bit 7
        assert abs(node.sdo[0x606C].raw) < 1000
    finally:
        r.close()


def test_huge_external_force_stops_at_the_end_stop_and_reset_node_restores_the_plant():
    """Items 4 + #18: 0x2011 = -1e6 N on a disabled drive: the table stops at the hard end stop (before:
    17 km, then NaN and a dead drive thread); enabling gives no NaN; NMT reset node restores the plant at
    rest where it stands (the buffer relaxed: at its surface, on the limit switch), with valid position
    objects, and the master drives it off the switch (only away from it) back into the stroke."""
    r = Rig()
    try:
        node = r.node
        node.nmt.state = "OPERATIONAL"
        node.sdo[0x2011].raw = -1e6
        r.sync(1000)
        half = r.drive.cfg.axis.stroke_m / 2
        lo, _, _, _, travel, _ = end_stops(r.drive.cfg)
        x = r.drive.state.table_position_m
        assert lo - travel - 0.002 < x < -half, x  # in the end stop's buffer, not beyond
        assert node.sdo[0x60FD].raw & 0x1
        r.enable()
        r.sync(200)
        s = r.drive.state
        assert math.isfinite(s.position_actual_m) and s.cia402_state in ("OPERATION ENABLED", "FAULT")
        assert r.drive.counters["cycle_exceptions"] == 0
        node.sdo[0x2011].raw = 0.0
        reset_and_wait_for_bootup(node, 5.0)
        r.sync(10)
        s = r.drive.state
        assert lo - 1e-6 <= s.table_position_m < -half and abs(s.velocity_actual_m_s) < 1e-3, s.table_position_m
        assert node.sdo[0x60FD].raw & 0x1 and abs(node.sdo[0x6064].raw) < 2**31 - 1
        _start(r, 3, **{"0x6083": 1_000_000, "0x6084": 1_000_000})
        node.sdo[0x60FF].raw = -20_000  # into the switch: refused (stays put)
        r.sync(200)
        assert r.drive.state.table_position_m < -half + 0.001
        node.sdo[0x60FF].raw = 50_000  # away from it: moves, back inside the stroke
        r.wait(lambda: r.drive.state.table_position_m > -half + 0.01, sync=True, timeout=10)
        assert not node.sdo[0x60FD].raw & 0x3
        with pytest.raises(canopen.SdoAbortedError) as exc:
            node.sdo[0x2011].raw = float("nan")
        assert exc.value.code == 0x06090030
    finally:
        r.close()


def test_defaults_run_the_maximum_profile_velocity_without_a_fault():
    """Item 5: PP at 0x607F (the maximum the defaults permit) and homing at 200 mm/s run without a
    following-error fault (the commissioned window 0x6065 covers the lag v/Kv)."""
    r = Rig()
    try:
        node = r.node
        vmax = node.sdo[0x607F].raw
        _start(r, 1, **{"0x6081": vmax, "0x6083": 5_000_000, "0x6084": 5_000_000})
        node.sdo[0x607A].raw = 200_000
        node.sdo[0x6040].raw = 0x1F
        node.sdo[0x6040].raw = 0x0F
        r.wait(lambda: r.sw() & 0x400, sync=True, timeout=10)
        assert r.sw() & 0x6F == 0x27, hex(r.sw())
        assert abs(node.sdo[0x6064].raw - 200_000) <= node.sdo[0x6067].raw
        assert not r.drive.faults
    finally:
        r.close()


def test_mode_change_pv_to_pp_while_moving_decelerates_with_the_profile_deceleration():
    """Item 7: PV at 100 mm/s, 0x6060 = 1: the axis decelerates with 0x6084 (2 m/s^2) from its actual
    motion, no hard stop at the torque limit and no back-travel (before: -300 % in 4 ms, 0.4 mm back)."""
    r = Rig()
    try:
        _start(r, 3, **{"0x6083": 2_000_000, "0x6084": 2_000_000})
        node = r.node
        node.sdo[0x60FF].raw = 100_000
        r.sync(400)
        x0 = node.sdo[0x6064].raw
        node.sdo[0x6060].raw = 1
        peak_pm, xmax = 0, x0
        for _ in range(150):
            r.sync(2)
            s = r.drive.state
            peak_pm = max(peak_pm, abs(node.sdo[0x6077].raw))
            xmax = max(xmax, round(s.position_actual_m / UNIT_M))
        r.sync(200)
        x_end = node.sdo[0x6064].raw
        assert peak_pm < 1500, peak_pm  # well below the -300 % hard stop
        assert xmax - x_end < 20  # no back-travel
        assert 2_000 < x_end - x0 < 5_000  # v^2/2a = 2.5 mm (+ the lag v/Kv of the position loop)
        assert r.sw() & 0x6F == 0x27
    finally:
        r.close()


def test_exception_in_the_drive_cycle_faults_0x6100_and_a_reset_clears_it(caplog):
    """#18: a hook raising in the drive cycle -> EMCY 0x6100, log line with traceback, SDO still answers,
    fault reset refused never (no persistent cause) and accepted once the cause is gone."""
    r = Rig()
    try:
        node = r.node
        _start(r, 3)

        def broken(drive):
            raise ValueError("test: cannot convert float NaN to integer")

        r.drive.add_cycle_hook(broken)
        r.sync(3)
        r.emcy.wait_for(0x6100)
        assert r.sw() & 0x6F == 0x28
        assert node.sdo[0x2110][6].raw >= 1
        assert "cannot convert float NaN" in caplog.text and "Traceback" in caplog.text
        r.drive.remove_cycle_hook(broken)
        node.sdo[0x6040].raw = 0x80
        r.sync(1)
        assert r.sw() & 0x6F == 0x40  # switch on disabled
    finally:
        r.close()


def test_raise_fault_reaction_classes_and_persistent_cause():
    """Contract: an encoder fault coasts (OFF2, pulses off at once), a fault with a cause cannot be reset
    until clear_cause; 0x4210 from PP at 100 mm/s brakes with 0x605E (before: 11.3 mm of coasting)."""
    r = Rig()
    try:
        node = r.node
        _start(r, 1, **{"0x6081": 100_000, "0x6083": 2_000_000, "0x6085": 10_000_000})
        node.sdo[0x607A].raw = 200_000
        node.sdo[0x6040].raw = 0x1F
        r.sync(300)
        assert abs(node.sdo[0x606C].raw - 100_000) < 2_000
        x0 = r.drive.state.position_actual_m
        r.drive.raise_fault(0x4210, 95, cause="heat sink")
        r.sync(100)
        assert (r.drive.state.position_actual_m - x0) * 1e3 < 1.0  # v^2/2a = 0.5 mm (before: 11.3 mm)
        node.sdo[0x6040].raw = 0x80
        r.sync(1)
        assert r.sw() & 0x6F == 0x28  # refused: cause persists
        r.drive.clear_cause("heat sink")
        node.sdo[0x6040].raw = 0x00
        node.sdo[0x6040].raw = 0x80
        r.sync(1)
        assert r.sw() & 0x6F == 0x40
        # encoder loss: coast (no controlled braking possible)
        node.sdo[0x6060].raw = 3
        r.enable()
        node.sdo[0x60FF].raw = 100_000
        r.sync(300)
        r.drive.raise_fault(0x7305)
        assert r.drive.cia402_state.name == "FAULT" and not r.drive.simulator.enabled
        r.drive.set_warning(0x4210, True)
        r.sync(1)
        assert node.sdo[0x2031].raw == 30004
        r.emcy.wait_for(0x4210)
    finally:
        r.close()


def test_force_far_beyond_the_motor_faults_overspeed_instead_of_diverging():
    """#18 root cause: 0x2011 = 1e6 N with PT enabled (seven legal writes) back-drives the motor far beyond its
    speed; the drive switches the pulses off (0x8401 F07901 overspeed, OFF2), the table ends at the end stop,
    no NaN, no cycle exception; a force beyond +-1e6 N is refused (0x06090031 / 0x06090032)."""
    r = Rig()
    try:
        node = r.node
        _start(r, 4)
        node.sdo[0x6071].raw = 3000
        node.sdo[0x2011].raw = 1e6
        r.sync(500)
        s = r.drive.state
        assert s.cia402_state == "FAULT" and 0x8401 in [f.emcy_code for f in s.faults]
        half = r.drive.cfg.axis.stroke_m / 2
        _, hi, _, _, travel, _ = end_stops(r.drive.cfg)
        assert half < s.table_position_m < hi + travel + 0.002
        assert math.isfinite(node.sdo[0x6077].raw) and r.drive.counters["cycle_exceptions"] == 0
        for value, code in ((1e30, 0x06090031), (-1.5e6, 0x06090032)):
            with pytest.raises(canopen.SdoAbortedError) as exc:
                node.sdo[0x2011].raw = value
            assert exc.value.code == code
    finally:
        r.close()


def test_position_objects_saturate_with_a_fault_instead_of_wrapping():
    """Item 4: with 1 position unit = 0.1 nm (0x6092:1 = 1.6e8 per 16 mm revolution) 2^31 units are 0.215 m;
    PV past it: 0x6064 stops at 2^31 - 1 (no wrap to -2^31) and fault 0x8600 (F07493) is raised."""
    r = Rig()
    try:
        node = r.node
        node.sdo[0x6092][1].raw = 160_000_000
        node.sdo[0x607D][1].raw = 0  # software limits off (min >= max)
        node.sdo[0x607D][2].raw = 0
        _start(r, 3, **{"0x6083": 2_000_000_000, "0x6085": 2_000_000_000, "0x6065": 0xFFFFFFFF,
                        "0x607F": 2_000_000_000})
        node.sdo[0x60FF].raw = 1_000_000_000  # 0.1 m/s
        r.sync(2500)
        r.emcy.wait_for(0x8600)
        assert r.sw() & 0x08
        r.sync(200)
        assert node.sdo[0x6064].raw == 0x7FFFFFFF
        assert 0.2147 < r.drive.state.table_position_m < 0.26  # braked with 0x6085 = 0.2 m/s^2
    finally:
        r.close()


def test_sync_loss_in_csp_is_a_loss_of_control_in_real_time():
    """Item 3: CSP paced by the wall clock, SYNC every 2 ms (0x1006 = 2000 us), 0x6007 = 1: SYNC stops ->
    EMCY 0x8100 and fault 0x8100 (before: EMCY only, the drive stayed enabled). (In SYNC lockstep the plant
    waits for SYNC and nothing is faulted: the other tests of this file run that way.)"""
    r = Rig(lockstep=False)
    try:
        node = r.node
        node.sdo[0x1006].raw = 2000
        _start(r, 8, **{"0x6007": 1})
        r.net.sync.start(0.002)
        time.sleep(0.3)
        assert r.sw() & 0x6F == 0x27
        r.net.sync.stop()
        r.emcy.wait_for(0x8100)
        r.wait(lambda: r.sw() & 0x6F == 0x28, timeout=2)
        assert r.drive.faults[0].emcy_code == 0x8100
    finally:
        r.close()


@pytest.mark.parametrize(("option", "max_mm"), [(3, 1.0), (0, None)])
def test_quick_stop_on_the_current_limit_and_coast(option, max_mm):
    """Item 1: controlword quick stop (0x02) at 100 mm/s: 0x605A = 3 brakes at the current limit (a few tenths of
    a mm) then switch on disabled; 0x605A = 0 coasts (pulses off at once, the axis runs out on friction)."""
    r = Rig()
    try:
        node = r.node
        _start(r, 3, **{"0x605A": option, "0x6083": 2_000_000})
        node.sdo[0x60FF].raw = 100_000
        r.sync(300)
        x0 = r.drive.state.position_actual_m
        node.sdo[0x6040].raw = 0x02
        r.sync(300)
        s = r.drive.state
        assert s.cia402_state == "SWITCH ON DISABLED"
        travel_mm = (s.position_actual_m - x0) * 1e3
        if max_mm is not None:
            assert 0.0 < travel_mm < max_mm, travel_mm
        else:
            assert travel_mm > 1.0 and not r.drive.simulator.enabled  # coasted further than any ramp here
    finally:
        r.close()


def test_torque_actual_is_computed_from_the_currents_and_stays_within_0x6072():
    """In PT with the target beyond 0x6072, 0x6077 read 3008 per mille with 0x6072 =
    3000 (the air-gap torque including cogging, and the current loop's overshoot of its limit). A drive shows
    the torque it computes from its measured currents, within its torque limit."""
    r = Rig()
    try:
        node = r.node
        _start(r, 4, **{"0x6072": 1000, "0x6087": 0})
        node.sdo[0x6071].raw = 2000
        seen = []
        for _ in range(30):
            r.sync(5)
            seen.append(node.sdo[0x6077].raw)
        assert max(seen) <= 1000 and seen[-1] >= 990, seen
        s = r.drive.state
        mot = r.drive.cfg.motor
        t_currents = mot.kt_nm_per_a * s.current_a  # ld = lq on the seed motor: no reluctance torque
        assert s.torque_nm == pytest.approx(min(t_currents, node.sdo[0x6076].raw / 1000.0), rel=1e-6)
    finally:
        r.close()


def test_zero_accelerations_are_refused_and_every_fault_reaction_option_is_offered():
    """An acceleration / deceleration of 0 (0x6083, 0x6084, 0x6085, 0x609A) is refused with 0x06090032 and the
    value kept (before: accepted, and a quick stop at 0x6085 = 0 kept the axis at 100 mm/s); 0x605E 3 and 4
    (current / voltage limit, CiA 402) are taken, 5 is refused (0x06090031). Found by a docs-only master."""
    r = Rig()
    try:
        node = r.node
        for index in (0x6083, 0x6084, 0x6085, 0x609A):
            before = node.sdo[index].raw
            with pytest.raises(canopen.SdoAbortedError) as exc:
                node.sdo[index].raw = 0
            assert exc.value.code == 0x06090032, (hex(index), hex(exc.value.code))
            assert node.sdo[index].raw == before
            node.sdo[index].raw = 1  # the smallest legal value
            node.sdo[index].raw = before
        for option in (3, 4):
            node.sdo[0x605E].raw = option
            assert node.sdo[0x605E].raw == option
        with pytest.raises(canopen.SdoAbortedError) as exc:
            node.sdo[0x605E].raw = 5
        assert exc.value.code == 0x06090031
    finally:
        r.close()


def test_communication_errors_clear_themselves_and_never_hide_the_fault_code():
    """CiA 301: a communication error that has gone (SYNC back after a gap, a heartbeat producer back) clears
    0x1001's communication bit, and with no other error left EMCY 0x0000 goes out and 0x1001 = 0x603F = 0
    (before: 0x1001 = 0x11 and 0x603F = 0x8100 stayed until a fault reset). In FAULT, a later SYNC gap does
    not replace the fault's code in 0x603F (before: 0x3220 read back as 0x8100), and the SYNC coming back
    sends no EMCY 0x0000 (the fault is still there); the fault reset does. Paced to the wall clock: in lockstep
    the slave's timers run on drive time, which a gap between SYNCs does not advance."""
    r = Rig(lockstep=False)
    try:
        node = r.node
        node.sdo[0x1006].raw = 10_000  # 10 ms: timeout 15 ms
        node.sdo[0x6007].raw = 0  # loss of SYNC: no drive reaction (only the EMCY)
        node.nmt.state = "OPERATIONAL"
        r.sync(5)
        time.sleep(0.06)  # a gap of 4 x the timeout
        r.net.sync.start(0.005)  # SYNC back, and kept coming while the objects are read (a pause of 15 ms would
        try:  # be a SYNC timeout again: on a loaded host the reads take that long)
            r.emcy.wait_for(0x8100)
            r.emcy.wait_for(0x0000)
            assert r.emcy.codes().index(0x8100) < r.emcy.codes().index(0x0000)
            assert node.sdo[0x1001].raw == 0 and node.sdo[0x603F].raw == 0
        finally:
            r.net.sync.stop()
        time.sleep(0.03)  # the SYNCs stop: 0x8100 again, cleared by switching SYNC monitoring off
        node.sdo[0x1006].raw = 0
        assert node.sdo[0x1001].raw == 0 and node.sdo[0x603F].raw == 0
        # heartbeat consumer: master 0x7F every 20 ms, monitored with 100 ms; lost, then back
        node.sdo[0x1016][1].raw = (0x7F << 16) | 100
        for _ in range(5):
            r.net.send_message(0x77F, b"\x05")
            time.sleep(0.02)
        n0 = len(r.emcy.codes())
        r.wait(lambda: 0x8130 in r.emcy.codes()[n0:], timeout=2.0)
        assert node.sdo[0x1001].raw & 0x10
        r.net.send_message(0x77F, b"\x05")
        r.wait(lambda: 0x0000 in r.emcy.codes()[n0 + 1:], timeout=2.0)
        assert node.sdo[0x1001].raw == 0 and node.sdo[0x603F].raw == 0
        node.sdo[0x1016][1].raw = 0
        # a fault, then a SYNC gap: 0x603F keeps the fault's code; the SYNC back sends no error reset
        node.sdo[0x1006].raw = 10_000
        node.nmt.state = "OPERATIONAL"  # (the heartbeat loss took the node to PRE-OPERATIONAL, 0x1029)
        r.sync(3)
        node.sdo[0x2010].raw = 0x3220  # injected DC-link undervoltage
        r.emcy.wait_for(0x3220)
        r.wait(lambda: r.sw() & 0x4F == 0x08, sync=True)  # FAULT
        n1 = len(r.emcy.codes())
        time.sleep(0.06)
        r.sync(5)
        assert 0x8100 in r.emcy.codes()[n1:]
        assert node.sdo[0x603F].raw == 0x3220
        assert 0x0000 not in r.emcy.codes()[n1:]
        assert node.sdo[0x1001].raw & 0x10 == 0 and node.sdo[0x1001].raw != 0  # the fault's bits stay
        node.sdo[0x2010].raw = 0  # clear the injected fault, then reset it: EMCY 0x0000, all clear
        node.sdo[0x6040].raw = 0x80
        r.sync(3)
        r.wait(lambda: 0x0000 in r.emcy.codes()[n1:], timeout=2.0)
        assert node.sdo[0x1001].raw == 0 and node.sdo[0x603F].raw == 0
    finally:
        r.close()


def _rpdo_deadline_rig() -> Rig:
    """OPERATIONAL, RPDO2 with a 30 ms deadline and no drive reaction to it (0x6007 = 0: only the stack's EMCY)."""
    r = Rig()
    r.node.sdo[0x6007].raw = 0
    r.node.sdo[0x1401][5].raw = 30
    r.node.nmt.state = "OPERATIONAL"
    return r


def test_rpdo_deadline_and_pdo_length_errors_never_hide_the_fault_code_and_clear_0x603f():
    """The rule of docs/canopen.md for every communication EMCY, not only 0x81xx (before: the RPDO deadline
    0x8250 and a short RPDO 0x8210 replaced a fault's 0x3220 in 0x603F, and after the RPDO came back 0x603F
    kept 0x8250 while 0x1001 read 0): a communication error takes 0x603F only while the application has no
    error of its own, and its clearing resets 0x603F with 0x1001."""
    r = _rpdo_deadline_rig()
    try:
        node = r.node
        _raw_rpdo2(r, 0x06, 0)
        r.emcy.wait_for(0x8250)
        assert node.sdo[0x603F].raw == 0x8250 and node.sdo[0x1001].raw == 0x11
        n0 = len(r.emcy.codes())
        _raw_rpdo2(r, 0x06, 0)  # the RPDO is back: error reset
        r.wait(lambda: 0x0000 in r.emcy.codes()[n0:], timeout=2.0)
        assert node.sdo[0x1001].raw == 0 and node.sdo[0x603F].raw == 0
        # in FAULT: neither the deadline nor a short RPDO replaces the fault's code
        node.sdo[0x2010].raw = 0x3220
        r.emcy.wait_for(0x3220)
        r.wait(lambda: r.sw() & 0x4F == 0x08, sync=True)
        n1 = len(r.emcy.codes())
        r.wait(lambda: 0x8250 in r.emcy.codes()[n1:], timeout=2.0)
        r.net.send_message(0x300 + node.id, b"\x06")  # 1 byte of a 6-byte RPDO: EMCY 0x8210
        r.wait(lambda: 0x8210 in r.emcy.codes()[n1:], timeout=2.0)
        assert node.sdo[0x603F].raw == 0x3220
        assert node.sdo[0x1003][1].raw & 0xFFFF in (0x8210, 0x8250)  # the history has them all
        node.sdo[0x1401][5].raw = 0
    finally:
        r.close()


def test_a_fault_reset_while_a_communication_error_lasts_sends_no_error_reset():
    """CiA 301: EMCY 0x0000 says no error is left. A fault reset that acknowledges the drive's fault while a
    communication error lasts (an RPDO deadline) leaves 0x1001 = 0x11 and 0x603F = that error's code and sends
    no EMCY (a docs-only master's case: a SYNC loss in PRE-OPERATIONAL got EMCY 0x0000 with register 0x11); the
    EMCY 0x0000 goes out when the communication error clears too."""
    r = _rpdo_deadline_rig()
    try:
        node = r.node
        node.sdo[0x2010].raw = 0x3220  # an injected DC-link undervoltage: FAULT
        r.emcy.wait_for(0x3220)
        r.wait(lambda: r.sw() & 0x4F == 0x08, sync=True)
        _raw_rpdo2(r, 0x00, 0)
        n0 = len(r.emcy.codes())
        r.wait(lambda: 0x8250 in r.emcy.codes()[n0:], timeout=2.0)  # the RPDO stays away: deadline error
        node.sdo[0x2010].raw = 0  # the fault's cause gone; fault reset
        node.nmt.state = "PRE-OPERATIONAL"
        node.sdo[0x6040].raw = 0x80
        r.wait(lambda: r.sw() & 0x4F == 0x40, timeout=2.0)  # SWITCH ON DISABLED
        time.sleep(0.1)
        assert 0x0000 not in r.emcy.codes()[n0:], [hex(c) for c in r.emcy.codes()[n0:]]
        assert node.sdo[0x1001].raw == 0x11 and node.sdo[0x603F].raw == 0x8250
        node.nmt.state = "OPERATIONAL"
        n1 = len(r.emcy.codes())
        _raw_rpdo2(r, 0x00, 0)  # the RPDO is back: now nothing is left
        r.wait(lambda: 0x0000 in r.emcy.codes()[n1:], timeout=2.0)
        assert node.sdo[0x1001].raw == 0 and node.sdo[0x603F].raw == 0
        node.sdo[0x1401][5].raw = 0
    finally:
        r.close()


def test_every_target_the_default_software_limits_allow_is_reached_without_a_limit_switch():
    """Item 5 / a docs-only master: with the defaults, 0x607D lies inside the hardware limit switches (before:
    +-300 mm with the switches at +-298 mm, so a PP move to the legal target 300000 faulted 0xFF11). A PP
    target beyond the limit is clamped to it (bit 11, 0x2110:3) and reached at full profile speed, no fault."""
    r = Rig()
    try:
        node = r.node
        lo, hi = node.sdo[0x607D][1].raw, node.sdo[0x607D][2].raw
        neg_m, pos_m, _ = r.drive._switch_at_m
        assert neg_m * 1e6 < lo < hi < pos_m * 1e6
        _start(r, 1, **{"0x6081": node.sdo[0x607F].raw, "0x6083": 5_000_000, "0x6084": 5_000_000})
        clamped0 = node.sdo[0x2110][3].raw
        node.sdo[0x607A].raw = 400_000
        node.sdo[0x6040].raw = 0x1F
        node.sdo[0x6040].raw = 0x0F
        r.wait(lambda: r.sw() & 0x400 or r.sw() & 0x08, sync=True, timeout=20)
        assert not r.sw() & 0x08, [hex(c) for c in r.emcy.codes()]  # no fault
        assert abs(node.sdo[0x6064].raw - hi) <= 50
        assert node.sdo[0x2110][3].raw == clamped0 + 1 and node.sdo[0x60FD].raw & 0x3 == 0
    finally:
        r.close()


def test_csp_at_the_default_max_motor_speed_brakes_after_the_limit_switch_before_the_end_stop():
    """A docs-only master ran CSP at the default 0x6080 (3000/min x 16 mm = 0.8 m/s; 0x607F does not limit
    CSP) into the + switch: it reached 7 mm into the end-stop buffer, which was sized for 0.5 m/s. The end stops
    are now sized for the fastest speed the defaults allow: the quick stop (0x6085 = 5 m/s^2) ends before the
    buffer, fault 0xFF11."""
    r = Rig({1: (seed_config(), 0.15)})
    try:
        node = r.node
        v_max_um_s = node.sdo[0x6080].raw / 60.0 * r.drive.cfg.mechanics.lead_m * 1e6
        _start(r, 8, **{"0x6085": 5_000_000})
        node.sdo[0x607D][1].raw = 0  # software limits off
        node.sdo[0x607D][2].raw = 0
        x = float(node.sdo[0x6064].raw)
        v = 0.0
        peak = -1.0
        for _ in range(2000):
            v = min(v_max_um_s, v + 5_000_000 * 1e-3)  # 5 m/s^2 up to 0x6080
            x += v * 1e-3
            _raw_rpdo2(r, 0x0F, int(x))
            r.sync(1)
            peak = max(peak, r.drive.state.table_position_m)
            if r.sw() & 0x4F == 0x08:
                break
        r.sync(300)
        peak = max(peak, r.drive.state.table_position_m)
        _, hi, _, _, _, _ = end_stops(r.drive.cfg)
        assert 0xFF11 in r.emcy.codes()
        assert r.drive.cfg.axis.stroke_m / 2 - 0.002 < peak < hi, (peak, hi)  # past the switch, not in the buffer
        assert abs(v_max_um_s - 800_000) < 1_000  # the run was at the full default speed
    finally:
        r.close()


def _halt_distance_um(r: Rig, mode: int, option: int) -> tuple[int, int]:
    """Moving at 100 mm/s in ``mode`` (PV, PP or HM method 18), halt (controlword bit 8) with 0x605D =
    ``option`` by SDO: (travel of the demand at the halt to rest [um], statusword at rest)."""
    node = r.node
    node.sdo[0x605D].raw = option
    if mode == 3:
        node.sdo[0x60FF].raw = 100_000
    elif mode == 1:
        node.sdo[0x607A].raw = 200_000
        node.sdo[0x6040].raw = 0x1F
        node.sdo[0x6040].raw = 0x0F
    else:
        node.sdo[0x6098].raw = 18
        node.sdo[0x6099][1].raw = 100_000  # search speed 100 mm/s
        node.sdo[0x6040].raw = 0x1F
    r.sync(300)
    assert abs(node.sdo[0x606C].raw - 100_000) < 2_000
    x0 = node.sdo[0x6064].raw + (node.sdo[0x60F4].raw if mode != 3 else 0)  # from the position demand
    node.sdo[0x6040].raw = node.sdo[0x6040].raw | 0x100
    r.sync(300)
    assert abs(node.sdo[0x606C].raw) < 200
    return node.sdo[0x6064].raw - x0, r.sw()


@pytest.mark.parametrize("mode", [3, 1, 6])
def test_halt_brakes_with_the_ramp_0x605d_names_in_every_profile_mode(mode):
    """CiA 402 0x605D: 1 slow-down ramp (PV / PP 0x6084, HM the homing acceleration 0x609A), 2 quick-stop ramp
    0x6085, 3 current limit. Found by a docs-only master: option 3 braked like 2, and homing braked with
    0x609A whatever the option. The halted axis shows bit 10 and moves on when bit 8 clears (PV / PP)."""
    travel = {}
    for option in (1, 2, 3):
        r = Rig()
        try:
            _start(r, mode, **{"0x6083": 5_000_000, "0x6084": 5_000_000, "0x6085": 10_000_000,
                               "0x609A": 500_000, "0x6081": 100_000})
            travel[option], sw = _halt_distance_um(r, mode, option)
            assert sw & 0x6F == 0x27 and sw & 0x400, hex(sw)  # OPERATION ENABLED, halted: target reached
            if mode != 6:  # released: the move goes on (homing was interrupted by the halt)
                node = r.node
                node.sdo[0x6040].raw = 0x0F
                r.sync(100)
                assert node.sdo[0x606C].raw > 50_000
        finally:
            r.close()
    slow = 0.1**2 / (2 * (0.5 if mode == 6 else 5.0)) * 1e6
    quick = 0.1**2 / (2 * 10.0) * 1e6
    assert 0.9 * slow < travel[1] < 1.3 * slow + 200, travel
    assert 0.9 * quick < travel[2] < 1.3 * quick + 200, travel
    assert travel[3] < 0.9 * quick, travel  # the current limit brakes harder than 10 m/s^2 here


def test_quick_stop_options_5_to_8_show_target_reached_once_halted():
    """CiA 402 statusword bit 10: with quick stop option 5..8, set when the quick stop has finished and the
    drive is halted (QUICK STOP ACTIVE), in every mode; 0 while it brakes. Found by a docs-only master: PP
    and PV read 0x0217 at rest. PV's bit 12 (speed = 0) is also shown there."""
    for mode in (1, 3, 8):
        r = Rig()
        try:
            _start(r, mode, **{"0x605A": 6, "0x6085": 5_000_000, "0x6083": 5_000_000, "0x6081": 100_000})
            node = r.node
            x = node.sdo[0x6064].raw
            if mode == 3:
                node.sdo[0x60FF].raw = 100_000
            elif mode == 1:
                node.sdo[0x607A].raw = x + 200_000
                node.sdo[0x6040].raw = 0x1F
                node.sdo[0x6040].raw = 0x0F
            for i in range(200):
                if mode == 8:
                    x += min(100, i + 1)
                    _raw_rpdo2(r, 0x0F, x)
                r.sync(1)
            node.sdo[0x6040].raw = 0x0B  # quick stop
            r.sync(1)
            braking = r.sw()
            assert braking & 0x6F == 0x07 and not braking & 0x400, hex(braking)
            r.sync(200)
            sw = r.sw()
            assert sw & 0x6F == 0x07 and sw & 0x400, (mode, hex(sw))
            assert bool(sw & 0x1000) == (mode == 3), (mode, hex(sw))  # PV: speed = 0; PP / CSP: no set-point
        finally:
            r.close()


def test_csp_shutdown_sent_in_every_rpdo_ramps_down_with_0x6084_and_ignores_the_targets():
    """A CSP master sends the shutdown controlword in its cyclic RPDO, i.e. again at every SYNC: the stop
    runs once from the actual speed with 0x6084 (before: restarted at every RPDO, 4.2 mm instead of 2.5 mm
    at 100 mm/s and 2 m/s^2), and bit 12 reads 0 while the targets are ignored."""
    for cw in (0x06, 0x07):
        r = Rig()
        try:
            _start(r, 8, **{"0x605B": 1, "0x605C": 1, "0x6084": 2_000_000})
            node = r.node
            x = node.sdo[0x6064].raw
            for i in range(300):
                x += min(100, i + 1)
                _raw_rpdo2(r, 0x0F, x)
                r.sync(1)
            x0 = node.sdo[0x6064].raw
            bits12 = []
            for _ in range(60):
                _raw_rpdo2(r, cw, x)  # the master holds its last target and repeats the controlword
                r.sync(1)
                sw = r.sw()
                if sw & 0x6F == 0x27:
                    bits12.append(sw & 0x1000)
            for _ in range(1000):  # at standstill (|v| < 0.1 mm/s) and held: ready to switch on / switched on
                _raw_rpdo2(r, cw, x)
                r.sync(1)
                if r.sw() & 0x6F != 0x27:
                    break
            travel_mm = (node.sdo[0x6064].raw - x0) * UNIT_M * 1e3
            assert 2.2 < travel_mm < 3.0, travel_mm  # v^2/2a = 2.5 mm
            assert bits12 and not any(bits12), bits12
            assert r.sw() & 0x6F == (0x21 if cw == 0x06 else 0x23), hex(r.sw())
        finally:
            r.close()
