"""The holding brake of the plant (``[effects] brake_*``): engaged it holds the table up to its holding force
and slips beyond it; it follows its command after its own opening / closing time."""

from __future__ import annotations

import dataclasses

import pytest

from virtualaxis.config import load_axis_config
from virtualaxis.runtime.axes import DEFAULT_CONFIG
from virtualaxis.sim import AxisSimulator


def _sim(load_n: float, holding_n: float = 2000.0) -> AxisSimulator:
    cfg = load_axis_config(DEFAULT_CONFIG)
    cfg = dataclasses.replace(cfg, effects=dataclasses.replace(
        cfg.effects, force_offset_n=load_n, brake_holding_force_n=holding_n, brake_opening_time_s=0.04,
        brake_closing_time_s=0.02))
    return AxisSimulator(cfg)


@pytest.mark.parametrize("load_n, slips", [(1500.0, False), (3000.0, True)])
def test_engaged_brake_holds_up_to_its_force_and_slips_beyond(load_n, slips):
    """No power: a load of 1500 N on a 2000 N brake (plus the guides' friction) leaves the table where it is;
    3000 N slips it (the table moves against +x, braked: slower than a free fall)."""
    sim = _sim(load_n)
    sim.advance(200)
    x = sim.state.table_position_m
    if slips:
        assert x < -1e-3
        free_fall_m = 0.5 * load_n / sim.cfg.mechanics.table_mass_kg * 0.2 ** 2
        assert -x < 0.5 * free_fall_m
    else:
        assert x == 0.0


def test_brake_follows_its_command_after_its_opening_and_closing_time():
    """Commanded open, it holds for its opening time (40 ms) and then the 1500 N load moves the table; commanded
    closed, it brakes again after its closing time (20 ms) and holds the table once it has stopped."""
    sim = _sim(1500.0)
    sim.command_brake(True)
    sim.advance(39)
    assert sim.state.table_position_m == 0.0 and not sim.brake_released()
    sim.advance(21)
    assert sim.brake_released() and sim.state.table_position_m < -1e-5
    sim.command_brake(False)
    sim.advance(19)
    assert sim.brake_released()
    sim.advance(250)  # (the brake's 2000 N against the 1500 N load decelerates table and rotor inertia in ~0.13 s)
    assert not sim.brake_released() and sim.state.stuck
    x = sim.state.table_position_m
    sim.advance(100)
    assert abs(sim.state.table_position_m - x) < 1e-6  # (the unpowered drivetrain rings out; the table is held)


def test_no_brake_without_a_holding_force():
    cfg = load_axis_config(DEFAULT_CONFIG)
    sim = AxisSimulator(cfg)
    assert sim.brake is None and sim.brake_released()
