"""Plant side of the limit switches: the hard end stops absorb an impact instead of throwing the axis back.

With a single stiff contact at the table, a disabled axis that coasted into the stop
came back out at 97 % of its impact speed: the table stopped within a fraction of a millisecond, the rotor
(1329 kg reflected on the seed 000 axis, five times the table) ran on, wound up the screw spring and threw
the whole axis back. A machine's end stop has a damped buffer in front of the rigid stop; the plant now has one
(sim/simulator.py ``end_stops``), and these tests push a disabled axis into either end of both seed axes."""

from __future__ import annotations

import pytest
from plant_helpers import SEED000, SEED004, seed_dict

from virtualaxis.config import axis_config_from_dict
from virtualaxis.sim.simulator import AxisSimulator, end_stop_mass_kg, end_stop_overtravel_m, end_stops

#: the motor-side speed at impact we aim the push for [m/s] (the 0.5 m/s limit of the seed configs, less margin)
IMPACT_M_S = 0.45


@pytest.mark.parametrize("path", [SEED000, SEED004], ids=["seed000", "seed004"])
@pytest.mark.parametrize("sign", [1, -1], ids=["plus", "minus"])
@pytest.mark.parametrize("push_m_s2", [0.5, 3.0])
def test_disabled_axis_pushed_into_the_end_stop_comes_to_rest_without_bouncing_back(path, sign, push_m_s2):
    cfg = axis_config_from_dict(seed_dict(path), path.name)
    lo, hi, _, _, travel, _ = end_stops(cfg)
    assert hi == -lo == pytest.approx(cfg.axis.stroke_m / 2 + end_stop_overtravel_m(cfg))
    r = cfg.mechanics.lead_m / (2 * 3.141592653589793)
    start = sign * (hi - IMPACT_M_S**2 / (2 * push_m_s2))
    sim = AxisSimulator(cfg, initial_position_m=start)
    sim.set_external_force(sign * 1.3 * end_stop_mass_kg(cfg) * push_m_s2)  # 1.3: friction, the rest accelerates
    impact = None
    penetration = rebound = 0.0
    for _ in range(20000):  # 2 s at the 100 us position cycle of both seeds
        sim.advance(1)
        s = sim.state
        if impact is None and sign * s.table_position_m > hi:
            impact = abs(s.motor_speed_rad_s) * r
            sim.set_external_force(0.0)  # the push ends at the contact: the stop alone takes the energy
        if impact is not None:
            penetration = max(penetration, sign * s.table_position_m - hi)
            rebound = max(rebound, -sign * s.motor_speed_rad_s * r)
    assert impact is not None and impact > 0.3, impact
    assert rebound < 0.08 * impact, (rebound, impact)  # before: 0.97
    assert 0.0 < penetration < travel  # the buffer took it; the rigid stop behind it was not reached
    s = sim.state
    assert abs(s.velocity_m_s) < 1e-4 and abs(s.motor_speed_rad_s) * r < 1e-4  # at rest ...
    assert -0.005 < sign * s.table_position_m - hi < travel  # ... at the stop, not thrown back
