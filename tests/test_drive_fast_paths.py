"""The drive cycle's fast paths give what the general code gives.

- ``Drive.check_object_write``: the range-only shortcut for integer objects without rules of their own gives
  the same answer (accepted, or the same abort code) as the full checks, for every such object at and beyond
  its limits and for non-integer values;
- ``Drive._publish_outputs``: the inlined round-and-saturate equals the INTEGER32 / INTEGER16 helpers, for
  ordinary values, beyond the 32-bit range and for NaN;
- ``Cia402Application.flush``: after cycles with motion, every drive object the OD serves holds the drive's
  value (REAL32 entries as float).
"""

from __future__ import annotations

import itertools
import math

import can
import pytest
from test_drive_rig import seed_config, seed_discrete

from virtualaxis.canopen_slave import NmtState
from virtualaxis.drive import Drive, ObjectAccessError
from virtualaxis.drive import core as drive_core
from virtualaxis.drive.core import ALIASES, SPECS, _i16, _i32


def _outcome(drive: Drive, index: int, sub: int, value) -> int | None:
    try:
        drive.check_object_write(index, sub, value)
    except ObjectAccessError as exc:
        return exc.code
    return None


def test_the_range_shortcut_of_the_write_check_answers_as_the_full_check(monkeypatch):
    drive = Drive(seed_config(), discrete=seed_discrete())
    plain = dict(drive.object_table.plain_int_ranges)
    assert (0x6040, 0) in plain and (0x607A, 0) in plain and (0x60FF, 0) in plain  # an RPDO's usual objects
    assert (0x6060, 0) not in plain and (0x2011, 0) not in plain  # objects with rules of their own
    assert (0x2005, 0) in plain  # an alias takes its object's range
    cases = []
    for (index, sub), (lo, hi) in plain.items():
        for value in (lo - 1, lo, lo + 1, 0, hi - 1, hi, hi + 1, float(lo), 0.5, True, math.nan, "1"):
            cases.append((index, sub, value))
    fast = [_outcome(drive, *case) for case in cases]
    monkeypatch.setattr(drive.object_table, "plain_int_ranges", {})
    full = [_outcome(drive, *case) for case in cases]
    assert fast == full
    assert fast.count(None) > len(plain) * 3  # (the cases accepted are many: the comparison means something)
    assert set(fast) - {None} >= {drive_core.ABORT_VALUE_TOO_HIGH, drive_core.ABORT_VALUE_TOO_LOW,
                                  drive_core.ABORT_VALUE_INVALID}


@pytest.mark.parametrize("demand_m", [0.0123456, -0.35, 2.0e3, -2.2e3, 1e30, -1e30, math.inf, math.nan])
def test_published_position_values_round_and_saturate_as_the_helpers(demand_m):
    drive = Drive(seed_config(), discrete=seed_discrete())
    drive.step(3)
    drive.setpoints.demand_m = demand_m
    drive.setpoints.demand_v = demand_m / 7.0 if math.isfinite(demand_m) else demand_m
    drive._publish_outputs()
    inv_u = drive._pc.inv_u
    assert drive.read_object(0x6062) == _i32(demand_m * inv_u)
    assert drive.read_object(0x606B) == _i32(drive.setpoints.demand_v * inv_u)
    ax = drive._axis
    assert drive.read_object(0x6064) == _i32((ax.position_m - drive.setpoints.zero_m) * inv_u)
    assert drive.read_object(0x6078) == _i16(ax.current_q_a / drive._pc.rated_a * 1000.0)
    assert drive.read_object(0x2110, 5) == drive.counters["cycles"]


def test_the_od_mirror_holds_every_drive_value_after_a_move():
    from virtualaxis.runtime import AxisNode

    bus = can.Bus(interface="virtual", channel="fast-paths-mirror")
    try:
        axis = AxisNode(bus, 1, seed_config(), name="X")
        slave, drive = axis.slave, axis.drive
        slave.boot(0.0)
        axis.app.flush()
        slave._set_state(NmtState.OPERATIONAL)
        slave.sdo_download(0x6060, 0, bytes([3]))
        for cw in (6, 7, 15):
            slave.sdo_download(0x6040, 0, cw.to_bytes(2, "little"))
        slave.sdo_download(0x60FF, 0, (20_000).to_bytes(4, "little", signed=True))  # 20 mm/s
        for _ in range(150):
            drive.step(1)
            axis.app.flush()
        assert drive.read_object(0x6064) > 0  # it moved
        checked = 0
        for key, entry in axis.app._entries.items():
            expected = drive.objects[ALIASES.get(key, key)]
            if entry.fmt in ("f", "d"):
                assert isinstance(entry.value, float), key
            assert entry.value == expected, (hex(key[0]), key[1], entry.value, expected)
            checked += 1
        assert checked > len(SPECS) // 2
        assert any(e.fmt in ("f", "d") for e in axis.app._entries.values())
        assert list(itertools.islice(drive.take_changed(), 1)) == []  # nothing left unmirrored
    finally:
        bus.shutdown()
