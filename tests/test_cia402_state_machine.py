"""CiA 402 power drive state machine through a real master (checklist items 12-17)."""

from __future__ import annotations

import time

import pytest
from test_drive_rig import Rig, rig  # noqa: F401  (fixture)


def test_state_chain_with_base_node_402_over_pdo(rig):  # noqa: F811
    """12: 0x06 -> 0x21, 0x07 -> 0x23, 0x0F -> 0x27; each visible in the TPDO and in SDO 0x6041."""
    node = rig.node
    node.setup_402_state_machine()
    node.nmt.state = "OPERATIONAL"
    seen = []
    node.tpdo[1].add_callback(lambda m: seen.append(m["Statusword"].raw))
    t0 = time.monotonic()
    node.state = "OPERATION ENABLED"  # BaseNode402 walks 0x06, 0x07, 0x0F and checks each TPDO (< 0.8 s)
    assert time.monotonic() - t0 < 0.8
    assert node.sdo[0x6041].raw & 0x6F == 0x27
    masked = [sw & 0x6F for sw in seen]
    for expect in (0x21, 0x23, 0x27):
        assert expect in masked
    assert masked.index(0x21) < masked.index(0x23) < masked.index(0x27)


@pytest.mark.parametrize(
    ("cw", "state_mask", "state_value", "name"),
    [
        (0x07, 0x6F, 0x23, "switched on"),
        (0x06, 0x6F, 0x21, "ready to switch on"),
        (0x00, 0x4F, 0x40, "switch on disabled"),
        (0x02, 0x6F, 0x07, "quick stop active"),
    ],
)
def test_transitions_out_of_operation_enabled(rig, cw, state_mask, state_value, name):  # noqa: F811
    """13: from operation enabled (at standstill; 0x605A = 6 keeps quick stop active)."""
    rig.node.sdo[0x605A].raw = 6
    rig.enable()
    rig.node.sdo[0x6040].raw = cw
    rig.wait(lambda: rig.sw() & state_mask == state_value, sync=True)
    if name == "quick stop active":
        assert not rig.sw() & 0x20  # bit 5 = 0 in quick stop


def test_disable_operation_slows_down_with_profile_deceleration_before_switched_on():
    """13: 0x605C = 1: transition 5 decelerates with 0x6084 first, the state changes once stopped."""
    r = Rig()
    try:
        node = r.node
        node.sdo[0x605C].raw = 1
        node.sdo[0x6084].raw = 1_000_000  # 1 m/s^2
        node.sdo[0x6060].raw = 3  # profile velocity
        node.sdo[0x6083].raw = 10_000_000
        node.sdo[0x60FF].raw = 100_000  # 0.1 m/s
        node.nmt.state = "OPERATIONAL"
        r.enable()
        r.sync(200)
        assert node.sdo[0x606C].raw > 90_000
        node.sdo[0x6040].raw = 0x07
        assert node.sdo[0x6041].raw & 0x6F == 0x27  # still enabled while decelerating
        r.sync(50)
        assert node.sdo[0x6041].raw & 0x6F == 0x27
        r.wait(lambda: r.sw() & 0x6F == 0x23, sync=True, timeout=5)
        # stopping from 0.1 m/s at 1 m/s^2 takes ~100 cycles
        assert r.drive.counters["cycles"] > 250
    finally:
        r.close()


@pytest.mark.parametrize("option", [1, 2, 3, 5, 6, 7])
def test_quick_stop_option_codes(option):
    """14: 0x605A = 1..4 -> switch on disabled after the stop; 5..8 stay in quick stop active and 0x0F
    returns to operation enabled."""
    r = Rig()
    try:
        node = r.node
        node.sdo[0x605A].raw = option
        node.sdo[0x6060].raw = 3
        node.sdo[0x6083].raw = 10_000_000
        node.sdo[0x6085].raw = 5_000_000
        node.sdo[0x60FF].raw = 50_000
        node.nmt.state = "OPERATIONAL"
        r.enable()
        r.sync(100)
        node.sdo[0x6040].raw = 0x02
        r.sync(400)
        assert abs(node.sdo[0x606C].raw) < 2_000  # stopped
        if option <= 4:
            assert r.sw() & 0x4F == 0x40
        else:
            assert r.sw() & 0x6F == 0x07
            node.sdo[0x6040].raw = 0x0F
            assert r.sw() & 0x6F == 0x27
    finally:
        r.close()


def test_internal_fault_reaction_emcy_and_error_history(rig):  # noqa: F811
    """15: fault -> fault reaction active -> fault; EMCY [code, 0x1001]; 0x603F; 0x1003 entry."""
    node = rig.node
    node.sdo[0x6060].raw = 3
    node.sdo[0x6083].raw = 10_000_000
    node.sdo[0x60FF].raw = 50_000
    node.nmt.state = "OPERATIONAL"
    rig.enable()
    rig.sync(50)
    states = []
    rig.drive.add_observer(lambda event, s: states.append(s.cia402_state))
    node.sdo[0x2010].raw = 0x2310  # inject over-current
    can_id, code, register, _ = rig.emcy.wait_for(0x2310)
    assert can_id == 0x81 and register & 0x03 == 0x03  # generic + current
    rig.wait(lambda: rig.sw() & 0x4F == 0x08, sync=True)
    assert "FAULT REACTION ACTIVE" in states and states[-1] == "FAULT"
    assert node.sdo[0x603F].raw == 0x2310
    assert node.sdo[0x1001].raw & 0x03 == 0x03
    assert node.sdo[0x1003][1].raw & 0xFFFF == 0x2310
    assert node.sdo[0x2030][1].raw == 30001  # fault number (r0947)


def test_fault_reset_on_rising_edge_only_and_not_while_the_cause_persists(rig):  # noqa: F811
    """16: bit 7 edge -> switch on disabled + EMCY 0x0000; holding bit 7 does nothing; a persisting
    cause keeps the fault."""
    node = rig.node
    node.sdo[0x2010].raw = 0x4210  # injected: persists until cleared
    rig.emcy.wait_for(0x4210)
    assert rig.sw() & 0x4F == 0x08
    node.sdo[0x6040].raw = 0x00
    node.sdo[0x6040].raw = 0x80
    assert rig.sw() & 0x4F == 0x08  # cause persists
    node.sdo[0x2010].raw = 0  # remove the cause (clear_fault acknowledges)
    assert rig.sw() & 0x4F == 0x40
    rig.emcy.wait_for(0x0000)
    # a following-error style fault whose cause is gone: the edge resets it, holding the bit does not repeat
    rig.drive.inject_fault(0x8611)
    rig.drive.clear_fault()  # clears the injected cause and acknowledges
    rig.drive.inject_fault(0x7320)
    rig.drive.clear_cause("injected")  # the encoder came back (cause gone) - only the fault state remains
    node.sdo[0x6040].raw = 0x80  # bit 7 was already 1: no edge
    assert rig.sw() & 0x4F == 0x08
    node.sdo[0x6040].raw = 0x00
    node.sdo[0x6040].raw = 0x80  # edge
    assert rig.sw() & 0x4F == 0x40
    n_resets = rig.emcy.codes().count(0)
    node.sdo[0x6040].raw = 0x80  # held
    time.sleep(0.05)
    assert rig.emcy.codes().count(0) == n_resets


def test_statusword_bits(rig):  # noqa: F811
    """17: bit 4 voltage enabled, 5 = 0 only in quick stop, 9 remote, 10/12 mode specific."""
    node = rig.node
    sw = rig.sw()
    assert sw & 0x10 and sw & 0x200 and not sw & 0x0F
    node.sdo[0x6060].raw = 8
    rig.enable()
    sw = rig.sw()
    assert sw & 0x20 and sw & 0x1000  # not quick stop; CSP: drive follows the target
    node.sdo[0x605A].raw = 6
    node.sdo[0x6040].raw = 0x02
    assert not rig.sw() & 0x20


@pytest.mark.parametrize(
    ("sequence", "illegal"),
    [
        ([0x0F], 1),  # enable operation from switch on disabled
        ([0x07], 1),  # switch on from switch on disabled
        ([0x06, 0x07, 0x0F, 0x02, 0x07], 1),  # switch on in quick stop active (0x605A = 6 stays there)
        ([0x06, 0x06, 0x00, 0x00], 0),  # repeats and legal transitions are not counted
    ],
)
def test_illegal_controlword_sequences_are_ignored_and_counted(rig, sequence, illegal):  # noqa: F811
    node = rig.node
    node.sdo[0x605A].raw = 6
    before = node.sdo[0x2110][1].raw
    for cw in sequence:
        node.sdo[0x6040].raw = cw
    assert node.sdo[0x2110][1].raw - before == illegal
    if illegal and sequence[-1] in (0x0F, 0x07) and len(sequence) == 1:
        assert rig.sw() & 0x4F == 0x40  # stayed in switch on disabled
    rig.sync(3)  # the drive cycle keeps running
