"""The library of candidate unmodelled effects.

Each :class:`Effect` is a plant component with physically bounded parameters. ``params(cfg)`` gives
the parameters with bounds and a typical ("realistic") size for the axis at hand; ``apply(cfg,
values)`` maps values onto an :class:`~virtualaxis.config.AxisConfig` (through ``cfg.replace``);
``applicable(cfg)`` says whether the effect exists on this kind of axis (no backlash or cogging on a
rigid force-driven axis); ``signature`` says in words where its gap should lie (the numbers are
checked by comparing localisations, see :mod:`virtualaxis.diagnosis.fit`).

Values are fitted in internal coordinates ``u``: ``value = typical * u`` (``scale = "lin"``) or
``value = typical * exp(u)`` (``"log"``), so that every parameter is of order one for the optimiser.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from virtualaxis.config import AxisConfig

STEEL_EXPANSION_PER_K = 11.5e-6


@dataclass(frozen=True)
class Param:
    """One fitted parameter: ``key`` is the config key (``section.key``) or a derived quantity."""

    name: str
    unit: str
    lower: float
    upper: float
    typical: float
    scale: str = "lin"  # "lin" | "log"
    nominal: float = 0.0  # the value in the nominal config (for the report)
    shape: bool = False  # a shape parameter (taken from the start point while screening, fitted later)

    def to_internal(self, value: float) -> float:
        if self.scale == "log":
            return math.log(max(value, 1e-300) / self.typical)
        return value / self.typical

    def from_internal(self, u: float) -> float:
        v = self.typical * math.exp(u) if self.scale == "log" else self.typical * u
        return min(max(v, self.lower), self.upper)

    def internal_bounds(self) -> tuple[float, float]:
        return self.to_internal(self.lower), self.to_internal(self.upper)


@dataclass(frozen=True)
class Effect:
    name: str
    description: str
    signature: str
    params: Callable[[AxisConfig], list[Param]]
    apply: Callable[[AxisConfig, dict[str, float]], AxisConfig]
    applicable: Callable[[AxisConfig], str | None]  # None = applicable, else the reason why not
    starts: Callable[[AxisConfig, dict], list[dict[str, float]]] = field(default=lambda cfg, hints: [])
    #: parameters that are compared in the gap bench (truth key -> fitted name)
    truth_keys: tuple[tuple[str, str], ...] = ()


def _has_screw(cfg: AxisConfig) -> str | None:
    if cfg.mechanics.model == "rigid":
        return "a rigid single-mass axis has no screw/nut elasticity"
    return None


def _has_lead(cfg: AxisConfig) -> str | None:
    if not cfg.mechanics.lead_m > 0:
        return "a direct drive has no screw lead"
    return None


def _has_motor(cfg: AxisConfig) -> str | None:
    if cfg.actuator.kind != "pmsm":
        return "a force-driven axis has no motor angle for cogging"
    return None


def _always(cfg: AxisConfig) -> str | None:
    return None


def _friction_on(cfg: AxisConfig, changes: dict) -> AxisConfig:
    return cfg.replace(friction={"enabled": True, **changes})


def _fc_neg(cfg: AxisConfig) -> float:
    f = cfg.friction
    if not f.enabled:
        return 0.0
    return f.coulomb_negative_n if f.coulomb_negative_n >= 0 else f.coulomb_n


def _fc(cfg: AxisConfig) -> float:
    return cfg.friction.coulomb_n if cfg.friction.enabled else 0.0


def _force_scale(cfg: AxisConfig) -> float:
    """A force of the order of the axis' rated drive force [N], for bounds."""
    if cfg.actuator.kind == "pmsm" and cfg.mechanics.lead_m > 0:
        tq = cfg.motor.rated_torque_nm or cfg.motor.rated_current_a * max(cfg.motor.torque_constant_nm_per_a, 0.1)
        return tq * 2 * math.pi / cfg.mechanics.lead_m
    if cfg.actuator.force_limit_n > 0:
        return cfg.actuator.force_limit_n
    return 20.0 * cfg.mechanics.table_mass_kg * 9.81  # 20 g worth of force


def _peak_force(cfg: AxisConfig) -> float:
    """The largest force the drive can apply at the table [N]: the current limit (0: 3 x rated) through k_t and
    the lead, or the force actuator's limit; else :func:`_force_scale`."""
    mo = cfg.motor
    if cfg.actuator.kind == "pmsm" and cfg.mechanics.lead_m > 0:
        i_max = cfg.control.current_limit_a or 3.0 * mo.rated_current_a
        if i_max > 0 and mo.torque_constant_nm_per_a > 0:
            return i_max * mo.torque_constant_nm_per_a * 2 * math.pi / cfg.mechanics.lead_m
        return 3.0 * _force_scale(cfg)
    if cfg.actuator.force_limit_n > 0:
        return cfg.actuator.force_limit_n
    return _force_scale(cfg)


# ---------------------------------------------------------------- backlash
def _backlash_params(cfg):
    g0 = cfg.backlash.gap_m if cfg.backlash.enabled else 0.0
    return [Param("gap_m", "m", 0.0, 300e-6, 20e-6, nominal=g0)]


def _backlash_apply(cfg, v):
    return cfg.replace(backlash={"enabled": bool(v["gap_m"] > 0), "gap_m": float(v["gap_m"])})


def _backlash_starts(cfg, hints):
    return [{"gap_m": (cfg.backlash.gap_m if cfg.backlash.enabled else 0.0) + 10e-6}]


# ---------------------------------------------------------------- friction
def _coulomb_params(cfg):
    fs = _force_scale(cfg)
    return [Param("coulomb_n", "N", 0.0, 0.3 * fs, max(0.02 * fs, 10.0), nominal=_fc(cfg))]


def _coulomb_apply(cfg, v):
    f = cfg.friction
    changes: dict = {"coulomb_n": v["coulomb_n"]}
    if f.enabled and f.coulomb_negative_n >= 0 and f.coulomb_n > 0:
        changes["coulomb_negative_n"] = f.coulomb_negative_n * v["coulomb_n"] / f.coulomb_n
    return _friction_on(cfg, changes)


def _coulomb_starts(cfg, hints):
    p = _coulomb_params(cfg)[0]
    return [{"coulomb_n": _fc(cfg) + p.typical}]


def _stribeck_params(cfg):
    fs = _force_scale(cfg)
    f = cfg.friction
    return [
        Param("stribeck_n", "N", 0.0, 0.3 * fs, max(0.02 * fs, 10.0), nominal=f.stribeck_n if f.enabled else 0.0),
        Param("stribeck_velocity_m_s", "m/s", 1e-4, 0.05, 2e-3, scale="log", nominal=f.stribeck_velocity_m_s,
              shape=True),
    ]


def _stribeck_apply(cfg, v):
    return _friction_on(cfg, {"stribeck_n": v["stribeck_n"], "stribeck_velocity_m_s": v["stribeck_velocity_m_s"]})


def _stribeck_starts(cfg, hints):
    p = _stribeck_params(cfg)[0]
    return [{"stribeck_n": p.nominal + p.typical, "stribeck_velocity_m_s": vs} for vs in (5e-4, 3e-3, 1.5e-2)]


def _viscous_params(cfg):
    fs = _force_scale(cfg)
    vmax = cfg.limits.max_velocity_m_s
    typ = max(0.02 * fs / vmax, 50.0)
    f = cfg.friction
    # upper bound: the viscous force at the axis' top speed cannot exceed the drive's peak force (else the axis
    # could not reach it); cold grease on a ball screw can take a good share of the rated force there
    return [Param("viscous_n_s_per_m", "N s/m", 0.0, max(_peak_force(cfg), 0.5 * fs) / vmax, typ,
                  nominal=f.viscous_n_s_per_m if f.enabled else 0.0)]


def _viscous_apply(cfg, v):
    f = cfg.friction
    changes: dict = {"viscous_n_s_per_m": v["viscous_n_s_per_m"]}
    if f.enabled and f.viscous_negative_n_s_per_m >= 0 and f.viscous_n_s_per_m > 0:  # keep the asymmetry ratio
        ratio = f.viscous_negative_n_s_per_m / f.viscous_n_s_per_m
        changes["viscous_negative_n_s_per_m"] = ratio * v["viscous_n_s_per_m"]
    return _friction_on(cfg, changes)


def _viscous_starts(cfg, hints):
    p = _viscous_params(cfg)[0]
    return [{"viscous_n_s_per_m": p.nominal + p.typical}]


def _asym_params(cfg):
    fs = _force_scale(cfg)
    typ = max(0.02 * fs, 10.0)
    return [
        Param("coulomb_n", "N", 0.0, 0.3 * fs, typ, nominal=_fc(cfg)),
        Param("coulomb_negative_n", "N", 0.0, 0.3 * fs, typ, nominal=_fc_neg(cfg)),
    ]


def _asym_apply(cfg, v):
    return _friction_on(cfg, {"coulomb_n": v["coulomb_n"], "coulomb_negative_n": v["coulomb_negative_n"]})


def _asym_starts(cfg, hints):
    fc, fcn = _fc(cfg), _fc_neg(cfg)
    typ = _asym_params(cfg)[0].typical
    return [{"coulomb_n": fc + typ, "coulomb_negative_n": fcn + typ}]


def _fv(cfg: AxisConfig) -> float:
    return cfg.friction.viscous_n_s_per_m if cfg.friction.enabled else 0.0


def _fv_neg(cfg: AxisConfig) -> float:
    f = cfg.friction
    if not f.enabled:
        return 0.0
    return f.viscous_negative_n_s_per_m if f.viscous_negative_n_s_per_m >= 0 else f.viscous_n_s_per_m


def _viscous_asym_params(cfg):
    p = _viscous_params(cfg)[0]  # same physical range as viscous friction, one coefficient per direction
    return [dataclasses.replace(p, nominal=_fv(cfg)),
            dataclasses.replace(p, name="viscous_negative_n_s_per_m", nominal=_fv_neg(cfg))]


def _viscous_asym_apply(cfg, v):
    return _friction_on(cfg, {"viscous_n_s_per_m": v["viscous_n_s_per_m"],
                              "viscous_negative_n_s_per_m": v["viscous_negative_n_s_per_m"]})


def _viscous_asym_starts(cfg, hints):
    typ = _viscous_asym_params(cfg)[0].typical
    fv, fvn = _fv(cfg), _fv_neg(cfg)
    # one direction at a time and both: the response to each coefficient lives in one direction's samples
    return [{"viscous_n_s_per_m": fv + typ, "viscous_negative_n_s_per_m": fvn + typ},
            {"viscous_n_s_per_m": fv, "viscous_negative_n_s_per_m": fvn + typ},
            {"viscous_n_s_per_m": fv + typ, "viscous_negative_n_s_per_m": fvn}]


def _offset_params(cfg):
    fs = _force_scale(cfg)
    return [Param("force_offset_n", "N", -0.3 * fs, 0.3 * fs, max(0.02 * fs, 10.0),
                  nominal=cfg.effects.force_offset_n)]


def _offset_apply(cfg, v):
    return cfg.replace(effects={"force_offset_n": v["force_offset_n"]})


def _offset_starts(cfg, hints):
    p = _offset_params(cfg)[0]
    return [{"force_offset_n": p.nominal + p.typical}]


# ---------------------------------------------------------------- inertia
def _mass_params(cfg):
    m0 = cfg.mechanics.table_mass_kg
    return [Param("table_mass_kg", "kg", 0.1 * m0, 5.0 * m0, m0, nominal=m0)]


def _mass_apply(cfg, v):
    return cfg.replace(mechanics={"table_mass_kg": v["table_mass_kg"]})


def _mass_starts(cfg, hints):
    m0 = cfg.mechanics.table_mass_kg
    return [{"table_mass_kg": m0 * 1.2}]


# ---------------------------------------------------------------- stiffness
_STIFFNESS_KEYS = (
    "bearing_axial_stiffness_n_per_m",
    "support_axial_stiffness_n_per_m",
    "nut_contact_stiffness_n_per_m",
    "equivalent_torsional_stiffness_nm_per_rad",
)


def _compliance_params(cfg):
    return [Param("axial_stiffness_scale", "1", 0.02, 2.0, 1.0, scale="log", nominal=1.0)]


def _compliance_apply(cfg, v):
    k = v["axial_stiffness_scale"]
    m = cfg.mechanics
    return cfg.replace(mechanics={key: getattr(m, key) * k for key in _STIFFNESS_KEYS})


def _compliance_starts(cfg, hints):
    return [{"axial_stiffness_scale": 0.5}]


# ---------------------------------------------------------------- extra mode
def _resonance_params(cfg):
    e = cfg.effects
    m0 = cfg.mechanics.table_mass_kg + e.resonance_mass_kg  # the weighed moving mass the mode is a part of
    return [
        Param("resonance_frequency_hz", "Hz", 3.0, 400.0, 50.0, scale="log", nominal=e.resonance_frequency_hz,
              shape=True),
        Param("resonance_mass_kg", "kg", 0.01 * m0, 0.9 * m0, 0.1 * m0, scale="log", nominal=e.resonance_mass_kg),
        Param("resonance_damping_ratio", "1", 0.003, 0.5, 0.05, scale="log", nominal=e.resonance_damping_ratio,
              shape=True),
    ]


def _resonance_apply(cfg, v):
    """The mode is a part of the moving mass on a spring (a fixture, a column): the config's table mass is the
    weighed moving mass, so the modal mass is taken out of the table (the total stays; a mass error is its own
    effect). Without this a 30 kg mode of a 250 kg table fitted as 250 + 30 kg."""
    m_r0 = cfg.effects.resonance_mass_kg
    table = cfg.mechanics.table_mass_kg + m_r0 - v["resonance_mass_kg"]
    return cfg.replace(mechanics={"table_mass_kg": max(table, 1e-3)},
                       effects={k: v[k] for k in ("resonance_frequency_hz", "resonance_mass_kg",
                                                  "resonance_damping_ratio")})


# coarse frequency scan for the mode: log-spaced, neighbours 1.3x apart (the screening step then
# picks the frequency whose response explains most of the residual; refinement polishes it). A mode
# inside a closed loop rarely shows as a clean peak of one channel's residual spectrum, so spectral
# peaks (of every measured channel) are only extra start points, not the only ones.
_RESONANCE_SCAN_HZ = tuple(float(4.0 * 1.3**k) for k in range(17))  # 4 .. ~266 Hz
_RESONANCE_MIN_RATIO = 1.08  # start frequencies closer than this to an earlier one are dropped


def _resonance_start_frequencies(hints) -> list[float]:
    peaks = [float(f) for f in list(hints.get("peaks_hz", []))[:3] + list(hints.get("peaks_all_hz", []))]
    out: list[float] = []
    for f in peaks + list(_RESONANCE_SCAN_HZ):
        if 3.0 <= f <= 400.0 and all(max(f, g) / min(f, g) >= _RESONANCE_MIN_RATIO for g in out):
            out.append(f)
    return out


def _resonance_starts(cfg, hints):
    m0 = cfg.mechanics.table_mass_kg
    return [{"resonance_frequency_hz": f, "resonance_mass_kg": 0.1 * m0, "resonance_damping_ratio": 0.05}
            for f in _resonance_start_frequencies(hints)]


# ---------------------------------------------------------------- lead error
def _lead_params(cfg):
    e = cfg.effects
    return [
        Param("lead_error_ppm", "um/m", -500.0, 500.0, 30.0, nominal=e.lead_error_ppm),
        Param("periodic_cos_m", "m", -50e-6, 50e-6, 3e-6,
              nominal=e.lead_error_periodic_m * math.cos(e.lead_error_periodic_phase_rad)),
        Param("periodic_sin_m", "m", -50e-6, 50e-6, 3e-6,
              nominal=e.lead_error_periodic_m * math.sin(e.lead_error_periodic_phase_rad)),
    ]


def _lead_apply(cfg, v):
    amp = math.hypot(v["periodic_cos_m"], v["periodic_sin_m"])
    ph = math.atan2(v["periodic_sin_m"], v["periodic_cos_m"])
    return cfg.replace(effects={"lead_error_ppm": v["lead_error_ppm"], "lead_error_periodic_m": amp,
                                "lead_error_periodic_phase_rad": ph})


def _lead_starts(cfg, hints):
    p = _lead_params(cfg)
    return [{"lead_error_ppm": p[0].nominal + 30.0, "periodic_cos_m": p[1].nominal + 2e-6,
             "periodic_sin_m": p[2].nominal + 2e-6}]


# ---------------------------------------------------------------- torque ripple
def _ripple_params(cfg):
    mo = cfg.motor
    tq = mo.rated_torque_nm or mo.rated_current_a * max(mo.torque_constant_nm_per_a, 0.1)
    c0 = mo.cogging_amplitude_nm * math.cos(mo.cogging_phase_rad)
    s0 = mo.cogging_amplitude_nm * math.sin(mo.cogging_phase_rad)
    return [
        Param("cogging_cos_nm", "N m", -0.2 * tq, 0.2 * tq, 0.01 * tq, nominal=c0),
        Param("cogging_sin_nm", "N m", -0.2 * tq, 0.2 * tq, 0.01 * tq, nominal=s0),
        Param("cogging_periods_per_rev", "1/rev", 1.0, 200.0, 1.0, nominal=mo.cogging_periods_per_rev),
    ]


def _ripple_apply(cfg, v):
    amp = math.hypot(v["cogging_cos_nm"], v["cogging_sin_nm"])
    ph = math.atan2(v["cogging_sin_nm"], v["cogging_cos_nm"])
    return cfg.replace(motor={"cogging_amplitude_nm": amp, "cogging_phase_rad": ph,
                              "cogging_periods_per_rev": float(round(v["cogging_periods_per_rev"]))})


def _ripple_starts(cfg, hints):
    orders = hints.get("angle_orders", []) or [cfg.motor.cogging_periods_per_rev or 2 * cfg.motor.pole_pairs * 3]
    typ = _ripple_params(cfg)[0].typical
    p = _ripple_params(cfg)
    return [{"cogging_cos_nm": p[0].nominal + typ, "cogging_sin_nm": p[1].nominal + typ,
             "cogging_periods_per_rev": float(n)} for n in orders[:3]]


# ---------------------------------------------------------------- delay, thermal
def _delay_scope(cfg) -> float:
    return 1.0 if cfg.sensors.dead_time_scope == "feedback_sensor" else 0.0


def _delay_params(cfg):
    # dead_time_feedback_sensor (discrete 0/1, sensors.dead_time_scope): 0 = only the position loop's feedback is
    # delayed; 1 = the feedback sensor's reading everywhere (speed loop, recorded motor_pos / pos_meas)
    return [Param("dead_time_s", "s", 0.0, 0.02, 1e-3, nominal=cfg.sensors.dead_time_s),
            Param("dead_time_feedback_sensor", "1", 0.0, 1.0, 1.0, nominal=_delay_scope(cfg))]


def _delay_apply(cfg, v):
    scope = v.get("dead_time_feedback_sensor", _delay_scope(cfg))
    return cfg.replace(sensors={"dead_time_s": v["dead_time_s"],
                                "dead_time_scope": "feedback_sensor" if scope >= 0.5 else "position_loop"})


def _delay_starts(cfg, hints):
    dt = cfg.control.position_cycle_s
    d = cfg.sensors.dead_time_s + max(dt, 1e-3)
    return [{"dead_time_s": d, "dead_time_feedback_sensor": s} for s in (_delay_scope(cfg), 1.0 - _delay_scope(cfg))]


# ---------------------------------------------------------------- speed estimator
def _estimator_params(cfg):
    c = cfg.control
    ts = c.speed_cycle_s
    # speed_estimator_samples (discrete 1/2, control.speed_estimator): (q[k] - q[k-1]) / T or (q[k] - q[k-2]) / 2T;
    # speed_filter_cycles: the low-pass time constant in speed cycles T (speed_filter_time_constant_s / T), up to
    # 20 (beyond that a speed loop no longer closes on its estimate)
    return [Param("speed_estimator_samples", "1", 1.0, 2.0, 1.0,
                  nominal=2.0 if c.speed_estimator == "two_sample_difference" else 1.0),
            Param("speed_filter_cycles", "speed cycles", 0.0, 20.0, 1.0, nominal=c.speed_filter_time_constant_s / ts)]


def _estimator_apply(cfg, v):
    c = cfg.control
    samples = v.get("speed_estimator_samples", 2.0 if c.speed_estimator == "two_sample_difference" else 1.0)
    return cfg.replace(control={
        "speed_estimator": "two_sample_difference" if samples >= 1.5 else "backward_difference",
        "speed_filter_time_constant_s": max(float(v["speed_filter_cycles"]), 0.0) * c.speed_cycle_s})


def _estimator_starts(cfg, hints):
    c0 = cfg.control.speed_filter_time_constant_s / cfg.control.speed_cycle_s
    # the screening step needs an amplitude that moves, and predicts linearly in it: the other form with the filter
    # nudged by 5 % of a speed cycle (the column is then the form change itself), each form with one speed cycle of
    # filter; the refinement takes the filter back to 0 when the form alone explains the gap
    return [{"speed_estimator_samples": s, "speed_filter_cycles": c0 + f} for s, f in ((2.0, 0.05), (2.0, 1.0),
                                                                                       (1.0, 1.0))]


def filter_delay_cycles(tau_cycles: float) -> float:
    """Low-frequency (group) delay of the step-invariant first-order filter w_f += (1 - exp(-T/tau)) (w - w_f), in
    samples T: (1 - a) / a = 1 / (exp(T / tau) - 1) (0 without a filter). The two-sample difference delays by 1/2
    against the one-sample difference, as does this filter with tau = T / ln 3 = 0.91 T."""
    if tau_cycles <= 0:
        return 0.0
    return 1.0 / math.expm1(1.0 / tau_cycles)


#: a one-sample estimate with a filter whose delay is within this of half a sample is the two-sample estimate
TWO_SAMPLE_DELAY_TOLERANCE = 0.125


def _thermal_params(cfg):
    e = cfg.effects
    return [
        Param("initial_temperature_rise_k", "K", -30.0, 30.0, 2.0, nominal=e.initial_temperature_rise_k),
        Param("thermal_resistance_k_per_w", "K/W", 0.0, 5.0, 0.1, nominal=e.thermal_resistance_k_per_w),
    ]


def _thermal_apply(cfg, v):
    alpha = cfg.effects.thermal_expansion_per_k or STEEL_EXPANSION_PER_K
    return cfg.replace(effects={"thermal_expansion_per_k": alpha,
                                "initial_temperature_rise_k": v["initial_temperature_rise_k"],
                                "thermal_resistance_k_per_w": v["thermal_resistance_k_per_w"]})


def _thermal_starts(cfg, hints):
    e = cfg.effects
    return [{"initial_temperature_rise_k": e.initial_temperature_rise_k + 2.0,
             "thermal_resistance_k_per_w": e.thermal_resistance_k_per_w + 0.1}]


EFFECTS: dict[str, Effect] = {
    e.name: e
    for e in (
        Effect("backlash", "dead zone at the nut contact (lost motion on reversal)",
               "reversal phase; position channels; step-like lost motion after each direction change",
               _backlash_params, _backlash_apply, _has_screw, _backlash_starts, (("backlash.gap_m", "gap_m"),)),
        Effect("coulomb_friction", "Coulomb friction force different from the model",
               "force/torque channel, sign of velocity (reversal, low speed); in position at reversals",
               _coulomb_params, _coulomb_apply, _always, _coulomb_starts, (("friction.coulomb_n", "coulomb_n"),)),
        Effect("stribeck_friction", "Stribeck (static over sliding) friction at low speed",
               "low-speed bin and reversals, force channel; decays within a few mm/s",
               _stribeck_params, _stribeck_apply, _always, _stribeck_starts,
               (("friction.stribeck_n", "stribeck_n"),)),
        Effect("viscous_friction", "viscous friction different from the model",
               "grows with speed; high-speed bins of the force channel, velocity-shaped",
               _viscous_params, _viscous_apply, _always, _viscous_starts,
               (("friction.viscous_n_s_per_m", "viscous_n_s_per_m"),)),
        Effect("friction_asymmetry", "Coulomb friction that differs between the directions",
               "direction: one direction carries more residual; force offset by direction",
               _asym_params, _asym_apply, _always, _asym_starts,
               (("friction.coulomb_n", "coulomb_n"), ("friction.coulomb_negative_n", "coulomb_negative_n"))),
        Effect("viscous_asymmetry", "viscous friction that differs between the directions (seals, a cable chain "
               "that drags one way): F_v for +v and for -v",
               "force channel grows with speed in one direction more than in the other; high-speed bins by direction",
               _viscous_asym_params, _viscous_asym_apply, _always, _viscous_asym_starts,
               (("friction.viscous_n_s_per_m", "viscous_n_s_per_m"),
                ("friction.viscous_negative_n_s_per_m", "viscous_negative_n_s_per_m"))),
        Effect("force_offset", "constant load force against +x (gravity on an inclined axis, cable drag): "
               "m a = F - F_friction - offset",
               "force/torque channel offset in both directions and at standstill; position only through the loop",
               _offset_params, _offset_apply, _always, _offset_starts, (("effects.force_offset_n", "force_offset_n"),)),
        Effect("mass_error", "moving mass (inertia) different from the model",
               "acceleration phase, force channel proportional to the command acceleration",
               _mass_params, _mass_apply, _always, _mass_starts, (("mechanics.table_mass_kg", "table_mass_kg"),)),
        Effect("axial_compliance", "axial stiffness (bearings, support, nut) lower than modelled, "
               "position dependent through K_as(x)",
               "position channel of the linear scale, grows with force; stroke-position dependent",
               _compliance_params, _compliance_apply, _has_screw, _compliance_starts,
               (("axial_stiffness_scale", "axial_stiffness_scale"),)),
        Effect("resonance", "an unmodelled structural mode on the table",
               "a peak in the residual spectrum, excited at acceleration changes",
               _resonance_params, _resonance_apply, _always, _resonance_starts,
               (("effects.resonance_frequency_hz", "resonance_frequency_hz"),)),
        Effect("lead_error", "screw pitch error: cumulative (ppm) and periodic per revolution",
               "linear-scale position only, a function of stroke position; periodic with the lead",
               _lead_params, _lead_apply, _has_lead, _lead_starts,
               (("effects.lead_error_ppm", "lead_error_ppm"),)),
        Effect("torque_ripple", "cogging / torque ripple periodic in the motor angle",
               "torque/current channel at (periods per rev) x motor speed; frequency grows with speed",
               _ripple_params, _ripple_apply, _has_motor, _ripple_starts,
               (("motor.cogging_amplitude_nm", "cogging_amplitude_nm"),)),
        Effect("time_delay", "measurement / loop dead time",
               "position error proportional to speed, phase lag growing with frequency",
               _delay_params, _delay_apply, _always, _delay_starts, (("sensors.dead_time_s", "dead_time_s"),)),
        Effect("speed_estimator", "the speed loop's speed estimate: one- or two-sample difference of the position it "
               "samples, optionally low-passed (control.speed_estimator, speed_filter_time_constant_s)",
               "force channel during acceleration changes (an extra lag in the speed loop); looks like a mass error",
               _estimator_params, _estimator_apply, _always, _estimator_starts,
               (("speed_estimator_samples", "speed_estimator_samples"),)),
        Effect("thermal_drift", "screw thermal expansion (initial temperature and friction heating)",
               "linear-scale position, grows with stroke position and with time",
               _thermal_params, _thermal_apply, _has_lead, _thermal_starts,
               (("effects.initial_temperature_rise_k", "initial_temperature_rise_k"),)),
    )
}

#: parameters that are chosen by search, not by the least-squares fit
DISCRETE_PARAMS = {"cogging_periods_per_rev", "dead_time_feedback_sensor", "speed_estimator_samples"}


def reduce_nested(effect: str, values: dict[str, float], stderr: dict[str, float]) -> tuple[str, dict] | None:
    """The simpler effect a fitted one reduces to, with its start values, or None: friction asymmetry whose
    two directions agree within their uncertainty (2 sigma) or within :data:`MIN_RELATIVE_CHANGE` of their mean (an
    asymmetry smaller than the change an effect must make to pay its way) is Coulomb friction; viscous asymmetry
    whose two directions agree so is viscous friction; a one-sample speed estimate
    low-passed by half a sample (:func:`filter_delay_cycles` within :data:`TWO_SAMPLE_DELAY_TOLERANCE` of 1/2) is
    the two-sample estimate without a filter."""
    symmetric = {"friction_asymmetry": ("coulomb_friction", "coulomb_n", "coulomb_negative_n"),
                 "viscous_asymmetry": ("viscous_friction", "viscous_n_s_per_m", "viscous_negative_n_s_per_m")}
    if effect in symmetric:
        simpler, key_pos, key_neg = symmetric[effect]
        a, b = values[key_pos], values[key_neg]
        sa, sb = stderr.get(key_pos, math.nan), stderr.get(key_neg, math.nan)
        sd = math.hypot(sa, sb) if math.isfinite(sa) and math.isfinite(sb) else 0.0
        if abs(a - b) <= max(2.0 * sd, MIN_RELATIVE_CHANGE * 0.5 * (a + b)):
            return simpler, {key_pos: 0.5 * (a + b)}
    if effect == "speed_estimator" and values.get("speed_estimator_samples", 1.0) < 1.5:
        # a one-sample difference low-passed with half a sample of delay is, at the frequencies a trace resolves,
        # the two-sample difference (same delay and gain at low frequency) without a free parameter: prefer that
        if abs(filter_delay_cycles(values.get("speed_filter_cycles", 0.0)) - 0.5) <= TWO_SAMPLE_DELAY_TOLERANCE:
            return "speed_estimator", {"speed_estimator_samples": 2.0, "speed_filter_cycles": 0.0}
    return None


#: separator of effect and parameter in the parameter names of a combined effect ("backlash/gap_m")
JOINT_SEP = "/"
#: an effect pays its way only if it changes some parameter of the current model by at least this share
MIN_RELATIVE_CHANGE = 0.05


def is_discrete(param_name: str) -> bool:
    return param_name.rsplit(JOINT_SEP, 1)[-1] in DISCRETE_PARAMS


def relative_change(effect: str, cfg: AxisConfig, values: dict[str, float]) -> float:
    """Largest change of a fitted (continuous) parameter relative to its value in ``cfg``; ``inf`` where that
    value is 0 and the fitted one is not (an effect the model did not have). A fit that only nudges values the
    model already has — a Coulomb force of 40.03 N where the config says 40 N — is a calibration of noise or
    of a small mismatch elsewhere, not a missing effect (:data:`MIN_RELATIVE_CHANGE`). A discrete parameter that
    differs from the model's (another speed-estimator form, dead-time scope, cogging order) is a structural change:
    ``inf``."""
    worst = 0.0
    for p in effect_of(effect).params(cfg):
        if p.name not in values:
            continue
        if is_discrete(p.name):
            if float(values[p.name]) != p.nominal:
                return math.inf
            continue
        v = float(values[p.name])
        if p.nominal == 0.0:
            if v != 0.0:
                return math.inf
            continue
        worst = max(worst, abs(v - p.nominal) / abs(p.nominal))
    return worst


#: an extra mode damped this much is no resonance (it does not ring): a fit that needs it is a model-form
#: mismatch the library does not describe (a wrong controller, a missing lag), not an answer
MAX_RESONANCE_DAMPING = 0.2
#: a fitted amplitude must differ from the model's value by this many standard errors to be determined
MIN_SIGNIFICANCE = 3.0


def implausible(effect: str, cfg: AxisConfig, values: dict[str, float], stderr: dict[str, float],
                at_bound: list[str]) -> list[str]:
    """Why a fitted effect is not a physical answer (empty list: it is). A parameter at a bound of its
    physical range other than zero (the fit wanted more than the range allows), a "resonance" damped
    >= :data:`MAX_RESONANCE_DAMPING`, an amplitude parameter not determined by the fit traces (standard error
    infinite) or not distinguishable from the model's value (:data:`MIN_SIGNIFICANCE` standard errors)."""
    why: list[str] = []
    params = {p.name: p for p in effect_of(effect).params(cfg)}
    for name in at_bound:
        p = params.get(name)
        if p is None or fx_is_zero_bound(p, values.get(name, math.nan)):
            continue
        why.append(f"{name} = {values.get(name, math.nan):.4g} {p.unit} at the bound of its range "
                   f"[{p.lower:g}, {p.upper:g}]")
    for key, v in values.items():
        base = key.rsplit(JOINT_SEP, 1)[-1]
        if base == "resonance_damping_ratio" and v >= MAX_RESONANCE_DAMPING:
            why.append(f"a mode damped {v:.2f} (>= {MAX_RESONANCE_DAMPING}) is not a resonance")
    amps = [p for p in params.values() if not p.shape and not is_discrete(p.name)]
    # a discrete parameter that differs from the model's (another speed-estimator form) is the answer by itself;
    # an amplitude left at its physical zero beside it (no speed filter) is then no parameter to determine
    structural = any(is_discrete(p.name) and p.name in values and float(values[p.name]) != p.nominal
                     for p in params.values())
    significant = structural
    loose: list[str] = []
    for p in amps:
        se = float(stderr.get(p.name, math.nan))
        v = float(values.get(p.name, p.nominal))
        if structural and p.nominal == 0.0 and fx_is_zero_bound(p, v):
            continue
        if se == math.inf:
            loose.append(f"{p.name} not determined by the fit traces")
        elif math.isfinite(se) and abs(v - p.nominal) >= MIN_SIGNIFICANCE * se:
            significant = True
        elif not math.isfinite(se):
            significant = True  # no uncertainty computed (e.g. differential evolution): not judged
    # an amplitude the traces do not determine is no answer unless another amplitude of the effect is determined
    # and significant: a warm screw's initial temperature (4.98 +- small K) establishes thermal growth, its heating
    # per friction watt over a few seconds is then a nuisance reported as not determined, not a veto
    if loose and not significant:
        why.extend(loose)
    if amps and not significant and not loose:
        why.append("no fitted value differs from the model's by " f"{MIN_SIGNIFICANCE:g} standard errors")
    return why


def fx_is_zero_bound(p: Param, value: float) -> bool:
    """True when ``value`` sits at a bound that is zero (no friction heating, no gap: a physical value). "At" is
    within a millionth of the parameter's typical size for a linear parameter (an optimiser stops near, not on,
    the bound: a thermal resistance of 5e-9 K/W against a typical 0.05 K/W is zero)."""
    tol = 1e-12 * max(abs(p.upper), 1.0)
    if p.scale == "lin":
        tol = max(tol, 1e-6 * abs(p.typical))
    return abs(value) <= tol and (p.lower == 0.0 or p.upper == 0.0)


def effect_of(name: str) -> Effect:
    """An effect of the library by name, or several joined by "+" as one effect (a joint refit of
    accepted effects: parameters named ``effect/param``, applied in the order given)."""
    if name in EFFECTS:
        return EFFECTS[name]
    parts = tuple(name.split("+"))
    unknown = [p for p in parts if p not in EFFECTS]
    if len(parts) < 2 or unknown:
        raise KeyError(f"unknown effect {name!r}")
    return _combined(parts)


def _combined(parts: tuple[str, ...]) -> Effect:
    def params(cfg: AxisConfig) -> list[Param]:
        return [dataclasses.replace(p, name=f"{e}{JOINT_SEP}{p.name}") for e in parts for p in EFFECTS[e].params(cfg)]

    def apply(cfg: AxisConfig, v: dict[str, float]) -> AxisConfig:
        for e, vals in split_joint(v).items():
            cfg = EFFECTS[e].apply(cfg, vals)
        return cfg

    return Effect("+".join(parts), "joint refit of " + ", ".join(parts), "", params, apply, _always)


def split_joint(values: dict[str, float]) -> dict[str, dict[str, float]]:
    """``{"a/x": 1, "b/y": 2}`` -> ``{"a": {"x": 1}, "b": {"y": 2}}`` (insertion order kept)."""
    out: dict[str, dict[str, float]] = {}
    for k, v in values.items():
        e, _, p = k.partition(JOINT_SEP)
        out.setdefault(e, {})[p] = v
    return out


def split_joint_names(names: list[str]) -> dict[str, list[str]]:
    """``["a/x", "b/y", "a/z"]`` -> ``{"a": ["x", "z"], "b": ["y"]}``: a joint fit's parameter names by effect."""
    out: dict[str, list[str]] = {}
    for k in names:
        e, _, p = k.partition(JOINT_SEP)
        out.setdefault(e, []).append(p)
    return out


#: effects fitted as cos/sin components and reported as amplitude/phase: (cos, sin, amplitude, phase) names
_POLAR = {"lead_error": ("periodic_cos_m", "periodic_sin_m", "lead_error_periodic_m", "lead_error_periodic_phase_rad"),
          "torque_ripple": ("cogging_cos_nm", "cogging_sin_nm", "cogging_amplitude_nm", "cogging_phase_rad")}


def derived_values(effect: str, values: dict[str, float]) -> dict[str, float]:
    """Report-friendly values (amplitude/phase instead of cos/sin components)."""
    out = dict(values)
    if effect in _POLAR:
        kc, ks, ka, kp = _POLAR[effect]
        out[ka] = math.hypot(values[kc], values[ks])
        out[kp] = math.atan2(values[ks], values[kc])
    return out


def derived_stderr(effect: str, values: dict[str, float], stderr: dict[str, float]) -> dict[str, float]:
    """Standard errors of :func:`derived_values` (first order, the two components taken as uncorrelated):
    amplitude ``A = hypot(c, s)``: ``sqrt((c sc)^2 + (s ss)^2) / A``; phase: ``sqrt((s sc)^2 + (c ss)^2) / A^2``."""
    out = dict(stderr)
    if effect in _POLAR and all(k in values for k in _POLAR[effect][:2]):
        kc, ks, ka, kp = _POLAR[effect]
        c, s_ = values[kc], values[ks]
        sc, ss = stderr.get(kc, math.nan), stderr.get(ks, math.nan)
        a = math.hypot(c, s_)
        if math.inf in (sc, ss):  # a component not determined: neither is the amplitude nor the phase
            out[ka] = out[kp] = math.inf
        elif a > 0:
            out[ka] = math.hypot(c * sc, s_ * ss) / a
            out[kp] = math.hypot(s_ * sc, c * ss) / a**2
    return out


def applicable_effects(cfg: AxisConfig, names: list[str] | None = None) -> tuple[list[Effect], dict[str, str]]:
    """Effects of the library that exist on this axis, and the reasons for the others."""
    chosen = [EFFECTS[n] for n in (names or list(EFFECTS))]
    ok, skipped = [], {}
    for e in chosen:
        why = e.applicable(cfg)
        if why is None:
            ok.append(e)
        else:
            skipped[e.name] = why
    return ok, skipped


def angle_orders_hint(motor_angle_rad: np.ndarray, effort_residual: np.ndarray, max_order: int = 120) -> list[int]:
    """Dominant harmonic orders of an effort residual over the motor angle (for cogging starts)."""
    if motor_angle_rad.size < 64 or np.ptp(motor_angle_rad) < 2 * math.pi:
        return []
    order = np.argsort(motor_angle_rad)
    th = motor_angle_rad[order]
    r = effort_residual[order] - np.mean(effort_residual)
    orders = np.arange(1, max_order + 1)
    amp = np.array([abs(np.sum(r * np.exp(-1j * n * th))) for n in orders])
    return [int(orders[i]) for i in np.argsort(-amp)[:3]]
