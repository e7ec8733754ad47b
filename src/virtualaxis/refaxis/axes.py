"""Nominal reference axes (physical parameters with sources), their kernel parameters and their config text.

Two structures:

* ``two_mass``: semi-closed-loop ball screw. Motor side (rotor + coupling + screw, one inertia) drives the
  table through one axial spring (screw, nut, bearings in series) with a parallel dashpot; P position loop
  with velocity feed-forward on the motor encoder at 1 kHz, PI speed loop at 125 us (one-sample encoder
  difference), first-order torque loop. LuGre friction on the table.
* ``rigid_pp``: linear motor, one rigid mass; P position loop and P velocity loop both at 1 kHz on the
  linear scale, force output through a first-order force loop. LuGre friction.

The config writer emits our TOML schema as text (this package imports nothing from ``virtualaxis``).
"""

from __future__ import annotations

import math

from virtualaxis.refaxis import kernel as K

# ---------------------------------------------------------------------------------------------------------
# Physical parameters. Keys carry units. Sources are given where the value is written into a config.
# ---------------------------------------------------------------------------------------------------------
STEEL_DENSITY = 7850.0
STEEL_E = 2.06e11

TWO_MASS: dict[str, float] = {
    "lead_m": 0.020,
    "rotor_inertia_kg_m2": 3.3e-3,
    "coupling_inertia_kg_m2": 0.45e-3,
    "screw_diameter_m": 0.032,
    "screw_root_diameter_m": 0.0275,
    "screw_length_m": 1.0,
    "table_mass_kg": 250.0,
    "axial_stiffness_n_per_m": 1.6e8,
    "axial_position_dependent": 1.0,
    "nut_distance_m": 0.45,
    "damping_ratio": 0.04,
    "motor_viscous_nm_s_per_rad": 2.0e-4,
    "coulomb_n": 30.0,
    "coulomb_negative_n": 30.0,
    "stribeck_n": 0.0,
    "stribeck_velocity_m_s": 0.003,
    "viscous_n_s_per_m": 250.0,
    "viscous_negative_n_s_per_m": 250.0,
    "force_offset_n": 0.0,
    "presliding_m": 0.2e-6,
    "bristle_damping_ratio": 0.5,
    "gap_m": 0.0,
    "resonance_hz": 0.0,
    "resonance_mass_kg": 0.0,
    "resonance_damping": 0.02,
    "lead_error_ppm": 0.0,
    "lead_error_periodic_m": 0.0,
    "lead_error_phase_rad": 0.0,
    "cogging_nm": 0.0,
    "cogging_order": 36.0,
    "cogging_phase_rad": 0.0,
    "alpha_per_k": 11.5e-6,
    "initial_temperature_rise_k": 0.0,
    "thermal_resistance_k_per_w": 0.0,
    "thermal_time_constant_s": 900.0,
    "effort_lag_s": 2.5e-4,
    "torque_constant_nm_per_a": 1.23,
    "rated_torque_nm": 8.0,
    "rated_current_a": 6.5,
    "effort_limit": 24.0,
    "kv_per_s": 40.0,
    "velocity_ff": 1.0,
    "speed_kp": 2.1,
    "speed_ti_s": 0.015,
    "speed_cycle_s": 125e-6,
    "position_cycle_s": 1e-3,
    "substeps": 4,
    "encoder_counts": float(1 << 20),
    "encoder_jitter_counts": 0.3,
    "scale_quantum_m": 2e-8,
    "scale_noise_m": 4e-8,
    "current_quantum_a": 80.0 / 16384,
    "current_noise_a": 0.015,
    "force_quantum_n": 0.0,
    "dead_time_s": 0.0,
    "speed_estimator_samples": 1.0,
    "output_delay_cycles": 0.0,
    "stroke_m": 0.5,
    "full_closed": 0.0,
}

RIGID_PP: dict[str, float] = {
    "lead_m": 0.0,
    "table_mass_kg": 60.0,
    "coulomb_n": 25.0,
    "coulomb_negative_n": 25.0,
    "stribeck_n": 0.0,
    "stribeck_velocity_m_s": 0.003,
    "viscous_n_s_per_m": 150.0,
    "viscous_negative_n_s_per_m": 150.0,
    "force_offset_n": 0.0,
    "presliding_m": 0.2e-6,
    "bristle_damping_ratio": 0.5,
    "resonance_hz": 0.0,
    "resonance_mass_kg": 0.0,
    "resonance_damping": 0.02,
    "effort_lag_s": 3e-4,
    "effort_limit": 1500.0,
    "kv_per_s": 20.0,
    "velocity_ff": 0.0,
    "speed_kp": 5000.0,
    "speed_ti_s": 0.0,
    "speed_cycle_s": 1e-3,
    "position_cycle_s": 1e-3,
    "substeps": 32,
    "scale_quantum_m": 1e-7,
    "scale_noise_m": 3e-8,
    "force_quantum_n": 0.05,
    "dead_time_s": 0.0,
    "speed_estimator_samples": 1.0,
    "output_delay_cycles": 0.0,
    "stroke_m": 0.4,
    "full_closed": 0.0,
}

# Full closed loop: the two-mass ball screw with the position loop on the linear scale (speed loop on the motor
# encoder); Kv lowered as usual when the mechanics is inside the position loop.
FULL_CLOSED: dict[str, float] = dict(TWO_MASS, kv_per_s=30.0, full_closed=1.0)

NOMINAL = {"two_mass": TWO_MASS, "rigid_pp": RIGID_PP, "full_closed": FULL_CLOSED}
SCREW_STRUCTURES = ("two_mass", "full_closed")


def screw_inertia_kg_m2(phys: dict) -> float:
    """Rotational inertia of a solid steel screw, pi/32 rho L d^4 [kg m^2]."""
    return math.pi / 32 * STEEL_DENSITY * phys["screw_length_m"] * phys["screw_diameter_m"] ** 4


def motor_side_inertia_kg_m2(phys: dict) -> float:
    """Rotor + coupling + screw [kg m^2] (all turn with the motor angle in the two-mass model)."""
    return phys["rotor_inertia_kg_m2"] + phys["coupling_inertia_kg_m2"] + screw_inertia_kg_m2(phys)


def radius_m_per_rad(phys: dict) -> float:
    """lead / 2 pi [m/rad]."""
    return phys["lead_m"] / (2 * math.pi)


def screw_ea_n(phys: dict) -> float:
    """E A of the screw core (root diameter) [N]."""
    return STEEL_E * math.pi / 4 * phys["screw_root_diameter_m"] ** 2


def two_mass_frequencies(phys: dict) -> tuple[float, float]:
    """(anti-resonance, resonance) of the motor-side FRF [rad/s]: sqrt(k / m_t), sqrt(k (1/m_m + 1/m_t)),
    with m_m = J / r^2 the motor side reflected through the lead."""
    k = phys["axial_stiffness_n_per_m"]
    m_m = motor_side_inertia_kg_m2(phys) / radius_m_per_rad(phys) ** 2
    m_t = phys["table_mass_kg"]
    return math.sqrt(k / m_t), math.sqrt(k * (1 / m_m + 1 / m_t))


def kernel_params(structure: str, phys: dict) -> dict:
    """Map physical parameters to the kernel's parameter names (``kernel.PARAM_NAMES``)."""
    two = structure in SCREW_STRUCTURES
    m_total = phys["table_mass_kg"]
    mr = phys["resonance_mass_kg"] if phys["resonance_hz"] > 0 else 0.0
    m_rigid = m_total - mr
    fc_min = max(min(phys["coulomb_n"], phys["coulomb_negative_n"]), 1e-3)
    sigma0 = fc_min / phys["presliding_m"]
    out = {
        "structure": 0.0 if two else 1.0,
        "m_kg": m_rigid,
        "sigma0_n_per_m": sigma0,
        "sigma1_n_s_per_m": 2 * phys["bristle_damping_ratio"] * math.sqrt(sigma0 * m_total),
        "fc_pos_n": phys["coulomb_n"],
        "fc_neg_n": phys["coulomb_negative_n"],
        "fs_n": phys["stribeck_n"],
        "vs_m_s": phys["stribeck_velocity_m_s"],
        "fv_pos_n_s_per_m": phys["viscous_n_s_per_m"],
        "fv_neg_n_s_per_m": phys["viscous_negative_n_s_per_m"],
        "f_off_n": phys["force_offset_n"],
        "tau_u_s": phys["effort_lag_s"],
        "u_max": phys["effort_limit"],
        "kv_per_s": phys["kv_per_s"],
        "kff": phys["velocity_ff"],
        "kp_speed": phys["speed_kp"],
        "ti_speed_s": phys["speed_ti_s"],
        "ts_speed_s": phys["speed_cycle_s"],
        "n_speed": round(phys["position_cycle_s"] / phys["speed_cycle_s"]),
        "n_sub": phys["substeps"],
        "delay_s": phys["dead_time_s"],
        "est_samples": phys["speed_estimator_samples"],
        "ctrl_on": 1.0,
        "t_pos_s": phys["position_cycle_s"],
        "out_delay_cycles": phys["output_delay_cycles"],
    }
    if mr > 0:
        wr = 2 * math.pi * phys["resonance_hz"]
        out.update(mr_kg=mr, kr_n_per_m=mr * wr**2, cr_n_s_per_m=2 * phys["resonance_damping"] * mr * wr)
    if two:
        k = phys["axial_stiffness_n_per_m"]
        _wa, wr2 = two_mass_frequencies(phys)
        out.update(
            r_m_per_rad=radius_m_per_rad(phys),
            j_kg_m2=motor_side_inertia_kg_m2(phys),
            bm_nm_s_per_rad=phys["motor_viscous_nm_s_per_rad"],
            k_mid_n_per_m=k,
            ea_n=screw_ea_n(phys) if phys["axial_position_dependent"] else 0.0,
            d0_m=phys["nut_distance_m"],
            c_ax_n_s_per_m=2 * phys["damping_ratio"] * k / wr2,
            gap_m=phys["gap_m"],
            lead_ppm=phys["lead_error_ppm"],
            lead_amp_m=phys["lead_error_periodic_m"],
            lead_phase_rad=phys["lead_error_phase_rad"],
            cog_amp_nm=phys["cogging_nm"],
            cog_order=phys["cogging_order"],
            cog_phase_rad=phys["cogging_phase_rad"],
            alpha_per_k=phys["alpha_per_k"],
            dtemp0_k=phys["initial_temperature_rise_k"],
            rth_k_per_w=phys["thermal_resistance_k_per_w"],
            tau_th_s=phys["thermal_time_constant_s"],
            enc_counts=phys["encoder_counts"],
            enc_jitter_counts=phys["encoder_jitter_counts"],
            fb_scale=phys["full_closed"],
            fb_quantum_m=phys["scale_quantum_m"],
            fb_noise_m=phys["scale_noise_m"],
        )
    else:
        out.update(fb_quantum_m=phys["scale_quantum_m"], fb_noise_m=phys["scale_noise_m"], tau_th_s=1.0)
    return out


def kernel_vector(structure: str, phys: dict):
    """``kernel.param_vector`` of :func:`kernel_params`."""
    return K.param_vector(kernel_params(structure, phys))


# ---------------------------------------------------------------------------------------------------------
# Config text in our schema
# ---------------------------------------------------------------------------------------------------------
def _v(value: float | int, source: str) -> str:
    src = source.replace("\\", "\\\\").replace('"', '\\"')
    return f'{{ value = {value!r}, source = "{src}" }}'


def config_toml(structure: str, phys: dict, name: str, header: str) -> str:
    """The nominal axis config (our schema) for ``phys`` — the caller passes the nominal parameters, i.e.
    WITHOUT the withheld effect(s). Every value names its source."""
    lines = [f"# {h}" for h in header.splitlines()]
    add = lines.append
    if structure in SCREW_STRUCTURES:
        full = bool(phys["full_closed"])
        r = radius_m_per_rad(phys)
        j = motor_side_inertia_kg_m2(phys)
        k = phys["axial_stiffness_n_per_m"]
        kt = phys["torque_constant_nm_per_a"]
        lq, rs = 6.0e-3, 0.9
        add("\n[axis]")
        add(f'name = "{name}"')
        add(f"stroke_m = {_v(phys['stroke_m'], 'chosen: 500 mm travel; the test strokes are 100 mm')}")
        add(f"nut_offset_m = {_v(phys['nut_distance_m'], 'drawing: fixed bearing to nut with the table at 0')}")
        add("\n[mechanics]")
        add('model = "two_mass"')
        add(f"lead_m = {_v(phys['lead_m'], 'catalogue: ball screw 32 x 20')}")
        add("motor_inertia_kg_m2 = " + _v(j, (
            f"rotor {phys['rotor_inertia_kg_m2']:g} (motor catalogue) + coupling {phys['coupling_inertia_kg_m2']:g}"
            f" (coupling catalogue) + screw {screw_inertia_kg_m2(phys):.4g} (pi/32 rho L d^4, d 32 mm, L 1 m);"
            " all on the motor side of the one spring")))
        add(f"coupling_inertia_kg_m2 = {_v(0.0, 'lumped into motor_inertia_kg_m2')}")
        add(f"screw_end_inertia_kg_m2 = {_v(0.0, 'lumped into motor_inertia_kg_m2')}")
        add(f"table_mass_kg = {_v(phys['table_mass_kg'], 'weighed: table, nut and fixture')}")
        add("equivalent_torsional_stiffness_nm_per_rad = " + _v(k * r * r, (
            f"axial stiffness {k:.4g} N/m at mid-stroke (bearings, screw, nut in series; catalogue values)"
            " x (lead / 2 pi)^2")))
        add(f"modal_damping_ratio = {_v(phys['damping_ratio'], 'chosen: 4 % for a preloaded screw drive')}")
        add(f"motor_viscous_nm_s_per_rad = {_v(phys['motor_viscous_nm_s_per_rad'], 'motor catalogue: bearing losses')}")
        add(f"table_viscous_n_s_per_m = {_v(0.0, 'friction section carries the viscous term')}")
        add("\n[backlash]")
        add("enabled = false")
        add(f"gap_m = {_v(0.0, 'preloaded double nut: no backlash expected')}")
        add("\n[friction]")
        add("enabled = true")
        add(f"coulomb_n = {_v(phys['coulomb_n'], 'reversal test at 10 mm/min on the machine (both directions)')}")
        add(f"coulomb_negative_n = {_v(-1.0, 'symmetric (same as coulomb_n)')}")
        add(f"stribeck_n = {_v(phys['stribeck_n'], 'not measured: assumed none')}")
        add(f"stribeck_velocity_m_s = {_v(0.001, 'textbook: about 1 mm/s for rolling guides')}")
        add(f"stribeck_exponent = {_v(2.0, 'Gaussian Stribeck curve (Armstrong-Helouvry)')}")
        add(f"viscous_n_s_per_m = {_v(phys['viscous_n_s_per_m'], 'constant-speed runs at F1000..F6000')}")
        add("\n[actuator]")
        add('kind = "pmsm"')
        add("\n[motor]")
        add(f"pole_pairs = {_v(3, 'motor catalogue: 6 poles')}")
        add(f"rs_ohm = {_v(rs, 'motor catalogue')}")
        add(f"ld_h = {_v(lq, 'motor catalogue')}")
        add(f"lq_h = {_v(lq, 'motor catalogue')}")
        add(f"torque_constant_nm_per_a = {_v(kt, 'motor catalogue: 8 N m / 6.5 A')}")
        add(f"rated_current_a = {_v(phys['rated_current_a'], 'motor catalogue')}")
        add(f"rated_torque_nm = {_v(phys['rated_torque_nm'], 'motor catalogue')}")
        add(f"rated_speed_rpm = {_v(3000.0, 'motor catalogue')}")
        add(f"cogging_amplitude_nm = {_v(0.0, 'not measured: assumed none')}")
        add(f"cogging_periods_per_rev = {_v(phys['cogging_order'], 'motor design: 36 slots, 6 poles, lcm = 36')}")
        add("\n[inverter]")
        add('model = "averaged"')
        add(f"dc_link_v = {_v(600.0, 'drive catalogue')}")
        add("\n[control]")
        add(f"current_cycle_s = {_v(62.5e-6, 'drive parameter list')}")
        add(f"speed_cycle_s = {_v(phys['speed_cycle_s'], 'drive parameter list')}")
        add(f"position_cycle_s = {_v(phys['position_cycle_s'], 'drive parameter list')}")
        tau = phys["effort_lag_s"]
        add("current_kp_v_per_a = " + _v(lq / tau, (
            f"drive: current loop tuned to a first-order lag of {tau * 1e6:g} us, Kp = L_q / tau")))
        add(f"current_ti_s = {_v(lq / rs, 'drive: current PI zero on the winding pole, Ti = L_q / R_s')}")
        add(f"speed_kp_nm_s_per_rad = {_v(phys['speed_kp'], 'drive parameter list')}")
        add(f"speed_ti_s = {_v(phys['speed_ti_s'], 'drive parameter list')}")
        kv = phys["kv_per_s"]
        add(f"kv_per_s = {_v(kv, f'NC machine data: Kv {kv * 60 / 1000:g} (m/min)/mm')}")
        add(f"velocity_ff_factor = {_v(phys['velocity_ff'], 'NC machine data: speed feed-forward 100 %')}")
        add(f"torque_ff_factor = {_v(0.0, 'NC machine data: off')}")
        add(f"current_limit_a = {_v(phys['effort_limit'] / kt, 'drive: 3 x rated torque')}")
        add(f"speed_limit_rpm = {_v(3000.0, 'drive: rated speed')}")
        add('position_feedback = "linear_scale"' if full else 'position_feedback = "motor_encoder"')
        if phys["output_delay_cycles"]:
            add("output_delay_s = " + _v(phys["output_delay_cycles"] * phys["speed_cycle_s"], "drive timing"))
        add("\n[sensors]")
        add(f"motor_encoder_counts_per_rev = {_v(int(phys['encoder_counts']), 'motor catalogue: 20-bit encoder')}")
        add(f"linear_scale_resolution_m = {_v(phys['scale_quantum_m'], 'linear scale data sheet: 20 nm')}")
        add(f"dead_time_s = {_v(0.0, 'drive: no feedback delay expected')}")
        add(f"position_noise_m = {_v(phys['scale_noise_m'], 'scale at standstill, 1 sigma')}")
        add(f"current_noise_a = {_v(phys['current_noise_a'], 'current at standstill, 1 sigma')}")
        add("\n[effects]")
        add(f"thermal_expansion_per_k = {_v(phys['alpha_per_k'], 'steel')}")
        add(f"thermal_resistance_k_per_w = {_v(0.0, 'not measured: assumed none')}")
        add(f"thermal_time_constant_s = {_v(phys['thermal_time_constant_s'], 'chosen: screw heat-up 15 min')}")
        add(f"initial_temperature_rise_k = {_v(0.0, 'traces recorded cold')}")
        add("\n[limits]")
        add(f"max_velocity_m_s = {_v(1.0, 'rated speed 3000/min x 20 mm lead')}")
        add(f"max_acceleration_m_s2 = {_v(5.0, 'NC machine data')}")
        add(f"travel_min_m = {_v(-0.25, 'NC software limit')}")
        add(f"travel_max_m = {_v(0.25, 'NC software limit')}")
    else:
        add("\n[axis]")
        add(f'name = "{name}"')
        add(f"stroke_m = {_v(phys['stroke_m'], 'chosen: linear-motor stage, 400 mm travel')}")
        add(f"nut_offset_m = {_v(0.0, 'no screw')}")
        add("\n[mechanics]")
        add('model = "rigid"')
        add(f"lead_m = {_v(0.0, 'direct drive')}")
        add(f"table_mass_kg = {_v(phys['table_mass_kg'], 'weighed: carriage, magnet plate and fixture')}")
        add("\n[friction]")
        add("enabled = true")
        add(f"coulomb_n = {_v(phys['coulomb_n'], 'slow reversal test, both directions')}")
        add(f"coulomb_negative_n = {_v(-1.0, 'symmetric (same as coulomb_n)')}")
        add(f"stribeck_n = {_v(phys['stribeck_n'], 'not measured: assumed none')}")
        add(f"stribeck_velocity_m_s = {_v(0.001, 'textbook: about 1 mm/s for rolling guides')}")
        add(f"stribeck_exponent = {_v(2.0, 'Gaussian Stribeck curve (Armstrong-Helouvry)')}")
        add(f"viscous_n_s_per_m = {_v(phys['viscous_n_s_per_m'], 'constant-speed runs')}")
        add("\n[actuator]")
        add('kind = "force"')
        add(f"force_limit_n = {_v(phys['effort_limit'], 'amplifier: peak force')}")
        add(f"force_lag_s = {_v(phys['effort_lag_s'], 'amplifier: current loop as a first-order lag')}")
        add("\n[control]")
        add(f"current_cycle_s = {_v(62.5e-6, 'amplifier data sheet')}")
        add(f"speed_cycle_s = {_v(phys['speed_cycle_s'], 'controller: both loops at 1 kHz')}")
        add(f"position_cycle_s = {_v(phys['position_cycle_s'], 'controller: both loops at 1 kHz')}")
        add(f"velocity_kp_n_s_per_m = {_v(phys['speed_kp'], 'controller: P velocity gain')}")
        add(f"speed_ti_s = {_v(0.0, 'controller: P only (no integral term)')}")
        add(f"kv_per_s = {_v(phys['kv_per_s'], 'controller: P position gain')}")
        add(f"velocity_ff_factor = {_v(0.0, 'controller: no feed-forward')}")
        add('position_feedback = "linear_scale"')
        if phys["speed_estimator_samples"] == 2:
            add('speed_estimator = "two_sample_difference"')
        if phys["output_delay_cycles"]:
            add("output_delay_s = " + _v(phys["output_delay_cycles"] * phys["speed_cycle_s"],
                                         "controller: output applied one cycle after its samples"
                                         if phys["output_delay_cycles"] == 1 else "controller timing"))
        add("\n[sensors]")
        add(f"motor_encoder_counts_per_rev = {_v(0, 'no rotary encoder')}")
        add(f"linear_scale_resolution_m = {_v(phys['scale_quantum_m'], 'scale data sheet: 0.1 um')}")
        add(f"dead_time_s = {_v(0.0, 'controller: no feedback delay expected')}")
        add(f"position_noise_m = {_v(phys['scale_noise_m'], 'scale at standstill, 1 sigma')}")
        add("\n[limits]")
        add(f"max_velocity_m_s = {_v(1.0, 'amplifier / stage data sheet')}")
        add(f"max_acceleration_m_s2 = {_v(20.0, 'stage data sheet')}")
        add(f"travel_min_m = {_v(-0.2, 'controller software limit')}")
        add(f"travel_max_m = {_v(0.2, 'controller software limit')}")
    return "\n".join(lines) + "\n"
