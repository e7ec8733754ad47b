"""Kernel parameters of the drive and axis options that real drives have and the first kernel did not
(the vocabulary real axes need). Each option is a config key whose default reproduces the kernel's
behaviour before the option existed bit for bit; :func:`fill_option_parameters` writes them into the kernel's
parameter vector (called by :func:`virtualaxis.sim.simulator.build_parameters`).

* ``friction.viscous_negative_n_s_per_m``: viscous friction for -v [N s/m] (direction-dependent viscous friction).
* ``control.speed_estimator``, ``control.speed_filter_time_constant_s``: how the speed loop estimates the speed from
  the quantised position it samples every speed cycle (one- or two-sample difference, optional first-order filter).
* ``control.velocity_ff_form``: the speed (and torque) feed-forward the position loop adds, from the caller's
  command derivative (``derivative``) or, as a CiA 402 CSP drive receiving one set-point per position cycle does,
  from the set-point differences (``setpoint_difference``: v_ff[k] = (x[k] - x[k-1]) / T_pos, a_ff[k] =
  (v_ff[k] - v_ff[k-1]) / T_pos, held for the cycle).
* ``control.output_delay_s``: the speed loop's computation delay, whole speed cycles from its samples to applying
  its output (``speed_cycle_s``: sample at k, compute, apply at k+1).
* ``sensors.dead_time_scope``: whether ``sensors.dead_time_s`` delays only the position loop's feedback or the
  feedback sensor's reading everywhere (speed loop, recorded channel).
"""

from __future__ import annotations

import math

import numpy as np

from virtualaxis.config import AxisConfig, ConfigError
from virtualaxis.sim import layout as L


def viscous_negative_n_s_per_m(cfg: AxisConfig) -> float:
    """Viscous coefficient for -v [N s/m]: ``friction.viscous_negative_n_s_per_m``, or the +v coefficient when
    that is negative (the default, "same as viscous_n_s_per_m")."""
    f = cfg.friction
    return f.viscous_negative_n_s_per_m if f.viscous_negative_n_s_per_m >= 0 else f.viscous_n_s_per_m


def speed_filter_gain(cycle_s: float, tau_s: float) -> float:
    """Gain a = 1 - exp(-T / tau) of the first-order speed filter sampled every ``cycle_s`` = T [s] (the exact,
    step-invariant discretisation of 1 / (1 + s tau) for an input held over the sample); 0 for no filter."""
    return -math.expm1(-cycle_s / tau_s) if tau_s > 0 else 0.0


def dead_time_cycles(cfg: AxisConfig) -> tuple[int, float]:
    """The feedback-sensor dead time D = ``sensors.dead_time_s`` in current cycles T: (floor(D / T), the fraction
    beyond it). With ``dead_time_scope = "feedback_sensor"`` the sensor's reading at t is its true value at t - D,
    interpolated linearly between the states at the current-cycle instants around it (the position-loop-only scope
    keeps its rounding to whole cycles). A ratio within 1e-9 of an integer counts as that integer."""
    x = cfg.sensors.dead_time_s / cfg.control.current_cycle_s
    if abs(x - round(x)) < 1e-9:
        x = float(round(x))
    n0 = int(math.floor(x))
    if cfg.sensors.dead_time_scope == "feedback_sensor" and n0 + 1 >= L.RING_SIZE:
        raise ConfigError(cfg.path, "sensors.dead_time_s",
                          f"must be below {(L.RING_SIZE - 1) * cfg.control.current_cycle_s:.4f} s")
    return n0, x - n0


def fill_option_parameters(pr: np.ndarray, cfg: AxisConfig) -> None:
    """Write the options' kernel parameters into ``pr`` (in place)."""
    c = cfg.control
    pr[L.P_FV_NEG] = viscous_negative_n_s_per_m(cfg)
    pr[L.P_DEAD_SENSOR] = 1.0 if cfg.sensors.dead_time_scope == "feedback_sensor" else 0.0
    pr[L.P_NDEAD0], pr[L.P_DEAD_FRAC] = dead_time_cycles(cfg)
    pr[L.P_EST2] = 1.0 if c.speed_estimator == "two_sample_difference" else 0.0
    pr[L.P_SPD_FILT] = speed_filter_gain(c.speed_cycle_s, c.speed_filter_time_constant_s)
    pr[L.P_FF_SETPOINT] = 1.0 if c.velocity_ff_form == "setpoint_difference" else 0.0
    pr[L.P_TPOS] = c.position_cycle_s
    pr[L.P_OUT_DELAY] = float(round(c.output_delay_s / c.speed_cycle_s))
