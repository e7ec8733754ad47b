"""Monitoring and faults through a real master: following error (24), software limits (25), plant faults
and EMCY (26), heartbeat loss and RPDO timeout reactions (4, 0x6007), motor temperature, NMT reset node."""

from __future__ import annotations

import time

import pytest
from nmt_wait import reset_and_wait_for_bootup
from test_drive_rig import Rig, rig  # noqa: F401  (fixture)


def _csp(r: Rig) -> None:
    node = r.node
    node.sdo[0x6060].raw = 8
    node.rpdo.read()
    node.rpdo[2].trans_type = 1  # controlword + target position, synchronous
    node.rpdo[2].save()
    node.nmt.state = "OPERATIONAL"
    r.enable()


def _send_target(r: Rig, target: int, cw: int = 0x0F) -> None:
    rpdo = r.node.rpdo[2]
    rpdo["Controlword"].raw = cw
    rpdo["Target position"].raw = target
    rpdo.transmit()


def test_following_error_fault_and_reset(rig):  # noqa: F811
    """24: |0x60F4| > 0x6065 for longer than 0x6066 ms -> bit 13, fault, EMCY 0x8611; reset and go on."""
    node = rig.node
    node.sdo[0x6065].raw = 200  # 200 um
    node.sdo[0x6066].raw = 5  # 5 ms
    _csp(rig)
    sws = []
    node.tpdo[1].add_callback(lambda m: sws.append(m["Statusword"].raw))
    x = 0
    for _ in range(200):  # ramp at 0.2 m/s: v/Kv = 1.7 mm >> 200 um
        x += 200
        _send_target(rig, x)
        rig.sync(1)
        if rig.sw() & 0x4F == 0x08:
            break
    assert rig.sw() & 0x4F == 0x08
    _, code, register, data = rig.emcy.wait_for(0x8611)
    assert register & 0x21 == 0x21  # generic + device profile
    assert int.from_bytes(data[0:4], "little", signed=True) > 200  # fault value: the following error
    assert node.sdo[0x603F].raw == 0x8611
    assert rig.sw() & 0x2000  # bit 13 shows the following error
    assert node.sdo[0x2030][1].raw == 7452
    # reset: bit 7 edge -> switch on disabled, EMCY 0x0000; the axis can be enabled and moved again
    node.sdo[0x6040].raw = 0x00
    node.sdo[0x6040].raw = 0x80
    assert rig.sw() & 0x4F == 0x40
    rig.emcy.wait_for(0x0000)
    assert node.sdo[0x603F].raw == 0
    here = node.sdo[0x6064].raw
    _send_target(rig, here, 0x06)
    rig.sync(2)
    rig.enable()
    for k in range(1, 50):
        _send_target(rig, here + 2 * k)
        rig.sync(1)
    assert rig.sw() & 0x6F == 0x27


def test_short_following_error_excursion_within_the_time_out_is_tolerated(rig):  # noqa: F811
    """24: exceeding the window for less than 0x6066 does not fault."""
    node = rig.node
    node.sdo[0x6065].raw = 300
    node.sdo[0x6066].raw = 200
    _csp(rig)
    _send_target(rig, 2000)  # a 2 mm step: large error for some ms, then back inside the window
    rig.sync(150)
    assert rig.sw() & 0x6F == 0x27


def test_target_beyond_software_limit_is_clamped_with_bit_11(rig):  # noqa: F811
    """25: CSP target outside 0x607D -> clamped, statusword bit 11."""
    node = rig.node
    node.sdo[0x607D][1].raw = -5_000
    node.sdo[0x607D][2].raw = 5_000
    node.sdo[0x6065].raw = 100_000
    _csp(rig)
    for k in range(1, 101):
        _send_target(rig, 100 * k)  # up to 10 mm, limit 5 mm
        rig.sync(1)
    rig.sync(300)
    assert rig.sw() & 0x800
    assert abs(node.sdo[0x6064].raw - 5_000) < 10
    assert node.sdo[0x2110][3].raw > 0  # counted
    _send_target(rig, 4_990)  # back inside (a small step: no current limit either)
    rig.sync(2)
    assert not rig.sw() & 0x800


def test_profile_position_target_beyond_limit_is_clamped(rig):  # noqa: F811
    node = rig.node
    node.sdo[0x607D][1].raw = -3_000
    node.sdo[0x607D][2].raw = 3_000
    node.sdo[0x6060].raw = 1
    node.nmt.state = "OPERATIONAL"
    rig.enable()
    node.sdo[0x607A].raw = -8_000
    node.sdo[0x6040].raw = 0x1F
    node.sdo[0x6040].raw = 0x0F
    assert rig.sw() & 0x800
    rig.wait(lambda: rig.sw() & 0x400, sync=True, timeout=10)
    assert abs(node.sdo[0x6064].raw + 3_000) <= 10


def test_target_beyond_software_limit_faults_when_configured(rig):  # noqa: F811
    """25: 0x2012 = 1 -> fault with EMCY 0x8612."""
    node = rig.node
    node.sdo[0x607D][1].raw = -5_000
    node.sdo[0x607D][2].raw = 5_000
    node.sdo[0x2012].raw = 1
    _csp(rig)
    _send_target(rig, 6_000)
    rig.sync(2)
    rig.emcy.wait_for(0x8612)
    assert rig.sw() & 0x4F == 0x08


@pytest.mark.parametrize(
    ("code", "register_bit", "fault_number"),
    [(0x2310, 0x02, 30001), (0x3210, 0x04, 30002), (0x3220, 0x04, 30003), (0x4210, 0x08, 30004), (0x7320, 0x80, 31110)],
)
def test_plant_faults_send_emcy_on_the_configured_cob_id(rig, code, register_bit, fault_number):  # noqa: F811
    """26: plant faults -> EMCY with the COB-ID of 0x1014 (moved to 0xA1 here), fault buffer entry."""
    node = rig.node
    node.sdo[0x1014].raw = 0x80000000 | 0xA1
    node.sdo[0x1014].raw = 0xA1
    seen = []
    rig.net.subscribe(0xA1, lambda cob, data, ts: seen.append(int.from_bytes(data[0:2], "little")))
    node.sdo[0x6060].raw = 8
    rig.enable()
    rig.drive.inject_fault(code)  # (the drive API, as HIL fault injection uses it)
    rig.wait(lambda: code in seen)
    rig.wait(lambda: rig.sw() & 0x4F == 0x08, sync=True)  # after the fault reaction
    assert node.sdo[0x1001].raw & register_bit
    assert node.sdo[0x2030][1].raw == fault_number
    assert rig.drive.faults[0].emcy_code == code
    rig.drive.clear_fault()
    assert rig.sw() & 0x4F == 0x40


MASTER_ID = 0x7E


def _heartbeat_rig(option: int) -> Rig:
    r = Rig()
    node = r.node
    node.sdo[0x6007].raw = option
    node.sdo[0x605A].raw = 2
    node.sdo[0x1016][1].raw = (MASTER_ID << 16) | 60  # expect the master's heartbeat every 60 ms
    node.sdo[0x6060].raw = 3
    node.sdo[0x6083].raw = 5_000_000
    node.sdo[0x60FF].raw = 20_000
    node.nmt.state = "OPERATIONAL"
    r.enable()
    return r


def _sync_with_master_heartbeat(r: Rig, n: int, every: int = 20) -> None:
    """``n`` SYNCs with the master's heartbeat before every ``every``-th: a lockstep master's heartbeat is part
    of its cycle, so it comes every ``every`` ms of drive time however fast the host runs the SYNCs."""
    for i in range(n):
        if i % every == 0:
            r.net.send_message(0x700 + MASTER_ID, b"\x05")
        r.sync(1)


def test_heartbeat_loss_faults_the_drive():
    """4: consumer heartbeat 0x1016 times out -> EMCY 0x8130 (bit 4 of 0x1001), 0x6007 = 1: fault."""
    r = _heartbeat_rig(1)
    try:
        _sync_with_master_heartbeat(r, 100)
        time.sleep(0.15)  # wall time without SYNCs is no drive time: the 60 ms have not passed
        r.sync(30)
        assert r.sw() & 0x6F == 0x27  # heartbeat present: still running
        assert 0x8130 not in r.emcy.codes()
        # the master's heartbeat stops
        # lockstep: the consumer's 60 ms are drive time, so they pass only with the SYNCs that advance it
        r.wait(lambda: 0x8130 in r.emcy.codes(), sync=True)
        r.wait(lambda: r.sw() & 0x4F == 0x08, sync=True)
        assert r.node.sdo[0x1001].raw & 0x10
        assert r.drive.faults[0].emcy_code == 0x8130
        assert r.emcy.codes().count(0x8130) == 1  # one EMCY, sent by the CiA 301 stack
    finally:
        r.close()


def test_heartbeat_loss_quick_stop_reaction():
    """4: 0x6007 = 3: quick stop (0x605A = 2: then switch on disabled) instead of a fault."""
    r = _heartbeat_rig(3)
    try:
        _sync_with_master_heartbeat(r, 50)
        assert 0x8130 not in r.emcy.codes()
        r.wait(lambda: 0x8130 in r.emcy.codes(), sync=True)  # the heartbeat stops; drive time: the SYNCs advance it
        r.wait(lambda: r.sw() & 0x4F == 0x40, sync=True, timeout=5)
        r.sync(20)
        assert abs(r.node.sdo[0x606C].raw) < 2_000
    finally:
        r.close()


def test_rpdo_timeout_faults_the_drive(rig):  # noqa: F811
    """26: RPDO deadline (0x1401:5) missed -> EMCY 0x8250, fault (0x6007 = 1)."""
    node = rig.node
    node.sdo[0x1401][5].raw = 50  # 50 ms
    _csp(rig)
    here = node.sdo[0x6064].raw
    _send_target(rig, here)
    rig.sync(2)
    assert rig.sw() & 0x6F == 0x27
    # lockstep: the 50 ms deadline is drive time, passed by the SYNCs that come without an RPDO
    rig.wait(lambda: 0x8250 in rig.emcy.codes(), sync=True)
    rig.wait(lambda: rig.sw() & 0x4F == 0x08, sync=True)


def test_motor_temperature_alarm_and_fault(rig):  # noqa: F811
    """Warning bit 7 + alarm 7910 above 0x200A; fault 0x4310 (F07011) above 0x200B."""
    node = rig.node
    node.sdo[0x200A].raw = 10.0
    rig.sync(2)
    assert rig.sw() & 0x80
    assert node.sdo[0x2031].raw == 7910
    node.sdo[0x200B].raw = 15.0
    rig.sync(2)
    rig.emcy.wait_for(0x4310)
    assert rig.sw() & 0x4F == 0x08
    assert node.sdo[0x2030][1].raw == 7011


def test_nmt_reset_node_restarts_the_application(rig):  # noqa: F811
    """3: reset node -> boot-up, application objects back to their defaults, switch on disabled."""
    node = rig.node
    default_window = node.sdo[0x6065].raw
    node.sdo[0x6065].raw = default_window + 123
    node.sdo[0x6060].raw = 8
    rig.enable()
    reset_and_wait_for_bootup(node, 2.0, send=lambda: node.nmt.send_command(0x81))
    assert node.sdo[0x6065].raw == default_window
    assert rig.sw() & 0x4F == 0x40
    assert node.sdo[0x6061].raw == 0
