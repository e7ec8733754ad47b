"""Plausibility bounds and unit conversion for every physical parameter of an axis config.

Bounds say what a servo feed axis can physically be, from a micro stage to a large gantry; a value outside
them is a typing error (1e-300 kg, 1e17 pole pairs) or a unit error (mm written as m), and the loader refuses
it naming the allowed range. The numerical settings (``simulation.*``, ``inverter.svpwm_substeps``) are bounded
by the memory and time they cost, derived below. Each bound is inclusive; ``0`` is allowed outside a positive
range only where :data:`ZERO_MEANS` gives it a meaning ("none", "rigid", "ideal", "derived from ...").

Units: a key's unit is in its name (``lead_m``). A value may be written with another unit of the same
quantity, ``lead_m = { value = 16, unit = "mm" }``; :func:`convert_unit` converts it to the key's SI unit
with the table :data:`UNIT_FACTORS`, and refuses a unit of another quantity rather than ignoring it.
"""

from __future__ import annotations

import math

# ---- numerical settings: bounds from memory and time -------------------------------------------------------
#: Largest mechanical step rate the kernel is asked for [1/s]. One mechanical step of the six-body model costs
#: about 0.12 us of compiled kernel time (measured: configs/seed004-siemens.toml with 64 substeps, a 20 s sine,
#: 2.4 s wall for 2.05e7 steps; 0.26 us at 16 substeps), so 1e7 steps per simulated second are 1-2 s of
#: wall time per simulated second: the slowest rate at which a study of minutes of motion still finishes. The
#: stiffest contact mode of a feed axis (nut contact 1e9 N/m on a 2 kg nut: 3.6 kHz; a bearing on a screw end
#: ~10 kHz) is resolved over 1000 times at this rate, so a finer step buys no accuracy.
MAX_MECHANICAL_STEP_RATE_HZ = 1e7
#: Memory of the discretised mode tables per nut-position grid point [bytes]: 4 contact/stick modes x
#: (s x s + s x 4) float64 with s = 12 states for the six-body model: 6 KiB (measured), ~10 KiB with extra modes.
GRID_POINT_BYTES = 4 * (16 * 16 + 16 * 4) * 8 + 2 * 2 * 8 * 8
#: Largest nut-position grid. Building a grid point takes four matrix exponentials: measured 5.9 ms per point
#: (2001 points of configs/seed004-siemens.toml in 11.8 s on the shared 2-vCPU machine), so 2001 points are
#: ~12 s of start-up and ~12 MiB of tables; the grid step, stroke/2000 (0.4 mm on a 0.8 m stroke), is far
#: below the length over which the screw's axial stiffness changes (the nut length, centimetres).
MAX_POSITION_GRID_POINTS = 2001
#: Switching-level SVPWM: integration steps per switching segment (six segments per PWM period); beyond 256 the
#: current ripple no longer changes (the segment is resolved to < 0.4 %) and the cost grows linearly.
MAX_SVPWM_SUBSTEPS = 256

#: ``section.key`` -> (lowest, highest) allowed value, both inclusive, in the key's SI unit.
#:
#: A key that must be physically positive (a lead, a stiffness, a gain, a limit, a quantum) has a positive lower
#: bound a few decades below the softest / smallest catalogue value, so that an exponent typo (``1e-9`` for
#: ``1e9``) or a unit slip is refused instead of giving a table that never moves or a run that diverges; ``0``
#: is then allowed only where :data:`ZERO_MEANS` gives it a documented meaning. Keys whose value may approach 0
#: continuously (damping, friction, noise, offsets, error amplitudes, delays that tend to "none") keep 0 as
#: their lower bound: a tiny value there is a tiny effect, not a broken axis. Seeds referred to: configs/
#: seed000-hust.toml, seed002-usst.toml, seed004-siemens.toml, spindle.toml and configs/examples/.
BOUNDS: dict[str, tuple[float, float]] = {
    # [axis]: strokes from a 0.1 mm micro stage to a 100 m gantry
    "axis.stroke_m": (1e-4, 100.0),
    "axis.nut_offset_m": (0.0, 100.0),  # a position on the screw: 0 is a real value
    # [mechanics]
    # leads: 0.1 mm (fine-pitch micro-stage screws) .. 0.5 m/rev (a rack pinion of 150 mm pitch diameter as a
    # lead); seeds 1 .. 40 mm
    "mechanics.lead_m": (1e-4, 0.5),
    "mechanics.motor_inertia_kg_m2": (1e-7, 100.0),  # 1e-7 (small servo) .. 10 kg m^2 (torque motor)
    "mechanics.coupling_inertia_kg_m2": (1e-8, 10.0),  # miniature bellows coupling .. large disc coupling
    "mechanics.screw_end_inertia_kg_m2": (1e-8, 10.0),  # seeds 5e-5 .. 1e-4
    # torsional springs: miniature bellows couplings ~1e2 N m/rad .. large shafts; seeds 5.5e3 .. 2e5
    "mechanics.coupling_stiffness_nm_per_rad": (10.0, 1e8),
    "mechanics.motor_shaft_stiffness_nm_per_rad": (100.0, 1e9),
    "mechanics.screw_end_stiffness_nm_per_rad": (100.0, 1e9),
    "mechanics.screw_length_m": (1e-3, 100.0),
    "mechanics.screw_root_diameter_m": (1e-3, 0.5),  # miniature screws (3 mm root) .. 200 mm heavy screws
    "mechanics.screw_density_kg_m3": (500.0, 25000.0),  # light alloys/composites .. tungsten
    "mechanics.youngs_modulus_pa": (1e9, 1.2e12),  # engineering plastics .. diamond
    "mechanics.shear_modulus_pa": (3e8, 6e11),
    # axial springs: catalogue bearings, nuts and supports 1e7 .. 1e10 N/m (seeds 7.2e7 .. 2e9); the lower bound
    # is two decades below the softest miniature part
    "mechanics.bearing_axial_stiffness_n_per_m": (1e5, 1e11),
    "mechanics.support_axial_stiffness_n_per_m": (1e5, 1e12),
    "mechanics.nut_contact_stiffness_n_per_m": (1e5, 1e11),
    "mechanics.nut_mass_kg": (1e-3, 1e3),  # a gram-scale miniature nut .. a 1 t heavy-duty nut; seeds 0.25 .. 2.5
    "mechanics.flange_stiffness_n_per_m": (1e5, 1e12),
    "mechanics.table_mass_kg": (1e-3, 1e6),  # a gram-scale slider .. a 1000 t machine bed
    "mechanics.equivalent_torsional_stiffness_nm_per_rad": (10.0, 1e9),  # as the coupling and shaft springs
    "mechanics.min_segment_m": (1e-4, 10.0),
    "mechanics.modal_damping_ratio": (0.0, 1.0),
    "mechanics.motor_viscous_nm_s_per_rad": (0.0, 1e3),
    "mechanics.table_viscous_n_s_per_m": (0.0, 1e7),
    "mechanics.efficiency": (0.01, 1.0),
    # [backlash]
    "backlash.gap_m": (0.0, 0.01),  # 10 mm of backlash is a broken axis, not a parameter
    # [friction]
    "friction.coulomb_n": (0.0, 1e6),
    "friction.coulomb_negative_n": (-1.0, 1e6),  # < 0 means "same as coulomb_n"
    "friction.stribeck_n": (0.0, 1e6),
    "friction.stribeck_velocity_m_s": (1e-7, 10.0),
    "friction.stribeck_exponent": (0.1, 10.0),
    "friction.viscous_n_s_per_m": (0.0, 1e7),
    "friction.viscous_negative_n_s_per_m": (-1.0, 1e7),  # < 0 means "same as viscous_n_s_per_m"
    # [actuator]
    "actuator.force_limit_n": (0.1, 1e7),  # a voice coil's newton .. a gantry's linear motors; seed 3000 N
    "actuator.force_lag_s": (1e-6, 1.0),  # below 1 us is below any current cycle: give 0 (none)
    # [motor]: catalogue servo and torque motors
    "motor.pole_pairs": (1, 128),
    "motor.rs_ohm": (1e-4, 1e3),
    "motor.ld_h": (1e-7, 10.0),
    "motor.lq_h": (1e-7, 10.0),
    "motor.flux_wb": (1e-4, 10.0),  # k_t = 1.5 p psi: seeds 0.09 .. 0.28 Wb; torque motors a few Wb
    "motor.torque_constant_nm_per_a": (1e-3, 1e3),  # micro servos 0.01 N m/A .. torque motors; seeds 0.55 .. 1.65
    "motor.rated_current_a": (1e-2, 1e4),
    "motor.rated_torque_nm": (1e-3, 1e5),
    "motor.rated_speed_rpm": (1.0, 1e5),
    "motor.cogging_amplitude_nm": (0.0, 1e4),
    "motor.cogging_periods_per_rev": (0.0, 1e4),
    "motor.cogging_phase_rad": (-1e3, 1e3),
    # [inverter]
    "inverter.dc_link_v": (1.0, 5000.0),
    "inverter.svpwm_substeps": (1, MAX_SVPWM_SUBSTEPS),
    # [control]: cycles of real drives are 31.25 us .. a few ms; gains from about four decades below the seeds'
    # (a 50 W servo) to beyond any stable loop
    "control.current_cycle_s": (1e-6, 0.01),
    "control.speed_cycle_s": (1e-6, 0.1),
    "control.position_cycle_s": (1e-5, 1.0),
    "control.current_kp_v_per_a": (1e-3, 1e5),  # Kp = L x bandwidth: 1e-5 H x 2 pi 1 kHz = 0.06; seeds 8 .. 28.5
    "control.current_ti_s": (1e-5, 100.0),  # Ti = L / R: 0.3 .. 50 ms; below 10 us the integrator diverges
    "control.speed_kp_nm_s_per_rad": (1e-4, 1e5),  # Kp = J x bandwidth: 2e-6 kg m^2 x 2 pi 200 Hz = 2.5e-3
    "control.velocity_kp_n_s_per_m": (0.1, 1e9),  # m x bandwidth: 0.01 kg x 2 pi 10 Hz .. ; seed 8000
    "control.speed_ti_s": (1e-5, 100.0),  # seeds 10 .. 40 ms
    # Kv: 0.1 1/s (a 10 s position time constant) .. 1e4 1/s (far beyond any stable loop); seeds 30 .. 120 1/s
    "control.kv_1000_per_min": (0.006, 600.0),
    "control.kv_per_min": (6.0, 6e5),
    "control.kv_per_s": (0.1, 1e4),
    "control.velocity_ff_factor": (0.0, 2.0),
    "control.torque_ff_factor": (0.0, 2.0),
    "control.current_limit_a": (1e-2, 1e5),  # seeds 15 .. 50 A
    "control.speed_limit_rpm": (1.0, 1e5),  # seeds 3000 .. 7000 1/min
    "control.speed_filter_time_constant_s": (0.0, 1.0),  # 0 (none) .. 1 s (far beyond any usable speed loop)
    "control.output_delay_s": (0.0, 0.2),  # 0 .. two of the slowest speed cycles
    # [sensors]
    "sensors.motor_encoder_counts_per_rev": (16, 1 << 40),  # a 4-line incremental encoder .. 40 bits; seeds 2^17..2^22
    "sensors.linear_scale_resolution_m": (1e-12, 0.01),  # interferometers 1 pm .. 10 mm magnetic tape; seeds 10..100 nm
    "sensors.dead_time_s": (0.0, 1.0),
    "sensors.position_noise_m": (0.0, 0.01),
    "sensors.current_noise_a": (0.0, 1e3),
    # [effects]
    "effects.lead_error_ppm": (-1e4, 1e4),
    "effects.lead_error_periodic_m": (0.0, 1e-3),
    "effects.lead_error_periodic_phase_rad": (-1e3, 1e3),
    "effects.thermal_expansion_per_k": (0.0, 1e-3),
    "effects.thermal_resistance_k_per_w": (0.0, 1e3),
    "effects.thermal_time_constant_s": (1e-3, 1e7),
    "effects.initial_temperature_rise_k": (-200.0, 500.0),
    "effects.resonance_frequency_hz": (0.1, 1e5),  # a fixture or column mode: a few Hz .. kHz
    "effects.resonance_mass_kg": (1e-3, 1e6),  # as mechanics.table_mass_kg
    "effects.resonance_damping_ratio": (0.0, 1.0),
    "effects.force_offset_n": (-1e7, 1e7),
    "effects.brake_holding_force_n": (0.0, 1e7),
    "effects.brake_opening_time_s": (0.0, 10.0),
    "effects.brake_closing_time_s": (0.0, 10.0),
    # [limits]: 1e9 m is the schema's "no limit"
    "limits.max_velocity_m_s": (1e-6, 100.0),
    "limits.max_acceleration_m_s2": (1e-6, 1e5),
    "limits.travel_min_m": (-1e9, 1e9),
    "limits.travel_max_m": (-1e9, 1e9),
    # [simulation]
    "simulation.mechanical_substeps": (1, 100_000),  # refined by the step-rate bound in the consistency check
    "simulation.position_grid_points": (1, MAX_POSITION_GRID_POINTS),
    "simulation.seed": (0, 2**63 - 1),  # numpy's generators take non-negative seeds
}

#: Keys whose positive range (above) does not include 0 but for which 0 is a documented setting: the meaning
#: of that 0. Every other key outside its range, 0 included, is refused.
ZERO_MEANS: dict[str, str] = {
    "mechanics.lead_m": "direct drive, no screw (rigid or force axis)",
    "mechanics.motor_inertia_kg_m2": "no rotor (force actuator)",
    "mechanics.coupling_inertia_kg_m2": "none",
    "mechanics.screw_end_inertia_kg_m2": "none",
    "mechanics.coupling_stiffness_nm_per_rad": "not used (two_mass or rigid model)",
    "mechanics.motor_shaft_stiffness_nm_per_rad": "rigid",
    "mechanics.screw_end_stiffness_nm_per_rad": "rigid",
    "mechanics.screw_length_m": "no screw (two_mass or rigid model)",
    "mechanics.screw_root_diameter_m": "no screw (two_mass or rigid model)",
    "mechanics.bearing_axial_stiffness_n_per_m": "not used (two_mass or rigid model)",
    "mechanics.support_axial_stiffness_n_per_m": "rigid",
    "mechanics.nut_contact_stiffness_n_per_m": "not used (two_mass or rigid model)",
    "mechanics.nut_mass_kg": "not used (two_mass or rigid model)",
    "mechanics.flange_stiffness_n_per_m": "rigid",
    "mechanics.equivalent_torsional_stiffness_nm_per_rad": "not used (ball_screw or rigid model)",
    "actuator.force_limit_n": "no limit",
    "actuator.force_lag_s": "none",
    "motor.flux_wb": "derived from torque_constant_nm_per_a",
    "motor.torque_constant_nm_per_a": "derived from flux_wb",
    "motor.rated_torque_nm": "torque_constant x rated_current",
    "control.current_kp_v_per_a": "not used (force actuator)",
    "control.current_ti_s": "P only",
    "control.speed_kp_nm_s_per_rad": "not used (force actuator)",
    "control.velocity_kp_n_s_per_m": "not used (pmsm actuator)",
    "control.speed_ti_s": "P only",
    "control.kv_1000_per_min": "Kv given in another unit",
    "control.kv_per_min": "Kv given in another unit",
    "control.kv_per_s": "Kv given in another unit",
    "control.current_limit_a": "3 x motor.rated_current_a",
    "control.speed_limit_rpm": "none",
    "sensors.motor_encoder_counts_per_rev": "ideal (unquantised)",
    "sensors.linear_scale_resolution_m": "ideal (unquantised)",
    "effects.resonance_frequency_hz": "none",
    "effects.resonance_mass_kg": "none",
}


def in_bounds(key: str, value: float) -> bool:
    """``value`` is inside ``key``'s range, or 0 where :data:`ZERO_MEANS` gives 0 a meaning (unbounded keys:
    True)."""
    lo_hi = BOUNDS.get(key)
    if lo_hi is None:
        return True
    return lo_hi[0] <= value <= lo_hi[1] or (value == 0 and key in ZERO_MEANS)


def _norm(unit: str) -> str:
    """Canonical spelling: no blanks, '·'/'*' dropped, 'µ'/'μ' as 'u', '^' dropped (``kg m^2`` -> ``kgm2``)."""
    u = unit.strip().replace("µ", "u").replace("μ", "u")
    for ch in (" ", "·", "*", "^", "⋅"):
        u = u.replace(ch, "")
    return u.replace("²", "2").replace("³", "3")


_PI = math.pi
#: key-name suffix -> {unit spelling: factor to the key's SI unit}. The longest matching suffix wins.
UNIT_FACTORS: dict[str, dict[str, float]] = {
    "_m": {"m": 1.0, "mm": 1e-3, "um": 1e-6, "nm": 1e-9, "cm": 1e-2, "km": 1e3},
    "_kg": {"kg": 1.0, "g": 1e-3, "t": 1e3},
    "_s": {"s": 1.0, "ms": 1e-3, "us": 1e-6, "ns": 1e-9, "min": 60.0},
    "_hz": {"Hz": 1.0, "kHz": 1e3, "1/s": 1.0},
    "_rpm": {"rpm": 1.0, "1/min": 1.0, "rev/min": 1.0, "min-1": 1.0, "rev/s": 60.0, "1/s": 60.0},
    "_1000_per_min": {"1000/min": 1.0, "(m/min)/mm": 1.0, "m/min/mm": 1.0, "1/min": 1e-3, "1/s": 0.06},
    "_per_min": {"1/min": 1.0, "min-1": 1.0, "1/s": 60.0},
    "_per_s": {"1/s": 1.0, "s-1": 1.0, "1/min": 1 / 60.0},
    "_kg_m2": {"kgm2": 1.0, "kgcm2": 1e-4, "gcm2": 1e-7},
    "_kg_m3": {"kg/m3": 1.0, "g/cm3": 1e3},
    "_nm_per_rad": {"Nm/rad": 1.0, "Nm/deg": 180.0 / _PI, "kNm/rad": 1e3},
    "_nm_s_per_rad": {"Nms/rad": 1.0},
    "_n_per_m": {"N/m": 1.0, "N/mm": 1e3, "N/um": 1e6, "kN/mm": 1e6, "kN/um": 1e9},
    "_n_s_per_m": {"Ns/m": 1.0, "Ns/mm": 1e3},
    "_nm_per_a": {"Nm/A": 1.0},
    "_v_per_a": {"V/A": 1.0, "ohm": 1.0},
    "_nm": {"Nm": 1.0, "mNm": 1e-3, "kNm": 1e3},
    "_n": {"N": 1.0, "kN": 1e3},
    "_pa": {"Pa": 1.0, "MPa": 1e6, "GPa": 1e9, "N/mm2": 1e6, "N/m2": 1.0},
    "_ohm": {"ohm": 1.0, "Ω": 1.0, "mohm": 1e-3, "mΩ": 1e-3},
    "_h": {"H": 1.0, "mH": 1e-3, "uH": 1e-6},
    "_a": {"A": 1.0, "mA": 1e-3},
    "_v": {"V": 1.0, "kV": 1e3},
    "_wb": {"Wb": 1.0, "Vs": 1.0, "mWb": 1e-3},
    "_rad": {"rad": 1.0, "deg": _PI / 180.0, "°": _PI / 180.0},
    "_m_s": {"m/s": 1.0, "mm/s": 1e-3, "m/min": 1 / 60.0, "mm/min": 1 / 60000.0},
    "_m_s2": {"m/s2": 1.0, "mm/s2": 1e-3, "g": 9.80665},
    "_k": {"K": 1.0},
    "_per_k": {"1/K": 1.0, "ppm/K": 1e-6, "um/(mK)": 1e-6, "um/m/K": 1e-6},
    "_k_per_w": {"K/W": 1.0},
    "_ppm": {"ppm": 1.0, "um/m": 1.0},
    "_per_rev": {"1/rev": 1.0},
}
#: dimensionless keys (ratios, counts): only these unit spellings are accepted
DIMENSIONLESS = {"1": 1.0, "-": 1.0, "": 1.0}
_UNIT_TABLES = {suffix: {_norm(k): v for k, v in table.items()} for suffix, table in UNIT_FACTORS.items()}
_SUFFIXES = sorted(UNIT_FACTORS, key=len, reverse=True)


def units_for_key(key: str) -> dict[str, float]:
    """The unit spellings accepted for ``key`` (its name's suffix), with their factors to the SI unit."""
    name = key.rsplit(".", 1)[-1]
    for suffix in _SUFFIXES:
        if name.endswith(suffix):
            return UNIT_FACTORS[suffix]
    return DIMENSIONLESS


def convert_unit(key: str, value: float, unit: str) -> float:
    """``value`` in ``unit`` converted to the unit of ``key``'s name. Raises ``ValueError`` (with the accepted
    units) for a unit of another quantity."""
    table = units_for_key(key)
    norm_table = {_norm(k): v for k, v in table.items()}
    factor = norm_table.get(_norm(unit))
    if factor is None:
        raise ValueError(f"unit {unit!r} does not fit this key; accepted: {', '.join(repr(u) for u in table)}")
    return value * factor


def format_bound(v: float) -> str:
    return f"{v:g}" if isinstance(v, float) else str(v)
