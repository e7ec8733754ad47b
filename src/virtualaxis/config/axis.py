"""The axis configuration schema and its loader.

A config file is TOML. Every physical parameter carries its unit in its key name (``lead_m``,
``rs_ohm``, ``kv_1000_per_min``) and may carry its source::

    [mechanics]
    lead_m = { value = 0.016, source = "seed 000 Table 2" }
    table_mass_kg = 300.0            # a bare number is accepted; its source is then "unspecified"

A value may carry another unit of the same quantity, ``lead_m = { value = 16, unit = "mm" }``: it is converted
to the key's unit (table in :mod:`virtualaxis.config.bounds`); a unit of another quantity is refused.

Loading validates every key: unknown keys, missing required keys, wrong types, non-finite numbers (nan, inf),
values outside the plausibility bounds of :mod:`virtualaxis.config.bounds`, files that are not UTF-8 and
duplicate keys raise :class:`~virtualaxis.config.ConfigError` naming the file and ``section.key`` (or line).

Sections (each a dataclass below, fields documented with unit and meaning):
``axis``, ``mechanics``, ``backlash``, ``friction``, ``actuator``, ``motor``, ``inverter``, ``control``,
``sensors``, ``effects``, ``limits``, ``simulation``. Sections owned by other packages (``rcsa``,
``drive``, ``canopen``, ``modbus``, ``mqtt``, ``diagnosis``) are kept verbatim in
:attr:`AxisConfig.extra` for their owners to validate.
"""

from __future__ import annotations

import dataclasses
import math
import sys
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

from virtualaxis.config.bounds import (
    BOUNDS,
    DIMENSIONLESS,
    MAX_MECHANICAL_STEP_RATE_HZ,
    ZERO_MEANS,
    convert_unit,
    format_bound,
    in_bounds,
    units_for_key,
)
from virtualaxis.config.errors import ConfigError
from virtualaxis.config.tomlfile import TomlError, parse_toml

#: a config file larger than this is not a config (``/dev/zero``, a trace given as --config) [bytes]
MAX_CONFIG_BYTES = 4 << 20

# Sections that belong to other packages; kept verbatim, validated by their owners.
EXTENSION_SECTIONS = ("rcsa", "drive", "canopen", "modbus", "mqtt", "diagnosis", "metadata")


def _p(default: Any = dataclasses.MISSING, *, check: str = "", doc: str = "", choices: tuple = ()):
    """A schema field. ``check``: '' | '>0' | '>=0' | '0..1' ; ``choices`` for strings."""
    meta = {"check": check, "doc": doc, "choices": choices}
    if default is dataclasses.MISSING:
        return field(metadata=meta)
    return field(default=default, metadata=meta)


@dataclass(frozen=True, kw_only=True)
class AxisInfo:
    """[axis] identity and geometry of the travel."""

    name: str = _p("axis", doc="free name")
    stroke_m: float = _p(check=">0", doc="usable table travel [m]")
    nut_offset_m: float = _p(
        check=">=0",
        doc="distance from the fixed (motor-side) bearing to the nut at table position 0, which is the"
        " middle of the stroke [m]",
    )


@dataclass(frozen=True, kw_only=True)
class MechanicsParams:
    """[mechanics] lumped bodies and springs (seed 004 six-body model, seed 000 stiffness formulas).

    ``model``: ``ball_screw`` (six bodies: rotor, screw end, screw rotation, screw axial, nut, table),
    ``two_mass`` (rotor + table through one equivalent spring) or ``rigid`` (one body).
    """

    model: str = _p("ball_screw", choices=("ball_screw", "two_mass", "rigid"))
    lead_m: float = _p(0.0, check=">=0", doc="screw lead [m/rev]; 0 only for a direct (linear) drive")
    motor_inertia_kg_m2: float = _p(0.0, check=">=0", doc="rotor inertia [kg m^2]")
    coupling_inertia_kg_m2: float = _p(0.0, check=">=0", doc="coupling inertia, split half/half [kg m^2]")
    screw_end_inertia_kg_m2: float = _p(0.0, check=">=0", doc="screw end (journal) inertia [kg m^2]")
    coupling_stiffness_nm_per_rad: float = _p(0.0, check=">=0", doc="coupling torsion K_tc [N m/rad]")
    motor_shaft_stiffness_nm_per_rad: float = _p(
        0.0, check=">=0", doc="motor shaft torsion, in series with the coupling; 0 = rigid [N m/rad]"
    )
    screw_end_stiffness_nm_per_rad: float = _p(
        0.0, check=">=0", doc="screw end torsion, in series with screw torsion; 0 = rigid [N m/rad]"
    )
    screw_length_m: float = _p(0.0, check=">=0", doc="distance between the support bearings L_sg [m]")
    screw_root_diameter_m: float = _p(0.0, check=">=0", doc="screw root diameter for A_s, I_p [m]")
    screw_density_kg_m3: float = _p(7850.0, check=">0", doc="steel [kg/m^3]")
    youngs_modulus_pa: float = _p(2.06e11, check=">0", doc="steel [Pa]")
    shear_modulus_pa: float = _p(7.9e10, check=">0", doc="steel [Pa]")
    screw_mounting: str = _p(
        "fixed_fixed",
        choices=("fixed_fixed", "fixed_free"),
        doc="axial mounting: fixed_fixed -> K_as = E A L / (x (L - x)); fixed_free -> E A / x",
    )
    bearing_axial_stiffness_n_per_m: float = _p(
        0.0, check=">=0", doc="K_ab1 + K_ab2 of the support bearings [N/m]"
    )
    support_axial_stiffness_n_per_m: float = _p(
        0.0, check=">=0", doc="metal support of the axis, 0 = rigid [N/m]"
    )
    nut_contact_stiffness_n_per_m: float = _p(0.0, check=">=0", doc="nut contact stiffness K_an [N/m]")
    nut_mass_kg: float = _p(0.0, check=">=0", doc="ball nut mass [kg]")
    flange_stiffness_n_per_m: float = _p(0.0, check=">=0", doc="nut flange to table [N/m]; 0 = rigid")
    table_mass_kg: float = _p(check=">0", doc="table (slide) moving mass incl. workpiece [kg]")
    equivalent_torsional_stiffness_nm_per_rad: float = _p(
        0.0, check=">=0", doc="two_mass model only: rotor-to-table spring, seen at the motor [N m/rad]"
    )
    min_segment_m: float = _p(0.02, check=">0", doc="screw segment length floor keeping K_as finite [m]")
    modal_damping_ratio: float = _p(
        0.03, check="0..1", doc="structural damping: C = b K with b = 2 zeta / omega_1 (seed 004 eq. 19-21)"
    )
    motor_viscous_nm_s_per_rad: float = _p(0.0, check=">=0", doc="motor bearing viscous damping B_m")
    table_viscous_n_s_per_m: float = _p(0.0, check=">=0", doc="linear guide viscous damping [N s/m]")
    efficiency: float = _p(1.0, check="0..1", doc="screw efficiency eta (used in the seed 000 K_L)")


@dataclass(frozen=True, kw_only=True)
class BacklashParams:
    """[backlash] dead-zone spring at the nut contact (seed 000 eq. 9)."""

    enabled: bool = _p(False)
    gap_m: float = _p(0.0, check=">=0", doc="total backlash b, measured at the table [m]")


@dataclass(frozen=True, kw_only=True)
class FrictionParams:
    """[friction] at the table/nut (seed 000 eq. 13) with a stick/slip switch that neither chatters nor creeps.

    Sliding force: (F_c,dir + F_s exp(-(|v|/v_s)^delta)) sgn(v) + F_v,dir v; break-away at F_c,dir + F_s.
    ``dir`` is the direction of motion: the Coulomb and viscous coefficients may differ between +v and -v
    (seals, a preloaded guide, a cable chain that drags one way).
    """

    enabled: bool = _p(False)
    coulomb_n: float = _p(0.0, check=">=0", doc="Coulomb force F_c for +v (mu (M g + F_z)) [N]")
    coulomb_negative_n: float = _p(-1.0, doc="Coulomb force for -v [N]; < 0 means 'same as coulomb_n'")
    stribeck_n: float = _p(0.0, check=">=0", doc="Stribeck excess F_s over Coulomb at v = 0 [N]")
    stribeck_velocity_m_s: float = _p(0.001, check=">0", doc="Stribeck velocity v_s [m/s]")
    stribeck_exponent: float = _p(1.0, check=">0", doc="shape delta (1 in seed 000 eq. 13)")
    viscous_n_s_per_m: float = _p(0.0, check=">=0", doc="viscous coefficient F_v for +v [N s/m]")
    viscous_negative_n_s_per_m: float = _p(
        -1.0, doc="viscous coefficient F_v for -v [N s/m]; < 0 means 'same as viscous_n_s_per_m' (default)"
    )


@dataclass(frozen=True, kw_only=True)
class ActuatorParams:
    """[actuator] what produces the drive effort: a PMSM (torque, rotary) or a force (linear, or
    an external controller's force output)."""

    kind: str = _p("pmsm", choices=("pmsm", "force"))
    force_limit_n: float = _p(0.0, check=">=0", doc="force actuator only: |F| limit, 0 = none [N]")
    force_lag_s: float = _p(0.0, check=">=0", doc="force actuator only: first-order force-loop lag [s]")


@dataclass(frozen=True, kw_only=True)
class MotorParams:
    """[motor] PMSM in the dq frame (seed 000 eqs. 15-19) and cogging."""

    pole_pairs: int = _p(4, check=">0")
    rs_ohm: float = _p(1.0, check=">0", doc="phase resistance R_s [ohm]")
    ld_h: float = _p(1e-3, check=">0", doc="d-axis inductance [H]")
    lq_h: float = _p(1e-3, check=">0", doc="q-axis inductance [H]")
    flux_wb: float = _p(0.0, check=">=0", doc="PM flux linkage psi_pm [Wb] (0: derived from torque constant)")
    torque_constant_nm_per_a: float = _p(0.0, check=">=0", doc="k_t = 1.5 p psi_pm [N m/A]")
    rated_current_a: float = _p(10.0, check=">0", doc="rated (nominal) current [A]")
    rated_torque_nm: float = _p(0.0, check=">=0", doc="nominal torque [N m] (catalogue)")
    rated_speed_rpm: float = _p(3000.0, check=">0", doc="nominal speed [1/min]")
    cogging_amplitude_nm: float = _p(0.0, check=">=0", doc="cogging/ripple torque amplitude [N m]")
    cogging_periods_per_rev: float = _p(0.0, check=">=0", doc="ripple periods per mechanical rev")
    cogging_phase_rad: float = _p(0.0, doc="ripple phase [rad]")

    @property
    def psi_wb(self) -> float:
        """PM flux linkage [Wb]: ``flux_wb``, or derived from the torque constant (k_t = 1.5 p psi_pm)."""
        return self.flux_wb if self.flux_wb > 0 else self.torque_constant_nm_per_a / (1.5 * self.pole_pairs)

    @property
    def kt_nm_per_a(self) -> float:
        """Torque constant k_t = 1.5 p psi_pm [N m/A] (q-axis current to torque)."""
        return 1.5 * self.pole_pairs * self.psi_wb


@dataclass(frozen=True, kw_only=True)
class InverterParams:
    """[inverter] averaged (voltage clamp, one PWM period delay) or switching-level SVPWM."""

    model: str = _p("averaged", choices=("averaged", "svpwm"))
    dc_link_v: float = _p(560.0, check=">0", doc="DC-link voltage [V]")
    svpwm_substeps: int = _p(16, check=">0", doc="svpwm: integration steps per switching segment")


@dataclass(frozen=True, kw_only=True)
class ControlParams:
    """[control] Siemens-style cascade: P position loop (Kv), PI speed loop, PI current loops.

    Kv may be given in exactly one of ``kv_1000_per_min`` (SINUMERIK MD32200, (m/min)/mm),
    ``kv_per_min`` (seed 004) or ``kv_per_s``. For ``actuator.kind = "force"`` the speed loop output is a
    force and its gain is ``velocity_kp_n_s_per_m``.
    """

    current_cycle_s: float = _p(62.5e-6, check=">0", doc="current-loop cycle [s]")
    speed_cycle_s: float = _p(125e-6, check=">0", doc="speed-loop cycle [s]")
    position_cycle_s: float = _p(1e-3, check=">0", doc="position-loop cycle [s]")
    current_kp_v_per_a: float = _p(0.0, check=">=0", doc="current PI gain [V/A]")
    current_ti_s: float = _p(0.0, check=">=0", doc="current PI integral time, 0 = P only [s]")
    current_decoupling: bool = _p(True, doc="dq cross-coupling and back-EMF feed-forward")
    speed_kp_nm_s_per_rad: float = _p(0.0, check=">=0", doc="speed PI gain (pmsm) [N m s/rad]")
    velocity_kp_n_s_per_m: float = _p(0.0, check=">=0", doc="velocity PI gain (force actuator) [N s/m]")
    speed_ti_s: float = _p(0.0, check=">=0", doc="speed PI integral time, 0 = P only [s]")
    kv_1000_per_min: float = _p(0.0, check=">=0", doc="position gain Kv [1000/min]")
    kv_per_min: float = _p(0.0, check=">=0", doc="position gain Kv [1/min] (seed 004)")
    kv_per_s: float = _p(0.0, check=">=0", doc="position gain Kv [1/s]")
    velocity_ff_factor: float = _p(0.0, check=">=0", doc="speed feed-forward weight (MD32610), 0..1")
    torque_ff_factor: float = _p(0.0, check=">=0", doc="torque feed-forward weight, 0..1")
    velocity_ff_form: str = _p("derivative", choices=("derivative", "setpoint_difference"),
                               doc="how the speed feed-forward is derived from the position set-points: "
                               "derivative (the command's derivative at t_k) or setpoint_difference (a CSP "
                               "drive: (x_k - x_k-1) / position cycle, held for the cycle)")
    current_limit_a: float = _p(0.0, check=">=0", doc="|i_q| limit [A] (pmsm); 0 -> 3 x rated")
    speed_limit_rpm: float = _p(0.0, check=">=0", doc="motor speed set-point limit [1/min]; 0 = none")
    position_feedback: str = _p("motor_encoder", choices=("motor_encoder", "linear_scale"))
    speed_estimator: str = _p(
        "backward_difference", choices=("backward_difference", "two_sample_difference"),
        doc="speed the speed loop closes on, from the quantised position q sampled every speed cycle T: "
        "backward_difference w[k] = (q[k] - q[k-1]) / T; two_sample_difference w[k] = (q[k] - q[k-2]) / (2 T)",
    )
    speed_filter_time_constant_s: float = _p(
        0.0, check=">=0", doc="first-order low-pass on that speed estimate, w_f[k] = w_f[k-1] + (1 - exp(-T/tau)) "
        "(w[k] - w_f[k-1]); 0 = none [s]",
    )
    output_delay_s: float = _p(
        0.0, check=">=0", doc="computation delay of the speed loop's output: the output computed from the samples "
        "taken at t_k is applied at t_k + output_delay_s; 0 = at once, speed_cycle_s = the common digital timing "
        "'sample at k, compute, apply at k+1'; a whole number of speed cycles, at most 2 [s]",
    )

    @property
    def kv_1_per_s(self) -> float:
        """Position-loop gain in 1/s, whichever unit the file used."""
        if self.kv_per_s:
            return self.kv_per_s
        if self.kv_1000_per_min:
            return self.kv_1000_per_min * 1000.0 / 60.0
        return self.kv_per_min / 60.0


@dataclass(frozen=True, kw_only=True)
class SensorParams:
    """[sensors] encoders, quantisation, measurement dead time and noise."""

    motor_encoder_counts_per_rev: int = _p(1 << 20, check=">=0", doc="0 = ideal")
    linear_scale_resolution_m: float = _p(0.0, check=">=0", doc="linear scale quantum, 0 = ideal [m]")
    dead_time_s: float = _p(0.0, check=">=0", doc="measurement dead time of position feedback [s]")
    dead_time_scope: str = _p(
        "position_loop", choices=("position_loop", "feedback_sensor"),
        doc="where dead_time_s acts: position_loop = only the position loop's feedback is delayed; "
        "feedback_sensor = the feedback sensor's reading is delayed wherever it is used (position loop, the speed "
        "loop when it differentiates that sensor, and its recorded channel: motor_pos for motor_encoder feedback, "
        "pos_meas for linear_scale feedback)",
    )
    position_noise_m: float = _p(0.0, check=">=0", doc="white noise on the linear scale (1 sigma) [m]")
    current_noise_a: float = _p(0.0, check=">=0", doc="white noise on measured i_q (1 sigma) [A]")


@dataclass(frozen=True, kw_only=True)
class EffectsParams:
    """[effects] further physical effects, all off (zero) by default."""

    lead_error_ppm: float = _p(0.0, doc="cumulative lead deviation [um/m = ppm]")
    lead_error_periodic_m: float = _p(0.0, check=">=0", doc="per-revolution lead error amplitude [m]")
    lead_error_periodic_phase_rad: float = _p(0.0, doc="its phase [rad]")
    thermal_expansion_per_k: float = _p(0.0, check=">=0", doc="screw alpha [1/K] (11.5e-6 for steel)")
    thermal_resistance_k_per_w: float = _p(0.0, check=">=0", doc="screw temperature rise per friction W")
    thermal_time_constant_s: float = _p(600.0, check=">0", doc="screw thermal time constant [s]")
    initial_temperature_rise_k: float = _p(0.0, doc="screw temperature above ambient at t = 0 [K]")
    resonance_frequency_hz: float = _p(0.0, check=">=0", doc="extra mode on the table, 0 = none [Hz]")
    resonance_mass_kg: float = _p(0.0, check=">=0", doc="modal mass of the extra mode [kg]")
    resonance_damping_ratio: float = _p(0.02, check="0..1", doc="damping of the extra mode")
    force_offset_n: float = _p(0.0, doc="constant load force on the table against +x (gravity on an inclined "
                                        "axis, cable drag): m a = F - F_friction - offset; subtracted from any "
                                        "external force [N]")
    brake_holding_force_n: float = _p(0.0, check=">=0", doc="holding brake on the table: the force it holds "
                                                            "engaged, slipping beyond it; 0 = no brake [N]")
    brake_opening_time_s: float = _p(0.0, check=">=0", doc="holding brake: time from the command to open "
                                                           "until it is released (data sheet) [s]")
    brake_closing_time_s: float = _p(0.0, check=">=0", doc="holding brake: time from the command to close "
                                                           "until it holds (data sheet) [s]")


@dataclass(frozen=True, kw_only=True)
class LimitsParams:
    """[limits] axis limits; profiles beyond them are rejected with a clear error."""

    max_velocity_m_s: float = _p(1.0, check=">0")
    max_acceleration_m_s2: float = _p(20.0, check=">0")
    travel_min_m: float = _p(-1e9, doc="software limit [m]")
    travel_max_m: float = _p(1e9, doc="software limit [m]")


@dataclass(frozen=True, kw_only=True)
class SimulationParams:
    """[simulation] numerical settings of the compiled kernel."""

    mechanical_substeps: int = _p(1, check=">0", doc="mechanics steps per current-loop cycle")
    position_grid_points: int = _p(41, check=">0", doc="nut positions at which mechanics are discretised")
    seed: int = _p(0, doc="random seed for sensor noise")


@dataclass(frozen=True, kw_only=True)
class AxisConfig:
    """A whole axis. ``sources`` maps ``section.key`` to the value's source text."""

    axis: AxisInfo
    mechanics: MechanicsParams
    backlash: BacklashParams
    friction: FrictionParams
    actuator: ActuatorParams
    motor: MotorParams
    inverter: InverterParams
    control: ControlParams
    sensors: SensorParams
    effects: EffectsParams
    limits: LimitsParams
    simulation: SimulationParams
    sources: dict = field(default_factory=dict, compare=False)
    extra: dict = field(default_factory=dict, compare=False)
    path: str = field(default="<dict>", compare=False)

    def replace(self, **changes: dict) -> AxisConfig:
        """A copy with some parameters changed: ``cfg.replace(backlash={"enabled": True, "gap_m": 5e-6})``.

        Values are validated as on load.
        """
        data = self.to_dict()
        for section, values in changes.items():
            if section not in data:
                raise ConfigError(self.path, section, "unknown section")
            data[section].update(values)
        return axis_config_from_dict(data, self.path, sources=self.sources)

    def to_dict(self) -> dict:
        out: dict = {}
        for name, _cls in _SECTIONS.items():
            out[name] = dataclasses.asdict(getattr(self, name))
        for k, v in self.extra.items():
            out[k] = v
        return out

    def to_toml(self, header: str = "") -> str:
        """Serialise with sources, so a written config is as traceable as a hand-written one."""
        lines = [f"# {h}" for h in header.splitlines()] if header else []
        for name in _SECTIONS:
            lines.append(f"\n[{name}]")
            for f in fields(_SECTIONS[name]):
                v = getattr(getattr(self, name), f.name)
                src = self.sources.get(f"{name}.{f.name}")
                lines.append(f"{f.name} = {_toml_value(v, src)}")
        for k, v in self.extra.items():
            lines.append(_toml_table(k, v))
        return "\n".join(lines) + "\n"


_SECTIONS: dict[str, type] = {
    "axis": AxisInfo,
    "mechanics": MechanicsParams,
    "backlash": BacklashParams,
    "friction": FrictionParams,
    "actuator": ActuatorParams,
    "motor": MotorParams,
    "inverter": InverterParams,
    "control": ControlParams,
    "sensors": SensorParams,
    "effects": EffectsParams,
    "limits": LimitsParams,
    "simulation": SimulationParams,
}
_REQUIRED_SECTIONS = ("axis", "mechanics", "control")


def _toml_scalar(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        return repr(v) if math.isfinite(v) else ("inf" if v > 0 else "-inf")
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_scalar(x) for x in v) + "]"
    raise TypeError(type(v))


def _toml_value(v: Any, source: str | None) -> str:
    if source and not isinstance(v, (bool, str)):
        return f"{{ value = {_toml_scalar(v)}, source = {_toml_scalar(source)} }}"
    return _toml_scalar(v)


def _toml_table(name: str, value: dict) -> str:
    scalars = {k: v for k, v in value.items() if not isinstance(v, dict)}
    tables = {k: v for k, v in value.items() if isinstance(v, dict)}
    lines = [f"\n[{name}]"]
    for k, v in scalars.items():
        lines.append(f"{k} = {_toml_scalar(v)}")
    for k, v in tables.items():
        if "value" in v and set(v) <= {"value", "source", "unit"}:
            inner = ", ".join(f"{kk} = {_toml_scalar(vv)}" for kk, vv in v.items())
            lines.append(f"{k} = {{ {inner} }}")
        else:
            lines.append(_toml_table(f"{name}.{k}", v))
    return "\n".join(lines)


def _coerce(file: str, key: str, raw: Any, f: dataclasses.Field, unit: str | None = None) -> Any:
    meta = f.metadata
    typ = f.type if isinstance(f.type, str) else f.type.__name__
    if unit is not None and typ in ("bool", "str"):
        raise ConfigError(file, key, f"takes no unit (got unit = {unit!r})")
    if typ == "bool":
        if not isinstance(raw, bool):
            raise ConfigError(file, key, f"must be true or false (got {raw!r})")
        return raw
    if typ == "str":
        if not isinstance(raw, str):
            raise ConfigError(file, key, f"must be a string (got {raw!r})")
        if meta["choices"] and raw not in meta["choices"]:
            raise ConfigError(file, key, f"must be one of {', '.join(meta['choices'])} (got {raw!r})")
        if not raw.strip():
            raise ConfigError(file, key, "must not be empty")
        return raw
    if isinstance(raw, bool) or not isinstance(raw, (int, float)):
        kind = "an integer" if typ == "int" else "a number"
        raise ConfigError(file, key, f"must be {kind} (got {raw!r})")
    if isinstance(raw, float) and not math.isfinite(raw):
        raise ConfigError(file, key, f"must be a finite number (got {raw!r})")
    if isinstance(raw, int) and not _int_fits_float(raw):  # 400 digits parse as a Python int
        raise ConfigError(file, key, f"must be a finite number (got an integer of {len(str(abs(raw)))} digits, "
                                     "beyond the range of a number)")
    if unit is not None:
        if not isinstance(unit, str):
            raise ConfigError(file, key, f"unit must be a string (got {unit!r})")
        try:
            raw = convert_unit(key, float(raw), unit)
        except ValueError as exc:
            raise ConfigError(file, key, str(exc)) from None
    if typ == "int":
        if isinstance(raw, float):
            if not raw.is_integer():
                raise ConfigError(file, key, f"must be an integer (got {raw!r})")
            raw = int(raw)
        val: Any = raw
    else:  # float
        val = float(raw)
        if not math.isfinite(val):
            raise ConfigError(file, key, f"must be a finite number (got {raw!r})")
    if isinstance(val, float) and val != 0 and abs(val) < sys.float_info.min:
        raise ConfigError(file, key, f"{val!r} is a subnormal number (below 2.2e-308 in magnitude): a typing error; "
                                     "give 0 or a real value")
    check = meta["check"]
    if check == ">0" and not val > 0:
        raise ConfigError(file, key, f"must be > 0 (got {val})")
    if check == ">=0" and not val >= 0:
        raise ConfigError(file, key, f"must be >= 0 (got {val})")
    if check == "0..1" and not 0 <= val <= 1:
        raise ConfigError(file, key, f"must be between 0 and 1 (got {val})")
    if not in_bounds(key, val):
        lo, hi = BOUNDS[key]
        zero = f" (or 0 = {ZERO_MEANS[key]})" if key in ZERO_MEANS else ""
        raise ConfigError(
            file, key, f"{val:g} is outside the plausible range {format_bound(lo)} .. {format_bound(hi)}"
            f" {_unit_name(key)}".rstrip() + zero
        )
    return val


def _unit_name(key: str) -> str:
    units = units_for_key(key)
    return next(iter(units)) if units is not DIMENSIONLESS else ""


def _section(file: str, name: str, cls: type, raw: Any, sources: dict) -> Any:
    if raw is None:
        raw = {}
    if not isinstance(raw, dict):
        raise ConfigError(file, name, "must be a table")
    known = {f.name: f for f in fields(cls)}
    for k in raw:
        if k not in known:
            hint = _closest(k, known)
            raise ConfigError(file, f"{name}.{k}", "unknown key" + (f" (did you mean {hint}?)" if hint else ""))
    kwargs = {}
    for fname, f in known.items():
        key = f"{name}.{fname}"
        if fname not in raw:
            if f.default is dataclasses.MISSING:
                raise ConfigError(file, key, "missing (required)")
            continue
        value = raw[fname]
        if isinstance(value, dict):
            extra_keys = set(value) - {"value", "source", "unit"}
            if "value" not in value or extra_keys:
                raise ConfigError(
                    file, key, "a table value needs 'value' and optionally 'source' and 'unit'"
                    + (f" (unknown: {', '.join(sorted(extra_keys))})" if extra_keys else "")
                )
            src = value.get("source")
            if src is not None and not isinstance(src, str):
                raise ConfigError(file, key, "source must be a string")
            if src:
                sources[key] = src
            unit = value.get("unit")
            value = value["value"]
        else:
            unit = None
        kwargs[fname] = _coerce(file, key, value, f, unit)
    return cls(**kwargs)


def _closest(name: str, known: dict) -> str | None:
    import difflib

    m = difflib.get_close_matches(name, list(known), n=1, cutoff=0.6)
    return m[0] if m else None


def axis_config_from_dict(data: dict, file: str = "<dict>", sources: dict | None = None) -> AxisConfig:
    """Validate a parsed config (the TOML as a dict) and build an :class:`AxisConfig`."""
    file = str(file)
    srcs: dict = dict(sources or {})
    for sec in data:
        if sec not in _SECTIONS and sec not in EXTENSION_SECTIONS:
            hint = _closest(sec, {**_SECTIONS, **dict.fromkeys(EXTENSION_SECTIONS)})
            raise ConfigError(file, sec, "unknown section" + (f" (did you mean [{hint}]?)" if hint else ""))
    for sec in _REQUIRED_SECTIONS:
        if sec not in data:
            raise ConfigError(file, sec, "missing section (required)")
    parts = {name: _section(file, name, cls, data.get(name), srcs) for name, cls in _SECTIONS.items()}
    extra = {k: v for k, v in data.items() if k in EXTENSION_SECTIONS}
    for k, v in extra.items():
        _refuse_non_finite(file, k, v)
    cfg = AxisConfig(**parts, sources=srcs, extra=extra, path=file)
    given = {f"{sec}.{k}" for sec, vals in data.items() if isinstance(vals, dict) for k in vals}
    _check_consistency(cfg, given)
    return cfg


#: Keys that describe the particular motor and drive: no default stands in for them when the axis is driven by
#: a pmsm (a default 4 pole pairs or 1 ohm would be a hidden wrong value); a force actuator does not use them.
#: Every other key with a default may be omitted: its default and where it comes from are listed in
#: docs/plant.md ("Defaults").
PMSM_REQUIRED = (
    "motor.pole_pairs", "motor.rs_ohm", "motor.ld_h", "motor.lq_h", "motor.rated_current_a",
    "motor.rated_speed_rpm", "control.current_ti_s", "control.speed_ti_s",
)
#: Required for every axis: the loop cycles set every time step of the drive.
#: the speed loop's output may be applied at most this many speed cycles after its samples
MAX_OUTPUT_DELAY_CYCLES = 2

ALWAYS_REQUIRED = ("control.current_cycle_s", "control.speed_cycle_s", "control.position_cycle_s")
_KV_KEYS = ("kv_1000_per_min", "kv_per_min", "kv_per_s")


def _refuse_non_finite(file: str, key: str, value: Any) -> None:
    """Sections owned by other packages are kept verbatim, but no number in a config may be nan, inf or an
    integer beyond TOML's 64 bits: refused here, naming the key, for every owner."""
    if isinstance(value, dict):
        for k, v in value.items():
            _refuse_non_finite(file, f"{key}.{k}", v)
    elif isinstance(value, list):
        for i, v in enumerate(value):
            _refuse_non_finite(file, f"{key}[{i}]", v)
    elif isinstance(value, float) and not math.isfinite(value):
        raise ConfigError(file, key, f"must be a finite number (got {value!r})")
    elif isinstance(value, int) and not isinstance(value, bool) and not _int_fits_float(value):
        raise ConfigError(file, key, f"must be a finite number (got an integer of {len(str(abs(value)))} digits, "
                                     "beyond the range of a number)")


def _int_fits_float(value: int) -> bool:
    try:
        float(value)
    except OverflowError:
        return False
    return True


def _positive_for(f: str, key: str, value: float, given: set, what: str) -> None:
    """``key`` must be > 0 for ``what``: 'missing' when the file does not give it, else the 0 named."""
    if value > 0:
        return
    if key not in given:
        raise ConfigError(f, key, f"missing (required for {what})")
    raise ConfigError(f, key, f"must be > 0 for {what} (got {value:g})")


def _check_consistency(cfg: AxisConfig, given: set | None = None) -> None:
    f = cfg.path
    m, c, a = cfg.mechanics, cfg.control, cfg.actuator
    if given is None:  # built from a complete dict: every key is given
        given = {f"{sec}.{fl.name}" for sec, cls in _SECTIONS.items() for fl in fields(cls)}
    for key in ALWAYS_REQUIRED + (PMSM_REQUIRED if a.kind == "pmsm" else ()):
        if key not in given:
            raise ConfigError(f, key, f"missing (required{' for a pmsm actuator' if key in PMSM_REQUIRED else ''}; "
                                      "no default stands in for the motor's or the drive's own value)")
    if m.model in ("ball_screw", "two_mass"):
        _positive_for(f, "mechanics.lead_m", m.lead_m, given, f"a {m.model} axis")
    if m.model == "ball_screw":
        for key in (
            "screw_length_m",
            "screw_root_diameter_m",
            "coupling_stiffness_nm_per_rad",
            "nut_contact_stiffness_n_per_m",
            "bearing_axial_stiffness_n_per_m",
            "motor_inertia_kg_m2",
            "nut_mass_kg",
        ):
            _positive_for(f, f"mechanics.{key}", getattr(m, key), given, "a ball_screw axis")
        half = cfg.axis.stroke_m / 2
        if cfg.axis.nut_offset_m - half < 0 or cfg.axis.nut_offset_m + half > m.screw_length_m:
            raise ConfigError(
                f, "axis.stroke_m", "nut_offset_m +- stroke_m/2 must lie inside 0..mechanics.screw_length_m"
            )
    if m.model == "two_mass":
        for key in ("equivalent_torsional_stiffness_nm_per_rad", "motor_inertia_kg_m2"):
            _positive_for(f, f"mechanics.{key}", getattr(m, key), given, "a two_mass axis")
    if a.kind == "pmsm":
        if m.model != "rigid":
            _positive_for(f, "mechanics.motor_inertia_kg_m2", m.motor_inertia_kg_m2, given, "a pmsm actuator")
        if m.model == "rigid":
            _positive_for(f, "mechanics.lead_m", m.lead_m, given, "a rigid axis driven by a pmsm")
        if not (cfg.motor.flux_wb > 0 or cfg.motor.torque_constant_nm_per_a > 0):
            gone = not ({"motor.flux_wb", "motor.torque_constant_nm_per_a"} & given)
            raise ConfigError(f, "motor.flux_wb", ("missing: " if gone else "") +
                              "give flux_wb or torque_constant_nm_per_a (> 0)")
        _positive_for(f, "control.speed_kp_nm_s_per_rad", c.speed_kp_nm_s_per_rad, given, "a pmsm actuator")
        _positive_for(f, "control.current_kp_v_per_a", c.current_kp_v_per_a, given, "a pmsm actuator")
    else:
        _positive_for(f, "control.velocity_kp_n_s_per_m", c.velocity_kp_n_s_per_m, given, "a force actuator")
    kvs = [k for k in _KV_KEYS if getattr(c, k) > 0]
    if len(kvs) > 1:
        got = ", ".join(f"{k} = {getattr(c, k):g}" for k in kvs)
        raise ConfigError(
            f, f"control.{kvs[0]}", f"give exactly one of kv_1000_per_min, kv_per_min, kv_per_s (got {got})"
        )
    if not kvs:
        zeros = [k for k in _KV_KEYS if f"control.{k}" in given]
        if not zeros:
            raise ConfigError(f, "control.kv_per_s", "missing (required): give the position-loop gain Kv as one of "
                                                     "kv_1000_per_min, kv_per_min, kv_per_s")
        lo, hi = BOUNDS[f"control.{zeros[0]}"]
        raise ConfigError(
            f, f"control.{zeros[0]}", f"must be > 0: a position-loop gain of 0 leaves the position loop open "
            f"(plausible range {format_bound(lo)} .. {format_bound(hi)} {_unit_name(f'control.{zeros[0]}')})",
        )
    # loop cycles must nest: current | speed | position, integer ratios
    for inner, outer in (("current_cycle_s", "speed_cycle_s"), ("speed_cycle_s", "position_cycle_s")):
        ti, to = getattr(c, inner), getattr(c, outer)
        ratio = to / ti
        if ratio < 1 - 1e-9 or abs(ratio - round(ratio)) > 1e-6:
            raise ConfigError(
                f, f"control.{outer}", f"must be an integer multiple of control.{inner} ({to} / {ti} = {ratio:g})"
            )
    cycles = c.output_delay_s / c.speed_cycle_s
    if abs(cycles - round(cycles)) > 1e-6 or round(cycles) > MAX_OUTPUT_DELAY_CYCLES:
        raise ConfigError(
            f, "control.output_delay_s", f"must be 0 .. {MAX_OUTPUT_DELAY_CYCLES} whole speed cycles "
            f"(control.speed_cycle_s = {c.speed_cycle_s:g} s; got {c.output_delay_s:g} s = {cycles:.4g} cycles)",
        )
    sim = cfg.simulation
    rate = sim.mechanical_substeps / c.current_cycle_s
    if rate > MAX_MECHANICAL_STEP_RATE_HZ:
        most = max(1, int(MAX_MECHANICAL_STEP_RATE_HZ * c.current_cycle_s))
        raise ConfigError(
            f, "simulation.mechanical_substeps",
            f"{sim.mechanical_substeps} substeps of the {c.current_cycle_s:g} s current cycle are {rate:.3g} "
            f"mechanical steps per simulated second; at most {MAX_MECHANICAL_STEP_RATE_HZ:.0e} (1..{most} here): "
            "finer steps add no accuracy and cost wall time linearly",
        )
    nyquist = 0.5 * rate
    if cfg.effects.resonance_frequency_hz > nyquist:
        raise ConfigError(
            f, "effects.resonance_frequency_hz",
            f"{cfg.effects.resonance_frequency_hz:g} Hz is above the Nyquist frequency {nyquist:g} Hz of the "
            "mechanical step (raise simulation.mechanical_substeps)",
        )
    if m.model == "ball_screw" and m.min_segment_m >= m.screw_length_m:
        raise ConfigError(f, "mechanics.min_segment_m", "must be smaller than mechanics.screw_length_m")
    if cfg.limits.travel_min_m >= cfg.limits.travel_max_m:
        raise ConfigError(
            f, "limits.travel_max_m",
            f"must be greater than limits.travel_min_m ({cfg.limits.travel_max_m:g} <= {cfg.limits.travel_min_m:g})",
        )
    if cfg.effects.resonance_frequency_hz > 0 and not cfg.effects.resonance_mass_kg > 0:
        raise ConfigError(f, "effects.resonance_mass_kg", "must be > 0 when resonance_frequency_hz is set")
    if cfg.backlash.enabled and m.model == "rigid":
        raise ConfigError(f, "backlash.enabled", "a rigid axis has no nut contact for backlash")


def _short(path: str, keep: int = 120) -> str:
    """A path for an error line: at most ``keep`` characters (a 4096-character name is cut in the middle)."""
    return path if len(path) <= keep else f"{path[:keep // 2]}...{path[-keep // 2:]}"


def read_text_file(path: str | Path, what: str = "file", max_bytes: int = MAX_CONFIG_BYTES) -> str:
    """A small UTF-8 text file's text (a BOM is accepted). Raises :class:`ConfigError` naming the file (and
    the line of the first byte that is not UTF-8) for a missing, unreadable, oversized or non-UTF-8 file."""
    if not str(path).strip():  # Path("") is "." and would read as "is a folder"
        raise ConfigError(repr(str(path)), "", f"empty or blank path: give a {what}")
    p = Path(path)
    try:
        if p.exists() and not p.is_dir() and not p.is_file() and not p.is_char_device():
            # a FIFO or socket would block the read until someone writes to it
            raise ConfigError(str(p), "", f"not a regular file (a pipe or socket); give a {what}")
        with p.open("rb") as fh:
            blob = fh.read(max_bytes + 1)
    except FileNotFoundError:
        raise ConfigError(str(p), "", f"{what} not found") from None
    except IsADirectoryError:
        raise ConfigError(str(p), "", f"is a folder, not a {what}") from None
    except OSError as exc:  # no permission, a name too long, a loop of symbolic links, ...
        raise ConfigError(_short(str(p)), "", f"cannot read ({exc.strerror or exc})") from None
    if len(blob) > max_bytes:
        raise ConfigError(str(p), "", f"larger than {max_bytes >> 20} MiB: not a {what}")
    try:
        return blob.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        line = blob[: exc.start].count(b"\n") + 1
        raise ConfigError(
            str(p), "", f"line {line}: not UTF-8 text (byte 0x{blob[exc.start]:02x} at offset {exc.start})"
        ) from None


#: without ``control.speed_limit_rpm``, the fastest speed = this x ``limits.max_velocity_m_s`` (chosen: 10 %
#: headroom for the position controller's correction at full traverse speed)
MAX_SPEED_HEADROOM = 1.1


def max_table_speed_m_s(cfg: AxisConfig) -> float:
    """The fastest table speed the axis runs at [m/s]: the motor speed limit ``control.speed_limit_rpm`` through
    the lead, else :data:`MAX_SPEED_HEADROOM` x ``limits.max_velocity_m_s``; never below the latter. The drive's
    default max motor speed 0x6080 and the plant's end-stop over-travel both come from it, so that every speed
    the drive allows by default brakes after the limit switch."""
    v_lim = cfg.limits.max_velocity_m_s
    if cfg.control.speed_limit_rpm > 0 and cfg.actuator.kind != "force" and cfg.mechanics.lead_m > 0:
        return max(v_lim, cfg.control.speed_limit_rpm / 60.0 * cfg.mechanics.lead_m)
    return MAX_SPEED_HEADROOM * v_lim


def load_axis_config(path: str | Path) -> AxisConfig:
    """Read and validate an axis config file. Raises :class:`ConfigError` naming file and key."""
    text = read_text_file(path, "config file")
    p = Path(path)
    try:
        data = parse_toml(text)
    except TomlError as exc:
        raise ConfigError(str(p), "", str(exc)) from None
    return axis_config_from_dict(data, str(p))
