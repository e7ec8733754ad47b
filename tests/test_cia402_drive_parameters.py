"""Homing speeds, the speed-zero bits at rest and the gear ratio 0x6091, through a real ``canopen`` master
(``Rig``: virtual bus, lockstep)."""

from __future__ import annotations

import time
from pathlib import Path

import canopen
import pytest
from test_drive_rig import Rig, seed_config, seed_discrete

from virtualaxis.drive.core import DEFAULT_EDS
from virtualaxis.runtime import AxisNode, Runtime, open_bus

ABORT_VALUE_INVALID = 0x06090030
ABORT_VALUE_TOO_LOW = 0x06090032


@pytest.mark.parametrize("sub", [1, 2])
def test_a_homing_speed_of_zero_is_refused_and_homing_still_finishes(sub):
    """0x6099:1 / :2 = 0 would be a search that never moves (the run hung with no error bit): refused with
    SDO abort 0x06090032 (value too low); the speed in force is kept and the homing run finishes."""
    r = Rig({1: (seed_config(), 0.03)})
    try:
        node = r.node
        node.sdo[0x6060].raw = 6
        node.sdo[0x6098].raw = 20
        node.sdo[0x6099][1].raw = 100_000
        node.sdo[0x6099][2].raw = 10_000
        node.sdo[0x609A].raw = 2_000_000
        with pytest.raises(canopen.SdoAbortedError) as err:
            node.sdo[0x6099][sub].raw = 0
        assert err.value.code == ABORT_VALUE_TOO_LOW
        assert node.sdo[0x6099][sub].raw == (100_000 if sub == 1 else 10_000)
        node.nmt.state = "OPERATIONAL"
        r.enable()
        node.sdo[0x6040].raw = 0x1F
        for _ in range(80):
            r.sync(50)
            if r.sw() & 0x3400 == 0x1400 or r.sw() & 0x2000:
                break
        assert r.sw() & 0x3400 == 0x1400, hex(r.sw())
    finally:
        r.close()


def _toggles(r: Rig, bit: int, cycles: int) -> tuple[int, int]:
    """(changes of ``bit`` in the statusword, cycles it was set) over ``cycles`` SYNCs."""
    last, changes, set_cycles = None, 0, 0
    for _ in range(cycles):
        r.sync(1)
        b = bool(r.sw() & bit)
        set_cycles += b
        changes += last is not None and b != last
        last = b
    return changes, set_cycles


def test_homing_error_bit_10_settles_once_instead_of_toggling():
    """A homing error (limit switch in the run) brakes the axis to rest; the axis settles into the position
    hold. Bit 10 (speed 0: |v| within 0x606F for 0x6070 ms, with hysteresis) changes only with real motion,
    not with every swing of the settling speed about the threshold, and reads 1 at rest."""
    r = Rig({1: (seed_config(), -0.1)})
    try:
        node = r.node
        node.sdo[0x6060].raw = 6
        node.sdo[0x6098].raw = 19
        node.sdo[0x6099][1].raw = 100_000
        node.sdo[0x609A].raw = 2_000_000
        node.nmt.state = "OPERATIONAL"
        r.enable()
        node.sdo[0x6040].raw = 0x1F
        r.sync(150)
        injector = next(iter(r.axes.values())).injection
        injector.inject("limit_switch", magnitude=1.0)
        r.wait(lambda: r.sw() & 0x2000, sync=True, timeout=10)
        changes, _ = _toggles(r, 0x400, 400)  # braking and settling
        assert changes <= 4, changes
        changes, set_cycles = _toggles(r, 0x400, 100)  # at rest
        assert r.sw() & 0x3000 == 0x2000, hex(r.sw())
        assert (changes, set_cycles) == (0, 100)
        injector.clear()
    finally:
        r.close()


def test_profile_velocity_speed_zero_bit_12_is_steady_while_creeping_below_the_threshold():
    """PV at 60 um/s, below the velocity threshold 0x606F = 100 um/s: the measured speed swings up to ~120 um/s
    about it; bit 12 (speed = 0) is set once and stays set."""
    r = Rig()
    try:
        node = r.node
        node.sdo[0x6060].raw = 3
        assert node.sdo[0x606F].raw == 100 and node.sdo[0x6070].raw == 10
        node.nmt.state = "OPERATIONAL"
        r.enable()
        node.sdo[0x60FF].raw = 60
        r.sync(300)
        changes, set_cycles = _toggles(r, 0x1000, 300)
        assert (changes, set_cycles) == (0, 300)
    finally:
        r.close()


def test_gear_ratio_other_than_the_machines_is_refused_and_the_index_stays_one_per_motor_revolution():
    """0x6091 describes the machine, whose motor drives the 16 mm screw directly: 2:1 is refused with SDO abort
    0x06090030 (counting two motor revolutions, index pulses every 8 mm and 0x6080 at half the speed against a
    plant whose motor turns once per lead); 1:1 is accepted. Homing method 1 then finds the first index pulse
    (one per motor revolution, every 16 mm) after the negative limit switch at -288 mm, and one screw
    revolution counts 0x608F increments in 0x6063."""
    r = Rig({1: (seed_config(), -0.27)})
    try:
        node = r.node
        for sub, value in ((1, 2), (2, 2)):
            with pytest.raises(canopen.SdoAbortedError) as err:
                node.sdo[0x6091][sub].raw = value
            assert err.value.code == ABORT_VALUE_INVALID
        node.sdo[0x6091][1].raw = 1
        assert (node.sdo[0x6091][1].raw, node.sdo[0x6091][2].raw) == (1, 1)
        node.sdo[0x6060].raw = 6
        node.sdo[0x6098].raw = 1
        node.sdo[0x6099][1].raw = 100_000
        node.sdo[0x6099][2].raw = 10_000
        node.sdo[0x609A].raw = 2_000_000
        node.sdo[0x607C].raw = 0
        node.nmt.state = "OPERATIONAL"
        r.enable()
        inc0 = node.sdo[0x6063].raw
        node.sdo[0x6040].raw = 0x1F
        for _ in range(160):
            r.sync(50)
            if r.sw() & 0x3400 == 0x1400 or r.sw() & 0x2000:
                break
        assert r.sw() & 0x3400 == 0x1400, hex(r.sw())
        assert abs(r.drive.sim.state.position_m - (-0.288)) < 0.0006
        lead_m = r.drive.cfg.mechanics.lead_m
        per_rev = node.sdo[0x608F][1].raw
        assert abs(inc0 - (-0.27) / lead_m * per_rev) < per_rev * 0.01  # before homing: from the plant's zero
    finally:
        r.close()


def test_homing_with_a_zero_speed_from_the_eds_ends_in_a_homing_error(tmp_path):
    """An EDS whose default 0x6099:2 is 0 (loaded at boot, no write to refuse): homing method 20 would crawl
    at speed 0 for ever; the run ends in a homing error (bits 13/12 = 1/0) instead."""
    eds = tmp_path / "zero-homing-speed.eds"
    text = Path(DEFAULT_EDS).read_text()
    head, sep, tail = text.partition("[6099sub2]")
    body, nl, rest = tail.partition("\n\n")
    eds.write_text(head + sep + body.replace("DefaultValue=2000", "DefaultValue=0") + nl + rest)
    channel = f"va-zero-speed-{time.monotonic_ns()}"
    bus = open_bus(f"virtual:{channel}")
    axis = AxisNode(bus, 1, seed_config(), name="axis1", initial_position_m=0.03, discrete=seed_discrete(),
                    eds_path=eds)
    runtime = Runtime(bus, [axis], lockstep=True)
    net = canopen.Network()
    net.connect(interface="virtual", channel=channel)
    try:
        runtime.start()
        node = canopen.BaseNode402(1, str(eds))
        node.sdo.RESPONSE_TIMEOUT = 2.0
        net.add_node(node)
        assert node.sdo[0x6099][2].raw == 0
        node.sdo[0x6060].raw = 6
        node.sdo[0x6098].raw = 20
        node.sdo[0x609A].raw = 2_000_000
        for cw in (0x06, 0x07, 0x0F, 0x1F):
            node.sdo[0x6040].raw = cw
        sw = 0
        for _ in range(3000):
            net.sync.transmit()
            time.sleep(0.002)
            sw = node.sdo[0x6041].raw
            if sw & 0x3000:
                break
        assert sw & 0x3000 == 0x2000, hex(sw)
    finally:
        net.disconnect()
        runtime.stop()
        bus.shutdown()
