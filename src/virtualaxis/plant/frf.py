"""Frequency responses of the linearised axis: mechanics, speed loop and position loop.

Mechanics: ``H(jw) = C (jw I - A)^-1 B`` of the lumped model (nut contact engaged, structural damping) from
the actuator input to motor speed and to table position.

Loops (continuous-time equivalents of the digital cascade, the usual drive-engineering approximation): the
current loop as ``w_c / (s + w_c)`` with ``w_c = K_p,i / L_q`` and a delay of 1.5 current cycles (computation
delay + ZOH); the speed controller ``K_p (1 + 1 / (s T_n))`` with a delay of one speed cycle (difference-quotient
measurement + ZOH); the position controller ``K_v`` (+ speed feed-forward) with a delay of one position cycle.
The time-domain simulator is the reference for anything these approximations leave out.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from virtualaxis.config import AxisConfig
from virtualaxis.plant.mechanics import (
    U_ACTUATOR,
    build_mechanics,
    damping_matrix,
    structural_damping_coefficient,
)


@dataclass
class Frf:
    name: str
    freq_hz: np.ndarray
    response: np.ndarray  # complex
    unit: str

    @property
    def magnitude_db(self) -> np.ndarray:
        return 20 * np.log10(np.maximum(np.abs(self.response), 1e-300))

    @property
    def phase_deg(self) -> np.ndarray:
        return np.degrees(np.unwrap(np.angle(self.response)))


def mechanical_frf(cfg: AxisConfig, freq_hz: np.ndarray, nut_position_m: float) -> dict[str, Frf]:
    """Actuator -> motor speed [rad/s per N m] and actuator -> table position [m per N m] (or per N)."""
    mech = build_mechanics(cfg, nut_position_m)
    m = mech.mass_matrix()
    k = mech.stiffness_matrix(True)
    c = damping_matrix(mech, structural_damping_coefficient(cfg), True)
    g = mech.input_matrix()[:, U_ACTUATOR]
    w = 2 * np.pi * np.asarray(freq_hz, dtype=float)
    speed = np.zeros(len(w), complex)
    pos = np.zeros(len(w), complex)
    mvec = mech.motor_angle_vector
    for i, wi in enumerate(w):
        dyn = -(wi**2) * m + 1j * wi * c + k
        q = np.linalg.solve(dyn, g)
        pos[i] = q[mech.table_body]
        speed[i] = 1j * wi * (mvec @ q)
    unit_in = "N" if cfg.actuator.kind == "force" else "N m"
    return {
        "mechanics_speed": Frf("actuator -> motor speed", np.asarray(freq_hz), speed, f"rad/s per {unit_in}"),
        "mechanics_position": Frf("actuator -> table position", np.asarray(freq_hz), pos, f"m per {unit_in}"),
    }


def loop_frfs(cfg: AxisConfig, freq_hz: np.ndarray, nut_position_m: float) -> dict[str, Frf]:
    """Mechanics, closed speed loop and closed position loop (and the open loops)."""
    f = np.asarray(freq_hz, dtype=float)
    s = 2j * np.pi * f
    mech = mechanical_frf(cfg, f, nut_position_m)
    c = cfg.control
    force = cfg.actuator.kind == "force"
    r = cfg.mechanics.lead_m / (2 * math.pi) if cfg.mechanics.lead_m > 0 else 1.0
    if force:
        # the 'speed' of a force axis is the table velocity
        p_speed = s * mech["mechanics_position"].response
        kp = c.velocity_kp_n_s_per_m
        g_cur = 1.0 / (1.0 + s * cfg.actuator.force_lag_s) * np.exp(-s * c.current_cycle_s)
    else:
        p_speed = mech["mechanics_speed"].response
        kp = c.speed_kp_nm_s_per_rad
        wc = c.current_kp_v_per_a / cfg.motor.lq_h
        g_cur = wc / (s + wc) * np.exp(-1.5 * s * c.current_cycle_s)
    ctrl = kp * (1 + (1 / (s * c.speed_ti_s) if c.speed_ti_s > 0 else 0))
    open_speed = ctrl * g_cur * p_speed * np.exp(-s * c.speed_cycle_s)
    closed_speed = ctrl * g_cur * p_speed / (1 + open_speed)
    # position: table position per speed reference, through the speed loop and the mechanics
    x_per_speed = np.divide(mech["mechanics_position"].response, p_speed, out=np.zeros_like(s), where=p_speed != 0)
    plant_pos = closed_speed * x_per_speed
    kv = c.kv_1_per_s
    delay_pos = np.exp(-s * c.position_cycle_s)
    gain = (1.0 / r) if not force else 1.0  # table error -> speed reference
    open_pos = kv * gain * plant_pos * delay_pos
    closed_pos = (kv + c.velocity_ff_factor * s) * gain * plant_pos * delay_pos / (1 + open_pos)
    return {
        **mech,
        "speed_open_loop": Frf("speed loop, open", f, open_speed, "1"),
        "speed_closed_loop": Frf("speed loop, closed (ref -> actual)", f, closed_speed, "1"),
        "position_open_loop": Frf("position loop, open", f, open_pos, "1"),
        "position_closed_loop": Frf("position loop, closed (cmd -> table)", f, closed_pos, "1"),
    }


def bandwidth_hz(frf: Frf, level_db: float = -3.0) -> float:
    """First frequency at which the magnitude falls below ``level_db`` (relative to the lowest frequency)."""
    mag = frf.magnitude_db - frf.magnitude_db[0]
    idx = np.flatnonzero(mag < level_db)
    return float(frf.freq_hz[idx[0]]) if idx.size else float("nan")
