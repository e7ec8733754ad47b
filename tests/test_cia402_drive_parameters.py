"""Homing speeds, the speed-zero bits at rest and the gear ratio 0x6091, through a real ``canopen`` master
(``Rig``: virtual bus, lockstep)."""

from __future__ import annotations

import canopen
import pytest
from test_drive_rig import Rig, seed_config

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
