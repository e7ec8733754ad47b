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


class _Entry:
    def __init__(self, value, tpdos=()):
        self.value = value
        self.tpdos = tpdos


class _Tpdo:
    dirty = False


def test_publish_stores_the_changed_outputs_and_marks_only_the_tpdos_of_changed_entries():
    from virtualaxis.drive.object_table import ObjectTable

    keys = ((0x6064, 0), (0x606C, 0), (0x2020, 0), (0x6041, 0))
    table = ObjectTable({}, keys, {}, {}, frozenset())
    table.reset({k: 0 for k in keys})
    tp_pos, tp_vel, tp_temp = _Tpdo(), _Tpdo(), _Tpdo()
    entries = [_Entry(0, (tp_pos,)), _Entry(0, (tp_vel,)), _Entry(0.0, (tp_temp,)), None]
    table.mirror_outputs(entries, [False, False, True, False])
    table.publish((5, 0, 25, 7))
    assert [table.values[k] for k in keys] == [5, 0, 25, 7]
    assert entries[0].value == 5 and entries[1].value == 0
    assert entries[2].value == 25.0 and isinstance(entries[2].value, float)  # a REAL entry gets a float
    assert (tp_pos.dirty, tp_vel.dirty, tp_temp.dirty) == (True, False, True)  # 0 -> 0: no mark
    tp_pos.dirty = tp_temp.dirty = False
    published = table.outputs
    table.publish((5, 0, 25, 7))
    assert table.outputs is published  # nothing changed: the same tuple
    table.publish((5, -3, 25, math.nan))
    assert table.values[(0x606C, 0)] == -3 and math.isnan(table.values[(0x6041, 0)])
    assert (tp_pos.dirty, tp_vel.dirty, tp_temp.dirty) == (False, True, False)
    table.values[(0x6064, 0)] = 99  # a value set apart from publish stays until its output changes
    table.publish((5, -3, 26, 1))
    assert table.values[(0x6064, 0)] == 99 and table.values[(0x2020, 0)] == 26
    for wrong in ((1, 2, 3), (1, 2, 3, 4, 5)):
        with pytest.raises(ValueError):
            table.publish(wrong)
    assert table.outputs == (5, -3, 26, 1)


@pytest.mark.parametrize("cycle_s", [1e-3, 2.5e-4, 1.25e-4, 4e-4, 1 / 3000, 0.7e-3])
def test_the_sync_loss_cycle_count_is_the_first_whose_run_time_exceeds_the_loss_time(cycle_s):
    from virtualaxis.drive.canopen_app import SYNC_LOSS_MIN_S, SYNC_LOSS_PERIODS, sync_loss_cycles

    for period_us in (0, 1, 250, 500, 1000, 1333, 2000, 4000, 9999, 10_000, 10_001, 20_000, 65_535, 10**6):
        timeout_s = 1.5 * period_us * 1e-6  # as the SYNC consumer derives it from 0x1006
        k = sync_loss_cycles(timeout_s, cycle_s)
        if period_us == 0:
            assert k is None
            continue
        limit_s = max(SYNC_LOSS_PERIODS * (timeout_s / 1.5), SYNC_LOSS_MIN_S)
        first = next(n for n in itertools.count(0) if n * cycle_s > limit_s)
        assert k == first, (period_us, cycle_s, k, first)
