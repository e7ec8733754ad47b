"""Holding brake control and safe torque off through a real ``canopen`` master: a vertical axis (the table's
weight as ``effects.force_offset_n``) held by a brake with an opening and a closing time; the drive opens it
after energising the motor and waits 0x2040 before OPERATION ENABLED, closes it at standstill and holds torque
for 0x2041 before switching off. STO (0x2042, fault injection) switches torque off at once with EMCY 0x5400 and
a restart interlock. The in-process cases run on the ``virtual`` bus in SYNC lockstep (tests/test_drive_rig.py);
the served cases against ``virtualaxis serve`` in another process (udp_multicast, hop_limit 0)."""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import canopen
import pytest
from served_drive import served
from test_drive_rig import Rig, rig, seed_config  # noqa: F401  (rig: fixture)

from virtualaxis.drive.core import DEFAULT_EDS
from virtualaxis.master import connect
from virtualaxis.runtime.axes import DEFAULT_CONFIG

G_M_S2 = 9.81
OPENING_S, CLOSING_S = 0.05, 0.03  # the brake's own opening / closing time


def vertical_config(holding_force_n: float = 3000.0, force_offset: bool = True):
    cfg = seed_config()
    weight_n = cfg.mechanics.table_mass_kg * G_M_S2
    return dataclasses.replace(cfg, effects=dataclasses.replace(
        cfg.effects, force_offset_n=weight_n if force_offset else 0.0, brake_holding_force_n=holding_force_n,
        brake_opening_time_s=OPENING_S, brake_closing_time_s=CLOSING_S))


@pytest.fixture
def vrig():
    r = Rig({1: (vertical_config(), 0.0)})
    yield r
    r.close()


def _state(r: Rig) -> int:
    return r.sw() & 0x6F


def _enable_until_operation(r: Rig) -> int:
    """Shutdown, switch on, enable by SDO; SYNCs until OPERATION ENABLED; returns the SYNCs it took."""
    node = r.node
    node.sdo[0x6040].raw = 0x06
    node.sdo[0x6040].raw = 0x07
    node.sdo[0x6040].raw = 0x0F
    n = 0
    while _state(r) != 0x27:
        assert _state(r) == 0x23, hex(r.sw())  # SWITCHED ON: holding with torque while the brake opens
        r.sync(1)
        n += 1
        assert n < 500
    return n


def _sag_after_disable_um(r: Rig, closing_delay_ms: int) -> float:
    """Enable, hold 100 ms, disable operation (0x605C = 1: ramp, then the brake sequence); how far 0x6064
    falls in the 300 ms from the disable command [um, 1 position unit = 1 um]."""
    node = r.node
    node.sdo[0x2041].raw = closing_delay_ms
    _enable_until_operation(r)
    r.sync(100)
    before = node.sdo[0x6064].raw
    node.sdo[0x6040].raw = 0x07
    r.sync(300)
    assert _state(r) == 0x23
    assert node.sdo[0x60FE][1].raw & 1 == 1  # brake applied
    return before - node.sdo[0x6064].raw


def test_no_brake_in_the_config_means_no_delays(rig):  # noqa: F811
    """The seed axis has no brake: 0x2040 / 0x2041 are 0 and enable operation is OPERATION ENABLED at once."""
    assert rig.node.sdo[0x2040].raw == 0 and rig.node.sdo[0x2041].raw == 0
    rig.enable()



def test_enable_opens_the_brake_and_waits_the_opening_delay(vrig):
    """The brake's data-sheet times are the commissioned delays (0x2040 = 50 ms, 0x2041 = 30 ms); on enable the
    drive holds the axis in SWITCHED ON with the brake output released (0x60FE:1 bit 0 = 0) for 0x2040, then
    OPERATION ENABLED; the vertical axis has not sagged (< 20 um of 0x6064)."""
    node = vrig.node
    assert node.sdo[0x2040].raw == 50 and node.sdo[0x2041].raw == 30
    assert node.sdo[0x60FE][1].raw & 1 == 1
    x0 = node.sdo[0x6064].raw
    n = _enable_until_operation(vrig)
    assert 49 <= n <= 51, n
    assert node.sdo[0x60FE][1].raw & 1 == 0
    vrig.sync(200)
    assert abs(node.sdo[0x6064].raw - x0) < 20


@pytest.mark.parametrize("delay_ms, sags", [(30, False), (5, True)])
def test_closing_delay_shorter_than_the_brake_lets_the_axis_sag(vrig, delay_ms, sags):
    """Disable with 0x2041 = the brake's closing time (30 ms): torque stays on until the brake holds; the motor
    encoder shows only the drivetrain relaxing onto the held table (< 80 um). With 0x2041 = 5 ms the torque goes
    25 ms before the brake holds: the table falls (> 300 um)."""
    sag = _sag_after_disable_um(vrig, delay_ms)
    if sags:
        assert sag > 300, sag
    else:
        assert -5 < sag < 80, sag


@pytest.mark.parametrize("delay_ms, against_brake", [(50, False), (10, True)])
def test_motion_waits_for_the_brake_opening_delay(vrig, delay_ms, against_brake):
    """PV up at 20 mm/s from the first cycle of OPERATION ENABLED. With 0x2040 = the brake's opening time the
    motor lifts the table with the torque of its weight and acceleration (0x6077 < 400 per mille 20..30 ms
    after OPERATION ENABLED). With 0x2040 = 10 ms the brake still holds for 40 ms: the motor drives against it
    (> 500 per mille) and slips it."""
    node = vrig.node
    node.sdo[0x2040].raw = delay_ms
    node.sdo[0x6060].raw = 3
    node.sdo[0x6083].raw = 2_000_000
    node.sdo[0x60FF].raw = 20_000
    _enable_until_operation(vrig)
    torques = []
    for _ in range(3):
        vrig.sync(10)
        torques.append(node.sdo[0x6077].raw)
    late = torques[1:]
    assert (min(late) > 500) if against_brake else (max(late) < 400), torques


def test_master_brake_release_refused_with_a_standing_load(vrig):
    """0x60FE:2 bit 0 gives the master the brake output: releasing it (0x60FE:1 bit 0 = 0) with the power
    stage off on the vertical axis is refused with abort 0x08000022; applying it is allowed."""
    node = vrig.node
    node.sdo[0x60FE][2].raw = 1
    with pytest.raises(canopen.SdoAbortedError) as exc:
        node.sdo[0x60FE][1].raw = 0
    assert exc.value.code == 0x08000022
    node.sdo[0x60FE][1].raw = 1
    assert node.sdo[0x60FE][1].raw & 1 == 1


def test_master_brake_release_on_a_horizontal_axis():
    """An axis with a brake and no standing load: the master may release the brake with the drive disabled
    (moving the axis by hand); an external force then moves the table, which the applied brake holds."""
    r = Rig({1: (vertical_config(force_offset=False), 0.0)})
    try:
        node = r.node
        node.sdo[0x2011].raw = -500.0  # a push on the table [N]
        r.sync(50)
        assert abs(node.sdo[0x6064].raw) < 5
        node.sdo[0x60FE][2].raw = 1
        node.sdo[0x60FE][1].raw = 0
        r.sync(100)
        assert node.sdo[0x6064].raw < -100
    finally:
        r.close()


def test_sto_switches_torque_off_with_emcy_and_restart_interlock(vrig):
    """0x2042 = 1 while enabled: from the next SYNC torque 0x6077 = 0, SWITCH ON DISABLED, statusword bits 14
    (STO) and 7 (warning), 0x60FD bit 18, brake applied, EMCY 0x5400; shutdown is ignored while it lasts.
    After 0x2042 = 0 the drive stays disabled with enable operation sent; shutdown -> switch on -> enable
    starts it again."""
    node = vrig.node
    vrig.node.sdo[0x2041].raw = 0
    _enable_until_operation(vrig)
    vrig.sync(100)
    assert node.sdo[0x6077].raw != 0  # holding the weight
    node.sdo[0x2042].raw = 1
    # before any further cycle: the statusword's STO bit 14 and 0x60FD bit 18 tell the same input
    assert node.sdo[0x6041].raw & 0x4000 and node.sdo[0x60FD].raw & (1 << 18)
    vrig.sync(1)
    assert node.sdo[0x6077].raw == 0
    sw = vrig.sw()
    assert sw & 0x4F == 0x40 and sw & 0x4000 and sw & 0x80, hex(sw)
    assert node.sdo[0x60FD].raw & (1 << 18)
    assert node.sdo[0x60FE][1].raw & 1 == 1
    assert vrig.emcy.wait_for(0x5400)[2] == 0x81  # error register: generic + manufacturer
    node.sdo[0x6040].raw = 0x06
    vrig.sync(5)
    assert vrig.sw() & 0x4F == 0x40
    node.sdo[0x2042].raw = 0
    assert not node.sdo[0x6041].raw & 0x4000 and not node.sdo[0x60FD].raw & (1 << 18)
    node.sdo[0x6040].raw = 0x0F
    vrig.sync(20)
    sw = vrig.sw()
    assert sw & 0x4F == 0x40 and not sw & 0x4000, hex(sw)
    assert not node.sdo[0x60FD].raw & (1 << 18)
    _enable_until_operation(vrig)


def test_sto_from_fault_injection(vrig):
    """Fault injection kind 11 (safe_torque_off) by 0x5FF0: the same STO reaction; clearing it (0x5FF1) leaves
    the drive disabled until the master enables it again."""
    node = vrig.node
    _enable_until_operation(vrig)
    node.sdo[0x5FF0].raw = 11
    vrig.sync(1)
    assert vrig.sw() & 0x4F == 0x40 and vrig.sw() & 0x4000
    assert node.sdo[0x6077].raw == 0
    vrig.emcy.wait_for(0x5400)
    node.sdo[0x5FF1].raw = 11
    vrig.sync(10)
    assert vrig.sw() & 0x4F == 0x40 and not vrig.sw() & 0x4000
    _enable_until_operation(vrig)


# ------------------------------------------------------------------ served in another process
def _config_file(tmp_path: Path) -> Path:
    weight_n = seed_config().mechanics.table_mass_kg * G_M_S2
    p = tmp_path / "vertical.toml"
    p.write_text(Path(DEFAULT_CONFIG).read_text() + f"""
[effects]
force_offset_n = {{ value = {weight_n:.2f}, source = "table mass x g: a vertical axis" }}
brake_holding_force_n = {{ value = 3000.0, source = "test: brake holding 2 x the weight" }}
brake_opening_time_s = {{ value = {OPENING_S}, source = "test" }}
brake_closing_time_s = {{ value = {CLOSING_S}, source = "test" }}
""")
    return p


def _master(spec: str) -> tuple[canopen.Network, canopen.BaseNode402]:
    net = connect(spec)
    node = canopen.BaseNode402(1, str(DEFAULT_EDS))
    node.sdo.RESPONSE_TIMEOUT = 2.0
    net.add_node(node)
    return net, node


def _wait(predicate, timeout_s: float = 5.0):
    end = time.monotonic() + timeout_s
    while not (value := predicate()):
        assert time.monotonic() < end, "condition not reached in time"
        time.sleep(0.005)
    return value


def test_served_brake_and_sto(tmp_path):
    """``virtualaxis serve --config`` a vertical axis with a brake: the EDS delays are commissioned from it,
    enable passes SWITCHED ON while the brake opens, the brake output follows, a disable holds the axis
    (< 80 um); STO by 0x2042 switches off with EMCY 0x5400 and the restart interlock."""
    with served("--config", str(_config_file(tmp_path)), "--duration", "120") as s:
        net, node = _master(s.spec)
        try:
            assert node.sdo[0x2040].raw == 50 and node.sdo[0x2041].raw == 30
            node.sdo[0x6040].raw = 0x06
            node.sdo[0x6040].raw = 0x07
            x0 = node.sdo[0x6064].raw
            cycles0 = node.sdo[0x2110][5].raw
            node.sdo[0x6040].raw = 0x0F
            _wait(lambda: node.sdo[0x6041].raw & 0x6F == 0x27)
            assert node.sdo[0x2110][5].raw - cycles0 >= 50  # (drive cycles: the 50 ms of the brake opening)
            assert node.sdo[0x60FE][1].raw & 1 == 0
            time.sleep(0.2)
            node.sdo[0x6040].raw = 0x07
            _wait(lambda: node.sdo[0x6041].raw & 0x6F == 0x23)
            time.sleep(0.3)
            assert node.sdo[0x60FE][1].raw & 1 == 1
            assert abs(node.sdo[0x6064].raw - x0) < 80
            node.sdo[0x6040].raw = 0x0F
            _wait(lambda: node.sdo[0x6041].raw & 0x6F == 0x27)
            node.sdo[0x2042].raw = 1
            _wait(lambda: node.sdo[0x6041].raw & 0x404F == 0x4040)
            assert node.sdo[0x6077].raw == 0
            _wait(lambda: 0x5400 in [e.code for e in node.emcy.log])
            node.sdo[0x2042].raw = 0
            node.sdo[0x6040].raw = 0x0F
            time.sleep(0.2)
            assert node.sdo[0x6041].raw & 0x404F == 0x0040
        finally:
            net.disconnect()
    assert s.returncode == 0, s.stderr[-2000:]


def test_fault_reaction_stops_then_closes_the_brake_before_torque_off(vrig):
    """A fault with a ramp reaction (0x2010 = 0x5530, 0x605E = 2) on the vertical axis: FAULT REACTION ACTIVE
    through the stop and the 30 ms brake closing delay with torque, then FAULT with the brake applied; the
    axis has not fallen (< 80 um of 0x6064)."""
    node = vrig.node
    _enable_until_operation(vrig)
    vrig.sync(100)
    x0 = node.sdo[0x6064].raw
    node.sdo[0x2010].raw = 0x5530
    vrig.sync(20)
    assert vrig.sw() & 0x4F == 0x0F  # fault reaction active: the brake is closing, torque on
    assert node.sdo[0x60FE][1].raw & 1 == 1 and node.sdo[0x6077].raw != 0
    vrig.sync(20)
    assert vrig.sw() & 0x4F == 0x08
    vrig.sync(200)
    assert abs(node.sdo[0x6064].raw - x0) < 80


def test_brake_output_follows_the_power_stage_without_a_brake(rig):  # noqa: F811
    """An axis without a brake still shows the output a brake would get: 0x60FE:1 bit 0 = 0 while enabled,
    1 after disable voltage."""
    assert rig.node.sdo[0x60FE][1].raw & 1 == 1
    rig.enable()
    assert rig.node.sdo[0x60FE][1].raw & 1 == 0
    rig.node.sdo[0x6040].raw = 0x00
    assert rig.node.sdo[0x60FE][1].raw & 1 == 1


@pytest.mark.parametrize("switch_off", ["disable voltage", "shutdown without ramp", "sto"])
def test_master_released_brake_reads_applied_once_the_drive_applies_it(vrig, switch_off):
    """0x60FE:2 = 1, the master releases the brake (0x60FE:1 = 0) in OPERATION ENABLED; a switch-off without a
    ramp (controlword 0x00, 0x06 with 0x605B = 0, STO) ends that release: the brake holds the vertical axis
    (it falls for the brake's closing time, then stays) and 0x60FE:1 bit 0 reads 1 (applied); releasing it
    again with the power stage off is refused (0x08000022)."""
    node = vrig.node
    node.sdo[0x605B].raw = 0
    node.sdo[0x60FE][2].raw = 1
    _enable_until_operation(vrig)
    node.sdo[0x60FE][1].raw = 0  # released by the master
    vrig.sync(100)
    assert node.sdo[0x60FE][1].raw & 1 == 0
    if switch_off == "sto":
        node.sdo[0x2042].raw = 1
    else:
        node.sdo[0x6040].raw = 0x00 if switch_off == "disable voltage" else 0x06
    vrig.sync(100)
    sw = vrig.sw()
    assert sw & 0x4F == 0x40 or sw & 0x6F == 0x21, hex(sw)  # SWITCH ON DISABLED / READY TO SWITCH ON
    assert node.sdo[0x60FE][1].raw & 1 == 1
    held = node.sdo[0x6064].raw
    vrig.sync(200)
    assert abs(node.sdo[0x6064].raw - held) < 20  # the brake holds
    with pytest.raises(canopen.SdoAbortedError) as exc:
        node.sdo[0x60FE][1].raw = 0
    assert exc.value.code == 0x08000022


def _emcy_codes_after(r: Rig, index: int) -> list[int]:
    return r.emcy.codes()[index:]


@pytest.mark.parametrize("kind, code, register, during_ramp",
                         [(2, 0x2310, 0x03, False), (4, 0x3220, 0x05, True)],
                         ids=["over_current", "dc_link_undervoltage_in_the_reaction_ramp"])
def test_sto_gone_in_fault_shows_the_fault_in_603f_and_1001(rig, kind, code, register, during_ramp):  # noqa: F811
    """A fault (over-current; DC-link under-voltage with STO during its 0x605E ramp), then STO on and off while in
    FAULT: while STO lasts 0x603F = 0x5400 and 0x1001 has bit 7 too; once it goes 0x603F is the fault's code
    again and 0x1001 the fault's bits (no error-reset EMCY: the fault is still there). STO again, a fault reset
    while it lasts: 0x603F = 0x5400, 0x1001 = 0x81 and no EMCY 0x0000; STO off: EMCY 0x0000, 0x603F = 0, 0x1001 = 0."""
    node = rig.node
    if during_ramp:
        node.sdo[0x6060].raw = 3
        node.sdo[0x605E].raw = 1
        node.sdo[0x6084].raw = 100_000  # a 1 s ramp from 0.1 m/s
        node.sdo[0x60FF].raw = 100_000
    rig.enable()
    rig.sync(150)
    node.sdo[0x5FF0].raw = kind
    rig.sync(2)
    assert _state(rig) & 0x4F == (0x0F if during_ramp else 0x08), hex(rig.sw())
    assert node.sdo[0x603F].raw == code and node.sdo[0x1001].raw == register
    node.sdo[0x2042].raw = 1
    rig.sync(1)
    assert _state(rig) & 0x4F == 0x08 and rig.sw() & 0x4080 == 0x4080, hex(rig.sw())
    assert node.sdo[0x603F].raw == 0x5400 and node.sdo[0x1001].raw == register | 0x81
    seen = len(rig.emcy.codes())
    node.sdo[0x2042].raw = 0
    rig.sync(1)
    assert node.sdo[0x2031].raw == 0 and not rig.sw() & 0x80
    assert node.sdo[0x603F].raw == code and node.sdo[0x1001].raw == register
    node.sdo[0x2042].raw = 1
    rig.sync(1)
    node.sdo[0x5FF1].raw = kind
    node.sdo[0x6040].raw = 0x00
    node.sdo[0x6040].raw = 0x80  # fault reset while STO lasts
    rig.sync(1)
    assert _state(rig) & 0x4F == 0x40
    assert node.sdo[0x603F].raw == 0x5400 and node.sdo[0x1001].raw == 0x81
    node.sdo[0x2042].raw = 0
    rig.sync(1)
    assert node.sdo[0x603F].raw == 0 and node.sdo[0x1001].raw == 0
    rig.emcy.wait_for(0x0000)
    after = _emcy_codes_after(rig, seen)
    assert after.count(0) == 1 and after[-1] == 0, [hex(c) for c in after]  # one error reset: when all went
