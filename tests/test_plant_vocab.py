"""Drive / axis options of issue #14 ("vocabulary real axes need"): each config key is bounded on load, its
default reproduces the kernel's earlier behaviour, and its physics is checked against a reference not derived
from the kernel (closed-form solutions, plain-numpy reimplementations)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from plant_helpers import rigid_force_axis

from virtualaxis.config import ConfigError
from virtualaxis.diagnosis import effects as fx
from virtualaxis.sim import AxisSimulator, ControlMode
from virtualaxis.sim.batch import simulate_command


def _dict_of(cfg) -> dict:
    return cfg.to_dict()


# ------------------------------------------------------------------------ 1. direction-dependent viscous friction
def _rigid_open_loop_velocity(cfg, force_n: float, cycles: int) -> np.ndarray:
    """Table velocity per position cycle of the rigid force axis under a constant force set-point (torque mode:
    no controller in the loop)."""
    sim = AxisSimulator(cfg)
    sim.enable(True)
    sim.set_mode(ControlMode.TORQUE)
    sim.set_torque_setpoint(force_n)
    v = np.empty(cycles)
    for k in range(cycles):
        sim.advance(1)
        v[k] = sim.state.velocity_m_s
    return v


@pytest.mark.parametrize("force_n, fv_expected", [(300.0, 400.0), (-300.0, 1200.0)])
def test_viscous_friction_per_direction_matches_the_closed_form_run_up(force_n, fv_expected):
    """m dv/dt = F - F_c sgn v - F_v,dir v from rest: v(t) = v_inf (1 - exp(-F_v,dir t / m)) with
    v_inf = (|F| - F_c) / F_v,dir (first-order run-up, textbook); the coefficient is the one of the direction."""
    fc, m = 60.0, 50.0
    cfg = rigid_force_axis(coulomb_n=fc, viscous_n_s_per_m=400.0, viscous_negative_n_s_per_m=1200.0)
    cfg = cfg.replace(actuator={"force_lag_s": 0.0})
    v = _rigid_open_loop_velocity(cfg, force_n, 400)
    t = (np.arange(400) + 1) * cfg.control.position_cycle_s
    v_inf = math.copysign((abs(force_n) - fc) / fv_expected, force_n)
    closed = v_inf * (1.0 - np.exp(-fv_expected * t / m))
    assert np.max(np.abs(v - closed)) < 2e-3 * abs(v_inf)
    # the other direction's coefficient would give a visibly different curve (the test can fail)
    other = 1600.0 - fv_expected
    wrong = math.copysign((abs(force_n) - fc) / other, force_n) * (1.0 - np.exp(-other * t / m))
    assert np.max(np.abs(v - wrong)) > 0.2 * abs(v_inf)


def test_viscous_negative_default_is_the_symmetric_kernel_bit_for_bit():
    base = rigid_force_axis(coulomb_n=30.0, viscous_n_s_per_m=700.0)
    assert base.friction.viscous_negative_n_s_per_m == -1.0  # the documented default: "same as +v"
    same = base.replace(friction={"viscous_negative_n_s_per_m": 700.0})
    t = np.arange(1500) * 1e-3
    pos = 0.05 * np.sin(2 * math.pi * 1.5 * t)
    a = simulate_command(base, t, pos, seed=1)
    b = simulate_command(same, t, pos, seed=1)
    for k in a:
        assert np.array_equal(a[k], b[k]), k
    c = simulate_command(base.replace(friction={"viscous_negative_n_s_per_m": 900.0}), t, pos, seed=1)
    assert not np.array_equal(a["force_drive"], c["force_drive"])


@pytest.mark.parametrize("value", [-2.0, 2e7, float("nan")])
def test_viscous_negative_out_of_bounds_names_the_key(value):
    d = _dict_of(rigid_force_axis(coulomb_n=1.0))
    d["friction"]["viscous_negative_n_s_per_m"] = value
    from virtualaxis.config import axis_config_from_dict

    with pytest.raises(ConfigError, match=r"friction\.viscous_negative_n_s_per_m"):
        axis_config_from_dict(d, "x.toml")


def test_viscous_asymmetry_effect_maps_onto_the_config_and_reduces_to_viscous_friction():
    cfg = rigid_force_axis(coulomb_n=25.0, viscous_n_s_per_m=150.0)
    eff = fx.EFFECTS["viscous_asymmetry"]
    params = {p.name: p for p in eff.params(cfg)}
    assert set(params) == {"viscous_n_s_per_m", "viscous_negative_n_s_per_m"}
    assert params["viscous_n_s_per_m"].nominal == 150.0 and params["viscous_negative_n_s_per_m"].nominal == 150.0
    assert params["viscous_negative_n_s_per_m"].upper == params["viscous_n_s_per_m"].upper > 400.0
    out = eff.apply(cfg, {"viscous_n_s_per_m": 150.0, "viscous_negative_n_s_per_m": 400.0})
    assert out.friction.viscous_n_s_per_m == 150.0 and out.friction.viscous_negative_n_s_per_m == 400.0
    assert eff.applicable(cfg) is None
    assert all(s["viscous_negative_n_s_per_m"] >= 150.0 for s in eff.starts(cfg, {}))
    # equal directions within their uncertainty: plain viscous friction
    assert fx.reduce_nested("viscous_asymmetry", {"viscous_n_s_per_m": 300.0, "viscous_negative_n_s_per_m": 304.0},
                            {"viscous_n_s_per_m": 5.0, "viscous_negative_n_s_per_m": 5.0}) == (
        "viscous_friction", {"viscous_n_s_per_m": 302.0})
    assert fx.reduce_nested("viscous_asymmetry", {"viscous_n_s_per_m": 150.0, "viscous_negative_n_s_per_m": 400.0},
                            {"viscous_n_s_per_m": 5.0, "viscous_negative_n_s_per_m": 5.0}) is None
    # the plain viscous effect keeps a configured asymmetry ratio
    asym = cfg.replace(friction={"viscous_negative_n_s_per_m": 300.0})
    scaled = fx.EFFECTS["viscous_friction"].apply(asym, {"viscous_n_s_per_m": 300.0})
    assert scaled.friction.viscous_negative_n_s_per_m == pytest.approx(600.0)
