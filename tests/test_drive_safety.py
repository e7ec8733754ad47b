"""Legal object values never make the axis unsafe, through a real ``canopen`` master: a torque / current limit
of 0 is zero torque, a stop is bounded in time and distance whatever 0x6084 / 0x6085 hold (monitored ramp,
fallback to the current limit, braking-failed fault), a jerk-limited set-point that cannot be planned is
refused (SDO abort, EMCY) instead of stalling the drive, and an illegal controlword repeated is ignored and
counted. The headline cases run against ``virtualaxis serve`` in another process (udp_multicast, hop_limit 0);
the rest on the in-process ``virtual`` bus (tests/test_drive_rig.py)."""

from __future__ import annotations

import math
import time

import canopen
import pytest
from served_drive import served
from test_drive_rig import Rig

from virtualaxis.drive.core import DEFAULT_EDS
from virtualaxis.master import connect
from virtualaxis.plant.mechanics import reflected_inertia_kg_m2

NODE = 1
UNIT_M = 1e-6


def _master(spec: str) -> tuple[canopen.Network, canopen.BaseNode402]:
    net = connect(spec)
    node = canopen.BaseNode402(NODE, str(DEFAULT_EDS))
    node.sdo.RESPONSE_TIMEOUT = 2.0
    net.add_node(node)
    return net, node


def _enable(node: canopen.BaseNode402) -> None:
    for cw, expect in ((0x06, 0x21), (0x07, 0x23), (0x0F, 0x27)):
        node.sdo[0x6040].raw = cw
        end = time.monotonic() + 2
        while node.sdo[0x6041].raw & 0x6F != expect:
            assert time.monotonic() < end, hex(node.sdo[0x6041].raw)
            time.sleep(0.005)


def _wait(predicate, timeout_s: float = 5.0):
    end = time.monotonic() + timeout_s
    while not (value := predicate()):
        assert time.monotonic() < end, "condition not reached in time"
        time.sleep(0.01)
    return value


def _emcy_codes(node: canopen.BaseNode402) -> list[int]:
    return [e.code for e in node.emcy.log]


@pytest.fixture(scope="module")
def served_node():
    """One ``virtualaxis serve`` process for the cross-process tests of this module, and a master for it."""
    with served("--duration", "300") as s:
        net, node = _master(s.spec)
        try:
            yield net, node
        finally:
            net.disconnect()
    assert s.returncode == 0, s.stderr[-2000:]


def _reset_node(node: canopen.BaseNode402) -> None:
    """NMT reset node (objects back to their defaults, the axis at rest where it stands), then OPERATIONAL."""
    node.nmt.state = "RESET"
    time.sleep(0.2)
    end = time.monotonic() + 10.0
    while True:  # (polled: a boot-up message sent before wait_for_bootup starts listening would be missed)
        try:
            if node.sdo[0x6041].raw & 0x6F == 0x40 and node.sdo[0x6060].raw == 0:
                break
        except canopen.SdoError:
            pass
        assert time.monotonic() < end, "the drive did not come back after NMT reset node"
        time.sleep(0.05)
    node.nmt.state = "OPERATIONAL"
    time.sleep(0.05)


def test_served_illegal_controlword_repeated_is_ignored_and_counted(served_node):
    """0x6040 = 0x0F twice in SWITCH ON DISABLED (no transition there) by SDO, then twice by RPDO: no SDO
    abort, no internal error (0x2100:25), counted once in 0x2110:1, statusword 0x0250; a shutdown still works."""
    net, node = served_node
    _reset_node(node)
    internal0 = node.sdo[0x2100][25].raw
    for _ in range(2):
        node.sdo[0x6040].raw = 0x0F
    for _ in range(2):
        net.send_message(0x200 + NODE, (0x0F).to_bytes(2, "little"))
        time.sleep(0.05)
    assert node.sdo[0x6041].raw == 0x0250
    assert node.sdo[0x2110][1].raw == 1
    assert node.sdo[0x2100][25].raw == internal0
    node.sdo[0x6040].raw = 0x06
    _wait(lambda: node.sdo[0x6041].raw & 0x6F == 0x21)


def test_served_jerk_set_point_that_cannot_be_planned_is_refused(served_node):
    """PP with 0x6086 = 3 and 0x60A4 = 10 (T_j = 1 m/s^2 / 10 um/s^3 = 1e5 s): the new set-point by SDO is
    refused with abort 0x08000022 at once, by RPDO with EMCY 0x6320; neither is acknowledged (bit 12), the drive
    keeps answering, and with a jerk it can plan (T_j = 10 ms) the next set-point moves the axis."""
    net, node = served_node
    _reset_node(node)
    node.sdo[0x6060].raw = 1
    node.sdo[0x6086].raw = 3
    node.sdo[0x60A4][1].raw = 10
    _enable(node)
    x0 = node.sdo[0x6064].raw
    node.sdo[0x607A].raw = x0 + 10_000
    t0 = time.monotonic()
    with pytest.raises(canopen.SdoAbortedError) as exc:
        node.sdo[0x6040].raw = 0x1F
    assert exc.value.code == 0x08000022
    assert time.monotonic() - t0 < 2.0
    node.sdo[0x6040].raw = 0x0F
    n_emcy = len(node.emcy.log)
    target = (x0 + 20_000).to_bytes(4, "little", signed=True)
    net.send_message(0x300 + NODE, bytes([0x1F, 0x00]) + target)
    _wait(lambda: 0x6320 in _emcy_codes(node)[n_emcy:])
    assert not node.sdo[0x6041].raw & 0x1000  # not acknowledged
    net.send_message(0x300 + NODE, bytes([0x0F, 0x00]) + target)
    node.sdo[0x60A4][1].raw = 100_000_000
    node.sdo[0x6040].raw = 0x1F
    _wait(lambda: abs(node.sdo[0x6064].raw - (x0 + 20_000)) < 50)


def test_served_quick_stop_with_the_smallest_deceleration_ends_before_the_limit_switch(served_node):
    """PV at 197 mm/s toward the + limit switch with 0x6085 = 1 (1 um/s^2), quick stop (0x605A = 2): the axis is
    at rest in SWITCH ON DISABLED within seconds, before the limit switch (the ramp as configured would take
    2e5 s)."""
    net, node = served_node
    _reset_node(node)
    node.sdo[0x6060].raw = 3
    node.sdo[0x6083].raw = 2_000_000
    node.sdo[0x6085].raw = 1
    node.sdo[0x605A].raw = 2
    if node.sdo[0x6064].raw > 100_000:  # room for the run: back toward the middle first
        _enable(node)
        node.sdo[0x60FF].raw = -197_000
        _wait(lambda: node.sdo[0x6064].raw < 0, timeout_s=10.0)
        node.sdo[0x6040].raw = 0x06
        _wait(lambda: node.sdo[0x6041].raw & 0x6F == 0x21, timeout_s=12.0)
    node.sdo[0x60FF].raw = 197_000
    _enable(node)
    _wait(lambda: abs(node.sdo[0x606C].raw - 197_000) < 5_000)
    node.sdo[0x6040].raw = 0x02
    _wait(lambda: node.sdo[0x6041].raw & 0x6F == 0x40, timeout_s=12.0)
    assert abs(node.sdo[0x606C].raw) < 1_000
    assert not node.sdo[0x60FD].raw & 0x3  # stopped before the limit switch


def test_served_torque_limit_zero_is_zero_torque(served_node):
    """PV at -50 mm/s against 0x2011 = 3 kN (0.4 x rated current to hold it), then 0x6072 = 0: the motor current
    0x6078 is zero while the force pushes the axis away (a limit of 0 was "no limit": it held the speed)."""
    net, node = served_node
    _reset_node(node)
    node.sdo[0x6060].raw = 3
    node.sdo[0x6083].raw = 2_000_000
    node.sdo[0x60FF].raw = -50_000
    _enable(node)
    _wait(lambda: abs(node.sdo[0x606C].raw + 50_000) < 2_000)
    node.sdo[0x2011].raw = 3_000.0
    time.sleep(0.2)
    assert abs(node.sdo[0x6078].raw) > 200  # holds the speed
    node.sdo[0x6072].raw = 0
    time.sleep(0.02)
    currents = [node.sdo[0x6078].raw for _ in range(3)]
    node.sdo[0x2011].raw = 0.0
    assert max(abs(c) for c in currents) <= 5, currents  # per mille of rated current: the current loop's error


def _start_pv(r: Rig, speed_units_s: int, **objects: int) -> None:
    node = r.node
    node.sdo[0x6083].raw = 2_000_000
    for index, value in objects.items():
        node.sdo[int(index, 16)].raw = value
    node.sdo[0x6060].raw = 3
    node.nmt.state = "OPERATIONAL"
    r.enable()
    node.sdo[0x60FF].raw = speed_units_s
    r.sync(400)


@pytest.mark.parametrize(("limit", "value"), [("0x6072", 0), ("0x6073", 0), ("0x6075", 1), ("0x6076", 1)])
def test_a_torque_or_current_limit_of_zero_is_zero_torque(limit, value):
    """PV at 50 mm/s against 10 kN (1.4 x rated current to hold it), then the torque or current limit set to 0,
    or the rated current / torque they are per mille of set to 1 mA / 1 mN m (limits of a few mA): no current
    beyond those, the force pushes the axis back (it no longer holds the speed)."""
    r = Rig()
    try:
        node = r.node
        _start_pv(r, 50_000)
        node.sdo[0x2011].raw = -10_000.0
        r.sync(200)
        assert abs(node.sdo[0x6078].raw) > 1000
        node.sdo[int(limit, 16)].raw = value
        r.sync(5)
        peak = 0.0
        for _ in range(20):
            r.sync(5)
            peak = max(peak, abs(r.drive.state.current_a))
        # zero within the current loop's tracking error (5 per mille of rated current; it held 1400 per mille)
        assert peak < 0.005 * r.drive.cfg.motor.rated_current_a, peak
        assert node.sdo[0x606C].raw < 40_000  # the force, not the motor, sets the motion now
    finally:
        r.close()


def test_slow_stop_ramp_is_bounded_in_time_and_ends_before_the_limit_switch():
    """0x6084 = 1 (1 um/s^2) and shutdown with 0x605B = 1 at 197 mm/s, 0.2 m before the + switch: the ramp is
    steepened to end before the switch (<= 0.8 x the room), the drive is in READY TO SWITCH ON within the ramp's
    bound; torque within 0x6072."""
    r = Rig()
    try:
        node = r.node
        _start_pv(r, 197_000, **{"0x6084": 1_000_000, "0x605B": 1})
        node.sdo[0x6084].raw = 1
        x0 = r.drive.state.table_position_m
        switch_m = r.drive.cfg.axis.stroke_m / 2 - r.drive.settings.limit_switch_inset_m
        node.sdo[0x6040].raw = 0x06
        torque_limit_nm = node.sdo[0x6072].raw / 1000 * node.sdo[0x6076].raw / 1000
        peak_nm = 0.0
        cycles = 0
        while cycles < 6000 and r.sw() & 0x6F != 0x21:
            r.sync(1)
            cycles += 1
            peak_nm = max(peak_nm, abs(r.drive.state.current_a) * r.drive.cfg.motor.kt_nm_per_a)
        s = r.drive.state
        assert s.cia402_state == "READY TO SWITCH ON", (cycles, s.cia402_state)
        assert s.table_position_m < switch_m
        assert s.table_position_m - x0 < 0.8 * (switch_m - x0) + 0.005
        assert peak_nm <= torque_limit_nm * 1.02
    finally:
        r.close()


def test_a_stop_ramp_the_axis_cannot_follow_falls_back_to_the_current_limit_before_the_end_stop():
    """0x6072 = 300 (0.3 x rated torque: ~1.6 m/s^2 on the seed axis), 0x6085 = 1 (1 um/s^2), quick stop at
    197 mm/s 5 mm before the + limit switch: the ramp, steepened to end before the switch (~4.9 m/s^2), is not
    followed; within 20 ms the stop brakes at the torque limit and the axis is at rest before the end stop,
    in SWITCH ON DISABLED, the torque within 0x6072 throughout."""
    from test_drive_rig import seed_config

    from virtualaxis.sim.simulator import end_stops

    cfg = seed_config()
    switch_m = cfg.axis.stroke_m / 2 - 0.002
    r = Rig({1: (cfg, switch_m - 0.15)})
    try:
        node = r.node
        _start_pv(r, 0, **{"0x605A": 2, "0x6085": 1, "0x6072": 300})
        node.sdo[0x60FF].raw = 197_000
        while r.drive.state.table_position_m < switch_m - 0.005:
            r.sync(1)
        node.sdo[0x6040].raw = 0x02
        limit_nm = 0.3 * node.sdo[0x6076].raw / 1000
        peak_nm, peak_x, cycles = 0.0, 0.0, 0
        while r.drive.state.cia402_state != "SWITCH ON DISABLED" and cycles < 2000:
            r.sync(1)
            cycles += 1
            s = r.drive.state
            peak_nm = max(peak_nm, abs(s.current_a) * cfg.motor.kt_nm_per_a)  # from the current: 0x6077 shows <= 0x6072
            peak_x = max(peak_x, s.table_position_m)
        assert r.drive.state.cia402_state == "SWITCH ON DISABLED", (cycles, r.drive.state.cia402_state)
        assert peak_x < end_stops(cfg)[1], peak_x
        assert peak_nm <= limit_nm * 1.02, (peak_nm, limit_nm)  # (the current loop overshoots for a cycle)
    finally:
        r.close()


def test_modbus_current_limit_register_zero_is_zero_torque():
    """Register 40321 (current limit, 0.1 A, 0x6073) written 0 by a pymodbus client while PV holds 50 mm/s
    against 10 kN: the motor current (40355 = 0x6078, per mille) goes to zero (it stayed at 1.4 x rated)."""
    from test_services_modbus import Server, make_drive

    drive = make_drive()
    server = Server({1: drive})
    try:
        for index, value in ((0x6083, 2_000_000), (0x6060, 3)):
            drive.write_object(index, 0, value)
        for cw in (6, 7, 0xF):
            drive.set_controlword(cw)
        drive.write_object(0x60FF, 0, 50_000)
        drive.step(300)
        drive.write_object(0x2011, 0, -10_000.0)
        drive.step(200)
        assert abs(server.read(40355)[0] - 0x10000 * (server.read(40355)[0] >> 15)) > 1000
        assert not server.client.write_register(40321 - 40001, 0, device_id=1).isError()
        drive.step(5)  # (the current loop brings the current down within a few cycles)
        peak_a = 0.0
        for _ in range(50):
            drive.step(1)
            peak_a = max(peak_a, abs(drive.state.current_a))
        assert server.read(40355)[0] in (0, 1, 2, 3, 4, 5, 0xFFFF, 0xFFFE, 0xFFFD, 0xFFFC, 0xFFFB)  # per mille
        assert peak_a < 0.005 * drive.cfg.motor.rated_current_a, peak_a  # zero within the current loop's error
    finally:
        server.close()


def _gain_bounds_from_config(cfg) -> tuple[float, float, float]:
    """The bounds of docs/drive.md ("Loop-gain bounds") from the axis config: speed Kp max [N m s/rad], Kv max
    [1000/min], Tn min [ms]."""
    c = cfg.control
    w_n = min(c.current_kp_v_per_a / cfg.motor.lq_h, math.pi / c.speed_cycle_s) / 2
    kv_per_s = min(w_n, math.pi / c.position_cycle_s) / 4
    return w_n * reflected_inertia_kg_m2(cfg), kv_per_s * 60 / 1000, 4 / w_n * 1000


def _abort_code(node: canopen.BaseNode402, index: int, value: float) -> int | None:
    try:
        node.sdo[index].raw = value
    except canopen.SdoAbortedError as exc:
        return exc.code
    return None


def test_loop_gains_beyond_what_the_cascade_follows_are_refused_and_those_accepted_keep_the_torque_limit():
    """Speed Kp 0x2003, Kv 0x2000 and Tn 0x2004 inside the EDS range but beyond the axis' cascade (speed-loop
    crossover above half the current loop's bandwidth, Kv above a quarter of it, Tn below 4 / crossover) are
    refused with 0x06090031 / 0x06090032 and leave the value as it was; at the bounds the axis at 200 mm/s
    quick-stops with the motor torque within 0x6072."""
    r = Rig()
    try:
        node = r.node
        kp_max, kv_max, tn_min_ms = _gain_bounds_from_config(r.drive.cfg)
        kp0, kv0, tn0 = node.sdo[0x2003].raw, node.sdo[0x2000].raw, node.sdo[0x2004].raw
        for index, value, code in ((0x2003, 1000.0, 0x06090031), (0x2003, 1e6, 0x06090031),
                                   (0x2003, kp_max * 1.01, 0x06090031), (0x2000, kv_max * 1.01, 0x06090031),
                                   (0x2000, 2000.0, 0x06090031), (0x2004, tn_min_ms * 0.99, 0x06090032),
                                   (0x2004, 1e-3, 0x06090032)):
            assert _abort_code(node, index, value) == code, (hex(index), value)
        assert (node.sdo[0x2003].raw, node.sdo[0x2000].raw, node.sdo[0x2004].raw) == (kp0, kv0, tn0)
        assert _abort_code(node, 0x2004, 0.0) is None  # 0: a P-only speed loop
        _start_pv(r, 200_000)
        for index, value in ((0x2003, kp_max * 0.99), (0x2000, kv_max * 0.99), (0x2004, tn_min_ms * 1.01)):
            assert _abort_code(node, index, value) is None, (hex(index), value)
        r.sync(50)
        torque_limit_nm = node.sdo[0x6072].raw / 1000 * node.sdo[0x6076].raw / 1000
        node.sdo[0x6040].raw = 0x02
        peak_nm, cycles = 0.0, 0
        while cycles < 2000 and abs(r.drive.state.velocity_actual_m_s) > 1e-3 or cycles < 50:
            r.sync(1)
            cycles += 1
            peak_nm = max(peak_nm, abs(r.drive.state.current_a) * r.drive.cfg.motor.kt_nm_per_a)
        assert cycles < 2000, "not at rest"
        assert 0 < peak_nm <= torque_limit_nm, (peak_nm, torque_limit_nm)
    finally:
        r.close()
