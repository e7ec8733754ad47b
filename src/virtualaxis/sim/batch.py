"""Batch simulation: a whole command in, trace columns (``docs/reference/trace-format.md``) out."""

from __future__ import annotations

import numpy as np

from virtualaxis.config import AxisConfig
from virtualaxis.sim import layout as L
from virtualaxis.sim.profiles import check_limits, parse_profile, sample_profile
from virtualaxis.sim.simulator import AxisSimulator

# trace-format column -> kernel output index
TRACE_COLUMNS = {
    "pos_cmd": L.O_POS_CMD,
    "pos_meas": L.O_POS_MEAS,
    "pos_fb": L.O_POS_FB,
    "motor_pos": L.O_MOTOR_POS,
    "vel_meas": L.O_VEL,
    "torque_meas": L.O_TORQUE,
    "current_q": L.O_CURRENT_Q,
    "force_drive": L.O_FORCE_DRIVE,
    "force_ext": L.O_FORCE_EXT,
    "following_error": L.O_FOLLOWING,
}
# extra internal signals, useful for studies and the diagnosis
EXTRA_COLUMNS = {
    "table_true": L.O_TABLE_TRUE,
    "motor_speed": L.O_MOTOR_SPEED,
    "current_d": L.O_CURRENT_D,
    "voltage_q": L.O_VOLT_Q,
    "voltage_d": L.O_VOLT_D,
    "friction_force": L.O_FRICTION,
    "stuck": L.O_STUCK,
    "contact_force": L.O_CONTACT_F,
    "voltage_saturated": L.O_VSAT,
    "current_limited": L.O_ILIM,
    "electrical_power": L.O_POWER,
    "screw_temperature_rise": L.O_TEMP,
    "airgap_torque": L.O_AIRGAP,
    "current_ripple_rms": L.O_RIPPLE,
}


def columns_for(cfg: AxisConfig) -> list[str]:
    """The trace columns an axis of this kind produces."""
    cols = ["pos_cmd", "pos_meas", "pos_fb", "motor_pos", "vel_meas"]
    if cfg.actuator.kind == "force":
        cols += ["force_drive"]
        if cfg.mechanics.lead_m <= 0:
            cols.remove("motor_pos")
    else:
        cols += ["torque_meas", "current_q"]
    return cols + ["force_ext", "following_error"]


def rows_to_columns(cfg: AxisConfig, out: np.ndarray, extras: bool = False) -> dict[str, np.ndarray]:
    res = {"t": out[:, L.O_T].copy()}
    for name in columns_for(cfg):
        res[name] = out[:, TRACE_COLUMNS[name]].copy()
    if extras:
        for name, idx in EXTRA_COLUMNS.items():
            res[name] = out[:, idx].copy()
    return res


def derivative(t: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Central-difference derivative (one-sided at the ends)."""
    if len(x) < 2:
        return np.zeros_like(x)
    return np.gradient(x, t)


def backward_difference(x: np.ndarray, cycle_s: float) -> np.ndarray:
    """``(x_k - x_k-1) / cycle_s`` (0 at the first sample): the set-point difference a CSP drive uses."""
    out = np.zeros_like(x)
    out[1:] = np.diff(x) / cycle_s
    return out


def simulate_command(
    cfg: AxisConfig,
    t_s: np.ndarray,
    pos_cmd_m: np.ndarray,
    force_ext_n: np.ndarray | None = None,
    seed: int | None = None,
    *,
    extras: bool = False,
    sim: AxisSimulator | None = None,
    vel_cmd_m_s: np.ndarray | None = None,
    acc_cmd_m_s2: np.ndarray | None = None,
) -> dict[str, np.ndarray]:
    """Simulate the axis following a sampled position command; outputs are sampled back on ``t_s``.

    The command is resampled (linearly) to the position-loop cycle; the velocity and acceleration
    feed-forward come from its derivatives unless given. The axis starts at rest at ``pos_cmd_m[0]``.
    """
    t_s = np.asarray(t_s, dtype=float)
    pos_cmd_m = np.asarray(pos_cmd_m, dtype=float)
    cyc = cfg.control.position_cycle_s
    t0 = t_s[0]
    n = int(np.floor((t_s[-1] - t0) / cyc + 1e-9)) + 1
    tc = t0 + np.arange(n) * cyc
    on_grid = len(t_s) == n and np.allclose(t_s, tc, rtol=0, atol=cyc * 1e-6)
    pos = pos_cmd_m.copy() if on_grid else np.interp(tc, t_s, pos_cmd_m)
    setpoint_difference = cfg.control.velocity_ff_form == "setpoint_difference"
    if vel_cmd_m_s is None:
        # a CSP drive derives its speed feed-forward from consecutive set-points (backward difference, held)
        vel = backward_difference(pos, cyc) if setpoint_difference else derivative(tc, pos)
    else:
        vel = np.asarray(vel_cmd_m_s, float) if on_grid else np.interp(tc, t_s, vel_cmd_m_s)
    if acc_cmd_m_s2 is None:
        acc = backward_difference(vel, cyc) if setpoint_difference else derivative(tc, vel)
    else:
        acc = np.asarray(acc_cmd_m_s2, float) if on_grid else np.interp(tc, t_s, acc_cmd_m_s2)
    if force_ext_n is None:
        fext = np.zeros(n)
    else:
        fext = np.asarray(force_ext_n, float) if on_grid else np.interp(tc, t_s, force_ext_n)
    if sim is None:
        sim = AxisSimulator(cfg, seed=seed, initial_position_m=float(pos[0]))
    else:
        sim.reset(float(pos[0]))
    sim.enable(True)
    out = sim.run_arrays(pos, vel, acc, fext)
    out[:, L.O_T] += t0
    cols = rows_to_columns(cfg, out, extras)
    if not on_grid:
        cols = {k: (np.interp(t_s, tc, v) if k != "t" else t_s.copy()) for k, v in cols.items()}
    return cols


def simulate_profile(cfg: AxisConfig, spec: str, duration_s: float | None = None, seed: int | None = None,
                     *, extras: bool = False, check: bool = True) -> dict[str, dict[str, np.ndarray]]:
    """Simulate a SPEC profile (see :mod:`virtualaxis.sim.profiles`); one trace per axis name."""
    prof = parse_profile(spec, cfg)
    dur = float(duration_s if duration_s is not None else prof.natural_duration_s)
    cyc = cfg.control.position_cycle_s
    if check:
        check_limits(prof, cfg, dur, cyc)
    t = np.arange(int(round(dur / cyc)) + 1) * cyc
    res = {}
    for name, (p, v, a) in sample_profile(prof, t, dur).items():
        res[name] = simulate_command(cfg, t, p, seed=seed, extras=extras, vel_cmd_m_s=v, acc_cmd_m_s2=a)
    return res
