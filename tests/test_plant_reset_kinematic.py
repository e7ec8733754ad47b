"""Issue #14: the simulation starts at rest, so the nut contact must start relaxed. With a lead error or a warm
screw the table sits where the screw's kinematics put it for the start angle; a reset at the nominal position
preloaded the contact spring and the axis jumped at t = 0 (no friction, no backlash, disabled, 0.3 s: 0.48 um
at 60 ppm 5 mm from the nut offset, 4.6 um with a 3 um periodic lead error, 36 um with a screw 4 K warm) -
a start transient the diagnosis then had to explain."""

from __future__ import annotations

import math

import background
import pytest
from plant_helpers import config_with

from virtualaxis.sim.simulator import AxisSimulator

CASES = {
    "cumulative_lead_error": ({"lead_error_ppm": 60.0}, 1e-9),
    "periodic_lead_error": ({"lead_error_periodic_m": 3e-6, "lead_error_periodic_phase_rad": 0.7}, 1e-9),
    # the screw cools (tau 600 s) while it runs: a little motion is real
    "warm_screw": ({"thermal_expansion_per_k": 11.5e-6, "initial_temperature_rise_k": 4.0,
                    "thermal_resistance_k_per_w": 0.01}, 0.5e-6),
}


@pytest.mark.parametrize("name", list(CASES))
@pytest.mark.parametrize("x0", [-0.005, 0.1])
def test_reset_puts_the_table_where_the_screw_kinematics_hold_it(name, x0):
    effects, tol_m = CASES[name]
    # no friction, backlash or cogging: nothing holds the axis and nothing else moves it
    cfg = config_with({"effects": effects, "friction": {"enabled": False}, "backlash": {"enabled": False},
                       "motor": {"cogging_amplitude_nm": 0.0}})
    sim = AxisSimulator(cfg, initial_position_m=x0)
    s0 = sim.state
    r = cfg.mechanics.lead_m / (2 * math.pi)
    assert s0.motor_angle_rad * r == pytest.approx(x0, abs=1e-15)  # the motor is where it was asked to be
    table_moved = motor_moved = 0.0
    for _ in range(3000):  # 0.3 s, disabled
        sim.advance(1)
        s = sim.state
        table_moved = max(table_moved, abs(s.table_position_m - s0.table_position_m))
        motor_moved = max(motor_moved, abs(s.motor_angle_rad - s0.motor_angle_rad) * r)
    assert table_moved < tol_m and motor_moved < tol_m, (table_moved, motor_moved)
    assert sim.observe().position_m == pytest.approx(x0, abs=2.5e-7)  # the feedback: one encoder quantum


def start_at_rest_runs(out=None) -> dict:
    """The kernel and the solve_ivp reference holding -5 mm with every kinematic effect (a background job of the
    suite: tests/background.py)."""
    import numpy as np

    from virtualaxis.sim.batch import simulate_command
    from virtualaxis.sim.reference import ReferenceAxis

    effects = {k: v for e, _ in CASES.values() for k, v in e.items()}
    cfg = config_with({"effects": effects, "friction": {"enabled": False}, "backlash": {"enabled": False},
                       "motor": {"cogging_amplitude_nm": 0.0}, "sensors": {"linear_scale_resolution_m": 0.0}})
    t = np.arange(151) * 1e-3  # 0.15 s
    p = np.full_like(t, -0.005)
    z = np.zeros_like(t)
    kern = simulate_command(cfg, t, p, vel_cmd_m_s=z, acc_cmd_m_s2=z)
    ref = ReferenceAxis(cfg, rtol=1e-8, atol=1e-12).run(t, p, z, z)
    return {name: {k: np.asarray(run[k]) for k in ("pos_meas", "pos_fb", "motor_pos")}
            for name, run in (("kern", kern), ("ref", ref))}


@pytest.mark.background("start_at_rest_runs")
def test_the_start_at_rest_agrees_with_the_solve_ivp_reference(request):
    """Checked apart from the simulator's closed-form shift: the solve_ivp reference (sim/reference.py, its own
    integrator and contact law) finds its rest state by root finding on that contact law. Enabled, holding
    -5 mm with every kinematic effect at once (60 ppm, 3 um periodic, screw 4 K warm): the two agree point by
    point, and neither moves the table (before the reset fix both started preloaded)."""
    import numpy as np

    job = background.result(request.config, "start_at_rest_runs")
    kern, ref = job["kern"], job["ref"]
    # unquantised scale: measured 1e-12 m apart, the table moving 5 nm (the screw cools, tau 600 s); before the
    # fix both jumped 33 um
    assert np.max(np.abs(kern["pos_meas"] - ref["pos_meas"])) < 1e-10
    for run in (kern, ref):
        assert np.ptp(run["pos_meas"]) < 5e-8
