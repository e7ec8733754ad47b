"""Drive / axis options (the vocabulary real axes need): each config key is bounded on load, its
default reproduces the kernel's earlier behaviour, and its physics is checked against a reference not derived
from the kernel (closed-form solutions, plain-numpy reimplementations)."""

from __future__ import annotations

import math

import background
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


# ------------------------------------------------------------------------ 2. speed estimator / 4. sensor dead time
def _rigid_p_velocity_axis(**control):
    """Rigid 60 kg force-driven axis, P velocity loop and position loop at 1 kHz on an ideal linear scale, no
    friction, no force lag (like the reference's rigid_pp structure), with ``control`` options."""
    cfg = rigid_force_axis()
    return cfg.replace(
        mechanics={"table_mass_kg": 60.0},
        actuator={"force_lag_s": 0.0, "force_limit_n": 0.0},
        control={"current_cycle_s": 250e-6, "speed_cycle_s": 1e-3, "position_cycle_s": 1e-3,
                 "velocity_kp_n_s_per_m": 5000.0, "speed_ti_s": 0.0, **control},
        sensors={"linear_scale_resolution_m": 0.0},
    )


def _numpy_velocity_loop(m_kg, kp, t_s, v_ref, n, samples=1, tau_s=0.0, delay_samples=0):
    """Plain-numpy reimplementation of a sampled P velocity loop on a rigid mass: at t_k the position sampled
    ``delay_samples`` periods earlier is differentiated ((q[k] - q[k-1]) / T or (q[k] - q[k-2]) / 2T), low-passed
    by w_f += (1 - exp(-T/tau)) (w - w_f), and F = kp (v_ref - w_f) is held over [t_k, t_k+1); the mass moves
    exactly under the held force. Returns the table position at every t_k (before the step)."""
    x, v = 0.0, 0.0
    hist = [0.0] * (delay_samples + 3)  # sampled positions, newest last
    wf = 0.0
    a = 1.0 - math.exp(-t_s / tau_s) if tau_s > 0 else 1.0
    out = np.empty(n)
    for k in range(n):
        out[k] = x
        hist.append(x)
        q = hist[-1 - delay_samples]
        q1 = hist[-2 - delay_samples]
        q2 = hist[-3 - delay_samples]
        w = (q - q1) / t_s if samples == 1 else (q - q2) / (2 * t_s)
        wf += a * (w - wf)
        f = kp * (v_ref - wf)
        x += v * t_s + 0.5 * f / m_kg * t_s * t_s
        v += f / m_kg * t_s
    return out


def _kernel_velocity_step(cfg, v_ref, n):
    sim = AxisSimulator(cfg)
    sim.enable(True)
    sim.set_mode(ControlMode.VELOCITY)
    z = np.zeros(n)
    rows = sim.run_arrays(z, z, z, z, aux=np.full(n, v_ref))
    from virtualaxis.sim import layout as L

    return rows[:, L.O_TABLE_TRUE], rows


@pytest.mark.parametrize("estimator, tau_s", [("backward_difference", 0.0), ("two_sample_difference", 0.0),
                                              ("backward_difference", 2e-3), ("two_sample_difference", 1.5e-3)])
def test_speed_estimator_forms_match_a_plain_numpy_velocity_loop(estimator, tau_s):
    n, v_ref = 300, 0.1
    cfg = _rigid_p_velocity_axis(speed_estimator=estimator, speed_filter_time_constant_s=tau_s)
    x, _ = _kernel_velocity_step(cfg, v_ref, n)
    samples = 2 if estimator == "two_sample_difference" else 1
    ref = _numpy_velocity_loop(60.0, 5000.0, 1e-3, v_ref, n, samples, tau_s)
    assert np.max(np.abs(x - ref)) < 1e-9 * np.max(np.abs(ref))
    # another form gives a visibly different response (kp T / m = 0.083: the estimator's delay shows)
    other = _numpy_velocity_loop(60.0, 5000.0, 1e-3, v_ref, n, 3 - samples, tau_s)
    assert np.max(np.abs(x - other)) > 1e-3 * np.max(np.abs(ref))


def test_speed_estimator_defaults_and_bounds():
    cfg = rigid_force_axis()
    assert cfg.control.speed_estimator == "backward_difference"
    assert cfg.control.speed_filter_time_constant_s == 0.0
    from virtualaxis.config import axis_config_from_dict

    for key, bad in (("speed_estimator", "three_sample"), ("speed_filter_time_constant_s", -1e-3),
                     ("speed_filter_time_constant_s", 5.0)):
        d = _dict_of(cfg)
        d["control"][key] = bad
        with pytest.raises(ConfigError, match=rf"control\.{key}"):
            axis_config_from_dict(d, "x.toml")


@pytest.mark.parametrize("scope, delayed", [("position_loop", 0), ("feedback_sensor", 3)])
def test_dead_time_scope_delays_the_speed_loop_only_for_the_feedback_sensor(scope, delayed):
    """Velocity mode (the position loop is out of the loop): a 3 ms dead time reaches the speed loop, which
    differentiates the linear scale on this axis, only with dead_time_scope = feedback_sensor."""
    n, v_ref = 300, 0.1
    cfg = _rigid_p_velocity_axis().replace(sensors={"dead_time_s": 3e-3, "dead_time_scope": scope})
    x, _ = _kernel_velocity_step(cfg, v_ref, n)
    ref = _numpy_velocity_loop(60.0, 5000.0, 1e-3, v_ref, n, delay_samples=delayed)
    assert np.max(np.abs(x - ref)) < 1e-9 * np.max(np.abs(ref))


def _torque_mode_run(cfg, n):
    """Open loop (torque mode, no feedback in the loop): the motion does not depend on the dead time's scope."""
    sim = AxisSimulator(cfg)
    sim.enable(True)
    sim.set_mode(ControlMode.TORQUE)
    t = np.arange(n) * cfg.control.position_cycle_s
    aux = 3.0 * np.sin(2 * math.pi * 3.0 * t)  # N m at the motor (N on a force axis)
    z = np.zeros(n)
    return sim.run_arrays(z, z, z, z, aux=aux)


def test_dead_time_scope_feedback_sensor_delays_the_recorded_motor_encoder():
    from plant_helpers import config_with

    from virtualaxis.sim import layout as L

    n, d_cycles = 400, 2
    base = config_with({"sensors": {"dead_time_s": d_cycles * 1e-3}})
    assert base.sensors.dead_time_scope == "position_loop"
    assert base.control.position_feedback == "motor_encoder"
    a = _torque_mode_run(base, n)
    b = _torque_mode_run(base.replace(sensors={"dead_time_scope": "feedback_sensor"}), n)
    assert np.array_equal(a[:, L.O_TABLE_TRUE], b[:, L.O_TABLE_TRUE])  # same motion
    assert np.ptp(a[:, L.O_MOTOR_POS]) > 1.0  # it moved (radians)
    # position_loop: motor_pos is the undelayed encoder; feedback_sensor: the same reading d_cycles later
    assert np.array_equal(b[d_cycles:, L.O_MOTOR_POS], a[:-d_cycles, L.O_MOTOR_POS])
    assert not np.array_equal(b[:, L.O_MOTOR_POS], a[:, L.O_MOTOR_POS])
    # the position feedback was delayed in both, the linear scale in neither (it is not the feedback sensor)
    assert np.array_equal(a[:, L.O_POS_FB], b[:, L.O_POS_FB])
    assert np.array_equal(a[:, L.O_POS_MEAS], b[:, L.O_POS_MEAS])
    # the delayed encoder is the position feedback's sensor: motor_pos x lead/2pi == pos_fb
    r = base.mechanics.lead_m / (2 * math.pi)
    assert np.allclose(b[:, L.O_MOTOR_POS] * r, b[:, L.O_POS_FB], rtol=0, atol=1e-12)


def test_dead_time_scope_feedback_sensor_delays_the_recorded_linear_scale():
    from virtualaxis.sim import layout as L

    n, d_cycles = 300, 3
    cfg = _rigid_p_velocity_axis().replace(sensors={"dead_time_s": d_cycles * 1e-3, "linear_scale_resolution_m": 1e-8})
    a = _torque_mode_run(cfg, n)
    b = _torque_mode_run(cfg.replace(sensors={"dead_time_scope": "feedback_sensor"}), n)
    assert np.array_equal(a[:, L.O_TABLE_TRUE], b[:, L.O_TABLE_TRUE])
    assert np.ptp(a[:, L.O_POS_MEAS]) > 1e-5  # it moved
    assert np.array_equal(b[d_cycles:, L.O_POS_MEAS], a[:-d_cycles, L.O_POS_MEAS])
    assert np.array_equal(b[:, L.O_POS_MEAS], b[:, L.O_POS_FB])


def test_feedback_sensor_dead_time_between_cycles_reads_the_interpolated_position():
    """With every loop at 1 ms, a 1.5 ms feedback-sensor dead time: the reading at t_k is the true position at
    t_k - 1.5 ms, linear between t_k-1 and t_k-2 (the position-loop-only scope rounds D to whole cycles)."""
    from virtualaxis.sim import layout as L

    cfg = _rigid_p_velocity_axis(current_cycle_s=1e-3).replace(
        sensors={"dead_time_s": 1.5e-3, "dead_time_scope": "feedback_sensor"})
    b = _torque_mode_run(cfg, 200)
    x = b[:, L.O_TABLE_TRUE]
    assert np.ptp(x) > 1e-5
    np.testing.assert_allclose(b[2:, L.O_POS_MEAS], 0.5 * (x[1:-1] + x[:-2]), rtol=0, atol=1e-15)
    np.testing.assert_allclose(b[2:, L.O_POS_FB], 0.5 * (x[1:-1] + x[:-2]), rtol=0, atol=1e-15)
    a = _torque_mode_run(cfg.replace(sensors={"dead_time_scope": "position_loop"}), 200)
    assert np.array_equal(a[2:, L.O_POS_FB], x[:-2])  # round(1.5) = 2 cycles, as before the option


def test_dead_time_scope_rejects_unknown_values_naming_the_key():
    from virtualaxis.config import axis_config_from_dict

    d = _dict_of(rigid_force_axis())
    d["sensors"]["dead_time_scope"] = "everything"
    with pytest.raises(ConfigError, match=r"sensors\.dead_time_scope"):
        axis_config_from_dict(d, "x.toml")


def test_speed_estimator_and_time_delay_effects_map_onto_the_config():
    cfg = _rigid_p_velocity_axis()
    est = fx.EFFECTS["speed_estimator"]
    p = {q.name: q for q in est.params(cfg)}
    assert p["speed_estimator_samples"].nominal == 1.0 and fx.is_discrete("speed_estimator_samples")
    assert p["speed_filter_cycles"].nominal == 0.0 and p["speed_filter_cycles"].upper == 20.0
    assert {s["speed_estimator_samples"] for s in est.starts(cfg, {})} == {1.0, 2.0}
    truth = cfg.replace(control={"speed_estimator": "two_sample_difference"})
    fitted = {"speed_estimator_samples": 2.0, "speed_filter_cycles": 0.0}
    out = est.apply(cfg, fitted)
    assert out.control == truth.control
    t = np.arange(800) * 1e-3
    pos = 0.02 * (1 - np.cos(2 * math.pi * 2.0 * t))
    a = simulate_command(out, t, pos, seed=0)
    b = simulate_command(truth, t, pos, seed=0)
    c = simulate_command(cfg, t, pos, seed=0)
    assert np.array_equal(a["force_drive"], b["force_drive"])
    assert not np.array_equal(a["force_drive"], c["force_drive"])
    # a form change alone is a structural change: it pays its way by itself, the unused filter is not judged
    assert fx.relative_change("speed_estimator", cfg, fitted) == math.inf
    assert fx.relative_change("speed_estimator", cfg, {"speed_estimator_samples": 1.0,
                                                       "speed_filter_cycles": 0.0}) == 0.0
    assert fx.implausible("speed_estimator", cfg, fitted, {"speed_filter_cycles": 0.1}, []) == []
    assert fx.implausible("speed_estimator", cfg, {"speed_estimator_samples": 1.0, "speed_filter_cycles": 0.01},
                          {"speed_filter_cycles": 0.1}, [])  # a filter within noise of 0: no answer
    # 2 ms of filter on the 1 ms speed loop maps onto the config in seconds
    assert est.apply(cfg, {"speed_estimator_samples": 1.0, "speed_filter_cycles": 2.0}).control == cfg.replace(
        control={"speed_filter_time_constant_s": 2e-3}).control
    # a one-sample estimate low-passed by half a sample (tau = T / ln 3) is the two-sample estimate: the simpler one
    # (no free parameter) is preferred; a filter of another delay is kept
    assert fx.filter_delay_cycles(1.0 / math.log(3.0)) == pytest.approx(0.5)
    assert fx.reduce_nested("speed_estimator", {"speed_estimator_samples": 1.0, "speed_filter_cycles": 0.91}, {}) == (
        "speed_estimator", {"speed_estimator_samples": 2.0, "speed_filter_cycles": 0.0})
    for c in (0.3, 2.0):
        one_sample = {"speed_estimator_samples": 1.0, "speed_filter_cycles": c}
        assert fx.reduce_nested("speed_estimator", one_sample, {}) is None
    assert fx.reduce_nested("speed_estimator", fitted, {}) is None
    # time_delay fits the scope as a discrete parameter (both scopes started)
    td = fx.EFFECTS["time_delay"]
    assert {s["dead_time_feedback_sensor"] for s in td.starts(cfg, {})} == {0.0, 1.0}
    d = td.apply(cfg, {"dead_time_s": 2e-3, "dead_time_feedback_sensor": 1.0})
    assert d.sensors.dead_time_s == 2e-3 and d.sensors.dead_time_scope == "feedback_sensor"
    assert td.apply(d, {"dead_time_s": 1e-3}).sensors.dead_time_scope == "feedback_sensor"  # scope kept
    assert td.apply(cfg, {"dead_time_s": 1e-3, "dead_time_feedback_sensor": 0.0}).sensors.dead_time_scope == (
        "position_loop")


# ------------------------------------------------------------------------ 3. feed-forward form of a CSP drive
def test_setpoint_difference_feed_forward_equals_the_closed_form_difference_of_a_sine():
    """CSP: v_ff[k] = (x[k] - x[k-1]) / T, a_ff[k] = (v_ff[k] - v_ff[k-1]) / T. For x = A sin(w t) the difference
    is (2 A / T) sin(w T / 2) cos(w (t_k - T / 2)) exactly (a trigonometric identity, not a difference of samples):
    the kernel told to use set-point differences, fed a wrong cmd_vel, must equal the kernel fed that closed form
    with the derivative form."""
    from plant_helpers import config_with

    cfg = config_with({"control": {"velocity_ff_factor": 1.0, "torque_ff_factor": 1.0}})
    n, tp = 1500, cfg.control.position_cycle_s
    amp, w = 0.05, 2 * math.pi * 1.3
    t = np.arange(n) * tp
    x = amp * np.sin(w * t)
    v = 2 * amp / tp * math.sin(w * tp / 2) * np.cos(w * (t - tp / 2))
    v[0] = 0.0  # the first set-point has no predecessor: the caller's value (0 here) is used
    a = np.r_[0.0, np.diff(v)] / tp
    ref_cfg = cfg.replace(control={"velocity_ff_form": "derivative"})
    csp_cfg = cfg.replace(control={"velocity_ff_form": "setpoint_difference"})

    def run(c, vel, acc):
        sim = AxisSimulator(c, initial_position_m=0.0)
        sim.enable(True)
        return sim.run_arrays(x, vel, acc, np.zeros(n))

    from virtualaxis.sim import layout as L

    ref = run(ref_cfg, v, a)
    rng = np.random.default_rng(0)
    junk = rng.normal(size=n)
    junk[0] = 0.0
    csp = run(csp_cfg, junk, junk)
    scale = np.max(np.abs(ref[:, L.O_FOLLOWING]))
    assert np.max(np.abs(csp[:, L.O_FOLLOWING] - ref[:, L.O_FOLLOWING])) < 1e-6 * scale
    # the analytic feed-forward (derivative form, true cos) leads by half a cycle: a visibly different error
    exact = run(ref_cfg, amp * w * np.cos(w * t), -amp * w * w * np.sin(w * t))
    assert np.max(np.abs(exact[:, L.O_FOLLOWING] - ref[:, L.O_FOLLOWING])) > 1e-3 * scale


def test_setpoint_difference_feed_forward_takes_the_callers_value_after_entering_position_control():
    """The first set-point in position control has no predecessor (the last command was the feedback, in velocity
    control): its feed-forward is the caller's, the next ones are set-point differences."""
    from plant_helpers import config_with

    from virtualaxis.sim import layout as L

    cfg = config_with({"control": {"velocity_ff_factor": 1.0, "velocity_ff_form": "setpoint_difference"}})
    g = 2 * math.pi / cfg.mechanics.lead_m  # rad per m
    kv, tp = cfg.control.kv_1_per_s, cfg.control.position_cycle_s
    sim = AxisSimulator(cfg)
    sim.enable(True)
    sim.set_mode(ControlMode.VELOCITY)
    sim.set_velocity_setpoint(0.05)
    sim.advance(300)
    sim.set_mode(ControlMode.POSITION)
    x0 = sim.state.position_m + 1e-3  # a set-point 1 mm ahead: a difference to the last command would be 1 m/s
    xs = [x0 + k * 0.04e-3 for k in range(5)]
    for k, x in enumerate(xs):
        sim.set_position_setpoint(x, 0.05, 0.0)
        sim.advance(1)
        vff = 0.05 if k == 0 else (x - xs[k - 1]) / tp
        assert sim.st[L.S_W_REF] == pytest.approx(g * (kv * sim.st[L.S_FE] + vff), rel=1e-12), k


# ------------------------------------------------------------------------ every option on: kernel vs solve_ivp
def every_option_runs(out=None) -> dict:
    """The kernel and the solve_ivp reference with every option on, and the kernel without the options (a
    background job of the suite: tests/background.py)."""
    from test_plant_reference import every_effect_config

    from virtualaxis.sim.reference import ReferenceAxis

    changes = {"friction": {"viscous_negative_n_s_per_m": 900.0},
               "control": {"speed_estimator": "two_sample_difference", "speed_filter_time_constant_s": 4e-4},
               "sensors": {"dead_time_s": 270e-6, "dead_time_scope": "feedback_sensor"}}  # 8.64 current cycles
    changes["control"].update(velocity_ff_form="setpoint_difference", velocity_ff_factor=1.0)
    cfg = every_effect_config().replace(**changes)
    amp, vmax, dur = 0.05, 0.1, 0.25
    w = vmax / amp
    t = np.arange(int(round(dur / 1e-3)) + 1) * 1e-3
    p, v, a = amp * (1 - np.cos(w * t)), amp * w * np.sin(w * t), amp * w * w * np.cos(w * t)
    kern = simulate_command(cfg, t, p, vel_cmd_m_s=v, acc_cmd_m_s2=a)
    ref = ReferenceAxis(cfg, rtol=1e-8, atol=1e-12).run(t, p, v, a)
    plain = simulate_command(every_effect_config(), t, p, vel_cmd_m_s=v, acc_cmd_m_s2=a)
    keep = ("pos_meas", "pos_fb", "motor_pos")
    return {"lead_m": cfg.mechanics.lead_m,
            **{name: {k: np.asarray(run[k]) for k in keep} for name, run in (("kern", kern), ("ref", ref),
                                                                                ("plain", plain))}}


@pytest.mark.background("every_option_runs")
def test_kernel_with_every_option_on_matches_the_solve_ivp_reference(request):
    """The solve_ivp reference (sim/reference.py: adaptive DOP853 between current-loop samples, event-located
    stick/slip, its own loop code) implements the options from their definitions too; with all of them on, the
    kernel's tracking error agrees with it point by point."""
    job = background.result(request.config, "every_option_runs")
    kern, ref, plain = job["kern"], job["ref"], job["plain"]
    r = job["lead_m"] / (2 * math.pi)
    tol = {"pos_meas": 0.2e-6, "pos_fb": 0.2e-6, "motor_pos": 0.2e-6 / r}
    for ch in tol:
        assert np.max(np.abs(kern[ch] - ref[ch])) < tol[ch], (ch, np.max(np.abs(kern[ch] - ref[ch])))
    # the options change the response by far more than that (the comparison can fail)
    for ch in tol:
        assert np.max(np.abs(kern[ch] - plain[ch])) > 10 * tol[ch], ch
