"""Withheld-effect cases of the reference axis: the truth (nominal + effect), the config written without it,
fit and held-out traces, and the truth record the bench scores against.

Effect names follow the diagnosis library (docs/diagnosis.md); the vocabulary real axes need but the library
may not have yet is named ``force_offset``, ``viscous_asymmetry``, ``moving_start``, ``channel_shift`` and
``speed_estimator`` (docs/refaxis.md).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from virtualaxis.refaxis import axes as A
from virtualaxis.refaxis import commands as C
from virtualaxis.refaxis.run import noise_seed, simulate


@dataclass(frozen=True)
class CaseSpec:
    """One case: truth overrides on the nominal physical parameters and what the bench should find."""

    structure: str
    name: str
    truth: dict = field(default_factory=dict)  # physical overrides (axes.TWO_MASS / RIGID_PP keys)
    effects: tuple = ()  # effect names as in the diagnosis library
    params: dict = field(default_factory=dict)  # config key or effect/param -> true value
    main_param: dict = field(default_factory=dict)  # effect -> key in params
    notes: str = ""
    moving_start: bool = False
    channel_shift: int = 0


def _r2() -> float:
    return A.radius_m_per_rad(A.TWO_MASS) ** 2


def _specs() -> list[CaseSpec]:
    tm, rp, fc = "two_mass", "rigid_pp", "full_closed"
    nom_k = A.TWO_MASS["axial_stiffness_n_per_m"]
    out = [
        CaseSpec(tm, "clean", notes="nominal axis; nothing withheld"),
        CaseSpec(tm, "backlash", {"gap_m": 12e-6}, ("backlash",), {"backlash.gap_m": 12e-6},
                 {"backlash": "backlash.gap_m"}, "12 um lost motion at the nut (worn single nut)"),
        CaseSpec(tm, "coulomb_friction", {"coulomb_n": 75.0, "coulomb_negative_n": 75.0}, ("coulomb_friction",),
                 {"friction.coulomb_n": 75.0}, {"coulomb_friction": "friction.coulomb_n"},
                 "guide wipers / seals added: Coulomb 30 -> 75 N"),
        CaseSpec(tm, "stribeck_friction", {"stribeck_n": 40.0, "stribeck_velocity_m_s": 0.003},
                 ("stribeck_friction",), {"friction.stribeck_n": 40.0, "friction.stribeck_velocity_m_s": 0.003},
                 {"stribeck_friction": "friction.stribeck_n"},
                 "40 N Stribeck excess, Gaussian curve (exponent 2) with v_s = 3 mm/s"),
        CaseSpec(tm, "viscous_friction", {"viscous_n_s_per_m": 2600.0, "viscous_negative_n_s_per_m": 2600.0},
                 ("viscous_friction",), {"friction.viscous_n_s_per_m": 2600.0},
                 {"viscous_friction": "friction.viscous_n_s_per_m"}, "cold grease: viscous 250 -> 2600 N s/m"),
        CaseSpec(tm, "friction_asymmetry", {"coulomb_n": 35.0, "coulomb_negative_n": 85.0}, ("friction_asymmetry",),
                 {"friction.coulomb_n": 35.0, "friction.coulomb_negative_n": 85.0},
                 {"friction_asymmetry": "friction.coulomb_negative_n"},
                 "Coulomb 35 N for +v, 85 N for -v (a tilted or one-sided loaded guide)"),
        CaseSpec(tm, "mass_error", {"table_mass_kg": 350.0}, ("mass_error",), {"mechanics.table_mass_kg": 350.0},
                 {"mass_error": "mechanics.table_mass_kg"}, "+40 % table mass: 100 kg workpiece not in the config"),
        CaseSpec(tm, "axial_compliance", {"axial_stiffness_n_per_m": nom_k / 2}, ("axial_compliance",),
                 {"mechanics.equivalent_torsional_stiffness_nm_per_rad": nom_k / 2 * _r2(),
                  "axial_compliance/stiffness_scale": 0.5},
                 {"axial_compliance": "axial_compliance/stiffness_scale"},
                 "axial stiffness halved at mid-stroke (nut preload lost); it still varies with the nut's distance"
                 " from the fixed bearing (screw E A): 82.7 / 80 / 77.5 MN/m at -50 / 0 / +50 mm"),
        CaseSpec(tm, "resonance", {"resonance_hz": 60.0, "resonance_mass_kg": 30.0, "resonance_damping": 0.025},
                 ("resonance",), {"effects.resonance_frequency_hz": 60.0, "effects.resonance_mass_kg": 30.0,
                                  "effects.resonance_damping_ratio": 0.025},
                 {"resonance": "effects.resonance_frequency_hz"},
                 "a 30 kg part of the 250 kg table (a fixture column) sits on a spring: 60 Hz, damping 2.5 %;"
                 " table_mass_kg stays the total moving mass"),
        CaseSpec(tm, "lead_error", {"lead_error_ppm": 40.0, "lead_error_periodic_m": 1.5e-6,
                                    "lead_error_phase_rad": 0.7}, ("lead_error",),
                 {"effects.lead_error_ppm": 40.0, "effects.lead_error_periodic_m": 1.5e-6,
                  "effects.lead_error_periodic_phase_rad": 0.7}, {"lead_error": "effects.lead_error_ppm"},
                 "cumulative 40 ppm about table 0 and 1.5 um per revolution, A sin(theta + 0.7 rad),"
                 " theta = motor angle (0 at table 0)"),
        CaseSpec(tm, "torque_ripple", {"cogging_nm": 0.3, "cogging_phase_rad": 1.1}, ("torque_ripple",),
                 {"motor.cogging_amplitude_nm": 0.3, "motor.cogging_periods_per_rev": 36.0,
                  "motor.cogging_phase_rad": 1.1}, {"torque_ripple": "motor.cogging_amplitude_nm"},
                 "cogging 0.3 N m (3.75 % of rated), 36 periods per rev, A sin(36 theta + 1.1 rad);"
                 " not in the measured current"),
        CaseSpec(tm, "time_delay", {"dead_time_s": 6e-4}, ("time_delay",), {"sensors.dead_time_s": 6e-4},
                 {"time_delay": "sensors.dead_time_s"},
                 "0.6 ms transmission delay of the motor encoder: the speed loop, the position loop and the recorded"
                 " motor_pos / pos_fb all see the delayed angle; the linear scale is not delayed"),
        CaseSpec(tm, "thermal_drift", {"initial_temperature_rise_k": 3.5, "thermal_resistance_k_per_w": 0.04},
                 ("thermal_drift",), {"effects.initial_temperature_rise_k": 3.5,
                                      "effects.thermal_resistance_k_per_w": 0.04,
                                      "effects.thermal_time_constant_s": 900.0},
                 {"thermal_drift": "effects.initial_temperature_rise_k"},
                 "screw 3.5 K warm at the start of every trace (expands from the fixed bearing, 0.45 m from the nut"
                 " at table 0); friction heating 0.04 K/W with 900 s is negligible over one trace"),
        CaseSpec(tm, "coulomb_friction+viscous_friction",
                 {"coulomb_n": 65.0, "coulomb_negative_n": 65.0, "viscous_n_s_per_m": 2000.0,
                  "viscous_negative_n_s_per_m": 2000.0}, ("coulomb_friction", "viscous_friction"),
                 {"friction.coulomb_n": 65.0, "friction.viscous_n_s_per_m": 2000.0},
                 {"coulomb_friction": "friction.coulomb_n", "viscous_friction": "friction.viscous_n_s_per_m"},
                 "both friction terms larger than the config: 65 N and 2000 N s/m"),
        CaseSpec(tm, "backlash+coulomb_friction", {"gap_m": 8e-6, "coulomb_n": 70.0, "coulomb_negative_n": 70.0},
                 ("backlash", "coulomb_friction"), {"backlash.gap_m": 8e-6, "friction.coulomb_n": 70.0},
                 {"backlash": "backlash.gap_m", "coulomb_friction": "friction.coulomb_n"},
                 "8 um backlash and Coulomb 70 N"),
        CaseSpec(tm, "mass_error+time_delay", {"table_mass_kg": 325.0, "dead_time_s": 4e-4},
                 ("mass_error", "time_delay"), {"mechanics.table_mass_kg": 325.0, "sensors.dead_time_s": 4e-4},
                 {"mass_error": "mechanics.table_mass_kg", "time_delay": "sensors.dead_time_s"},
                 "+30 % table mass and 0.4 ms encoder delay"),
        CaseSpec(tm, "force_offset", {"force_offset_n": 60.0}, ("force_offset",), {"force_offset_n": 60.0},
                 {"force_offset": "force_offset_n"},
                 "constant 60 N against +x (cable chain drag / counterweight imbalance); m a = F - F_fric - offset"),
        CaseSpec(tm, "moving_start", {}, ("moving_start",), {}, {},
                 "every trace starts with the axis already moving (recording starts at the command's first speed"
                 " peak); the true start speeds are in params", moving_start=True),
        # ---- the same ball screw in full closed loop (position loop on the linear scale) ------------------
        CaseSpec(fc, "clean", notes="nominal axis; nothing withheld"),
        CaseSpec(fc, "backlash", {"gap_m": 6e-6}, ("backlash",), {"backlash.gap_m": 6e-6},
                 {"backlash": "backlash.gap_m"}, "6 um backlash inside the position loop (the scale closes it)"),
        CaseSpec(fc, "coulomb_friction", {"coulomb_n": 60.0, "coulomb_negative_n": 60.0}, ("coulomb_friction",),
                 {"friction.coulomb_n": 60.0}, {"coulomb_friction": "friction.coulomb_n"}, "Coulomb 30 -> 60 N"),
        CaseSpec(fc, "mass_error", {"table_mass_kg": 375.0}, ("mass_error",), {"mechanics.table_mass_kg": 375.0},
                 {"mass_error": "mechanics.table_mass_kg"}, "+50 % table mass (heavy workpiece)"),
        CaseSpec(fc, "axial_compliance", {"axial_stiffness_n_per_m": nom_k * 0.6}, ("axial_compliance",),
                 {"mechanics.equivalent_torsional_stiffness_nm_per_rad": nom_k * 0.6 * _r2(),
                  "axial_compliance/stiffness_scale": 0.6},
                 {"axial_compliance": "axial_compliance/stiffness_scale"}, "axial stiffness 60 % of the config's"),
        CaseSpec(fc, "resonance", {"resonance_hz": 75.0, "resonance_mass_kg": 40.0, "resonance_damping": 0.03},
                 ("resonance",), {"effects.resonance_frequency_hz": 75.0, "effects.resonance_mass_kg": 40.0,
                                  "effects.resonance_damping_ratio": 0.03},
                 {"resonance": "effects.resonance_frequency_hz"},
                 "a 40 kg part of the table on a spring: 75 Hz, 3 %; table_mass_kg stays the total"),
        CaseSpec(fc, "time_delay", {"dead_time_s": 1.25e-3}, ("time_delay",), {"sensors.dead_time_s": 1.25e-3},
                 {"time_delay": "sensors.dead_time_s"},
                 "1.25 ms read-out delay of the linear scale (the position loop and the recorded pos_meas see it; the"
                 " speed loop's motor encoder does not)"),
        CaseSpec(fc, "backlash+coulomb_friction", {"gap_m": 10e-6, "coulomb_n": 55.0, "coulomb_negative_n": 55.0},
                 ("backlash", "coulomb_friction"), {"backlash.gap_m": 10e-6, "friction.coulomb_n": 55.0},
                 {"backlash": "backlash.gap_m", "coulomb_friction": "friction.coulomb_n"},
                 "10 um backlash and Coulomb 55 N in full closed loop"),
        # ---- rigid linear-motor axis, P/P cascade at 1 kHz -------------------------------------------------
        CaseSpec(rp, "clean", notes="nominal axis; nothing withheld"),
        CaseSpec(rp, "coulomb_friction", {"coulomb_n": 45.0, "coulomb_negative_n": 45.0}, ("coulomb_friction",),
                 {"friction.coulomb_n": 45.0}, {"coulomb_friction": "friction.coulomb_n"},
                 "cable chain and bellows: Coulomb 25 -> 45 N"),
        CaseSpec(rp, "stribeck_friction", {"stribeck_n": 20.0, "stribeck_velocity_m_s": 0.005},
                 ("stribeck_friction",), {"friction.stribeck_n": 20.0, "friction.stribeck_velocity_m_s": 0.005},
                 {"stribeck_friction": "friction.stribeck_n"}, "20 N Stribeck excess, v_s 5 mm/s, Gaussian"),
        CaseSpec(rp, "viscous_friction", {"viscous_n_s_per_m": 600.0, "viscous_negative_n_s_per_m": 600.0},
                 ("viscous_friction",), {"friction.viscous_n_s_per_m": 600.0},
                 {"viscous_friction": "friction.viscous_n_s_per_m"}, "viscous 150 -> 600 N s/m (seals)"),
        CaseSpec(rp, "friction_asymmetry", {"coulomb_n": 25.0, "coulomb_negative_n": 50.0}, ("friction_asymmetry",),
                 {"friction.coulomb_n": 25.0, "friction.coulomb_negative_n": 50.0},
                 {"friction_asymmetry": "friction.coulomb_negative_n"}, "Coulomb 25 N for +v, 50 N for -v"),
        CaseSpec(rp, "mass_error", {"table_mass_kg": 78.0}, ("mass_error",), {"mechanics.table_mass_kg": 78.0},
                 {"mass_error": "mechanics.table_mass_kg"}, "+30 % moving mass: 18 kg payload"),
        CaseSpec(rp, "resonance", {"resonance_hz": 40.0, "resonance_mass_kg": 15.0, "resonance_damping": 0.02},
                 ("resonance",), {"effects.resonance_frequency_hz": 40.0, "effects.resonance_mass_kg": 15.0,
                                  "effects.resonance_damping_ratio": 0.02},
                 {"resonance": "effects.resonance_frequency_hz"},
                 "a 15 kg part of the 60 kg carriage (a tall fixture) on a spring: 40 Hz, 2 %; table_mass_kg stays"
                 " the total"),
        CaseSpec(rp, "time_delay", {"dead_time_s": 2.5e-3}, ("time_delay",), {"sensors.dead_time_s": 2.5e-3},
                 {"time_delay": "sensors.dead_time_s"},
                 "2.5 ms scale read-out delay: both loops and the recorded pos_meas see the delayed scale"),
        CaseSpec(rp, "coulomb_friction+viscous_friction",
                 {"coulomb_n": 20.0, "coulomb_negative_n": 20.0, "viscous_n_s_per_m": 200.0,
                  "viscous_negative_n_s_per_m": 200.0}, ("coulomb_friction", "viscous_friction"),
                 {"friction.coulomb_n": 20.0, "friction.viscous_n_s_per_m": 200.0},
                 {"coulomb_friction": "friction.coulomb_n", "viscous_friction": "friction.viscous_n_s_per_m"},
                 "the published lab axis' friction (Fc ~ 20 N, Fv ~ 200 N s/m) against a config that has little"
                 " friction (see config: Coulomb 5 N, viscous 20 N s/m)"),
        CaseSpec(rp, "mass_error+time_delay", {"table_mass_kg": 75.0, "dead_time_s": 1.5e-3},
                 ("mass_error", "time_delay"), {"mechanics.table_mass_kg": 75.0, "sensors.dead_time_s": 1.5e-3},
                 {"mass_error": "mechanics.table_mass_kg", "time_delay": "sensors.dead_time_s"},
                 "+25 % mass and 1.5 ms scale delay"),
        CaseSpec(rp, "force_offset", {"force_offset_n": 12.0}, ("force_offset",), {"force_offset_n": 12.0},
                 {"force_offset": "force_offset_n"},
                 "constant 12 N against +x (cable drag, slightly inclined axis); m a = F - F_fric - offset"),
        CaseSpec(rp, "viscous_asymmetry", {"viscous_negative_n_s_per_m": 400.0}, ("viscous_asymmetry",),
                 {"friction.viscous_n_s_per_m": 150.0, "viscous_negative_n_s_per_m": 400.0},
                 {"viscous_asymmetry": "viscous_negative_n_s_per_m"}, "viscous 150 N s/m for +v, 400 for -v"),
        CaseSpec(rp, "moving_start", {}, ("moving_start",), {}, {},
                 "every trace starts with the axis already moving (first speed peak of the command)",
                 moving_start=True),
        CaseSpec(rp, "channel_shift", {}, ("channel_shift",), {"force_drive_shift_samples": 1},
                 {"channel_shift": "force_drive_shift_samples"},
                 "force_drive row k holds the command applied during [t_k, t_k+1) instead of [t_k-1, t_k):"
                 " the force channel leads by one sample", channel_shift=1),
        CaseSpec(rp, "speed_estimator", {"speed_estimator_samples": 2.0}, ("speed_estimator",),
                 {"speed_estimator_samples": 2}, {"speed_estimator": "speed_estimator_samples"},
                 "velocity estimate (q[k] - q[k-2]) / 2T instead of (q[k] - q[k-1]) / T"),
    ]
    return out


SPECS: dict[str, CaseSpec] = {f"{s.structure}/{s.name}": s for s in _specs()}
# the rigid Coulomb + viscous pair runs against a config with little friction (like the published lab axis)
CONFIG_OVERRIDES: dict[str, dict] = {
    "rigid_pp/coulomb_friction+viscous_friction": {"coulomb_n": 5.0, "coulomb_negative_n": 5.0,
                                                   "viscous_n_s_per_m": 20.0, "viscous_negative_n_s_per_m": 20.0},
}


def conditions(structure: str, quick: bool) -> tuple[list[tuple[str, np.ndarray]], list[tuple[str, np.ndarray]]]:
    """(fit, held-out) commands as (stem, 1 kHz position array).

    Fit: sines F1000 and F6000 over the stroke, a jerk-limited point-to-point move there and back, and a rapid
    traverse with 2 ms jerk phases. Held out: sines F2000..F5000 and another point-to-point move; on
    ``rigid_pp`` also a slow move with known +-40 N force pulses (``pulses``, see :func:`external_force`)."""
    s = 0.01 if quick else 0.1  # stroke [m]
    fit = [
        ("sine_F1000", C.sine(1000, s, 1)),
        ("sine_F6000", C.sine(6000, s, 2)),
        ("ptp_fit", C.point_to_point(-0.4 * s, 0.4 * s, 0.1, 1.0, 20.0)),
        ("rapid", C.point_to_point(-0.25 * s, 0.25 * s, 0.25, 3.0, 1500.0, dwell_s=0.3)),
    ]
    hold = [
        ("sine_F2000", C.sine(2000, s, 1)),
        ("sine_F3000", C.sine(3000, s, 1)),
        ("sine_F4000", C.sine(4000, s, 2)),
        ("sine_F5000", C.sine(5000, s, 2)),
        ("ptp_heldout", C.point_to_point(0.3 * s, -0.45 * s, 0.133, 1.5, 40.0, dwell_s=0.3)),
    ]
    if quick:
        hold = [hold[0], hold[2], hold[4]]
    if structure == "rigid_pp":  # a validation run with known force pulses (force_ext), like the lab axis
        hold.append(("pulses", C.point_to_point(-0.2 * s, 0.2 * s, 0.05, 0.5, 10.0, dwell_s=1.0)))
    return fit, hold


def external_force(structure: str, stem: str, n: int) -> np.ndarray | None:
    """Known external force of a condition [N] (recorded as ``force_ext``), or None."""
    if structure == "rigid_pp" and stem == "pulses":
        return C.force_pulses(n, 40.0, 0.06, 0.7, 0.1)
    return None


@dataclass
class CaseFiles:
    """What :func:`make_case` wrote. ``truth``: {"effects", "params", "main_param", "notes"}."""

    name: str
    config_path: Path
    fit: list[Path]
    holdout: list[Path]
    truth: dict


def case_names(structure: str | None = None) -> list[str]:
    """All case names ``"<structure>/<case>"``, optionally of one structure (``two_mass`` / ``rigid_pp``)."""
    if structure is not None and structure not in A.NOMINAL:
        raise ValueError(f"unknown structure {structure!r}; known: {', '.join(A.NOMINAL)}")
    return [n for n, s in SPECS.items() if structure is None or s.structure == structure]


def _write_csv(path: Path, cols: dict[str, np.ndarray]) -> None:
    names = list(cols)
    data = np.column_stack([cols[n] for n in names])
    fmt = ["%.6f"] + ["%.12g"] * (len(names) - 1)
    np.savetxt(path, data, delimiter=",", header=",".join(names), comments="", fmt=fmt)


def _moving_start_index(x: np.ndarray) -> int:
    v = np.abs(np.diff(x))
    half = len(v) // 2
    return int(np.argmax(v[:half])) + 1


def make_case(name: str, out_dir: Path, seed: int = 0, quick: bool = False) -> CaseFiles:
    """Generate case ``name`` into ``out_dir``: ``config.toml`` (nominal, the withheld effects not in it),
    ``fit_<stem>.csv``, ``heldout_<stem>.csv`` and ``truth.json``. ``seed`` sets the sensor noise;
    ``quick``: 10 mm stroke and three held-out traces (tests)."""
    if name not in SPECS:
        raise KeyError(f"unknown reference case {name!r}; known: {', '.join(SPECS)}")
    spec = SPECS[name]
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    nominal = dict(A.NOMINAL[spec.structure])
    nominal.update(CONFIG_OVERRIDES.get(name, {}))
    truth_phys = dict(A.NOMINAL[spec.structure])
    truth_phys.update(spec.truth)
    header = (f"Reference axis case {name} (virtualaxis.refaxis), nominal config: the withheld effect(s)"
              f" {', '.join(spec.effects) or '(none)'} are NOT in this file.\nWritten apart from the diagnosed model;"
              " see docs/refaxis.md.")
    cfg_path = out_dir / "config.toml"
    cfg_path.write_text(A.config_toml(spec.structure, nominal, name.replace("/", "-"), header), encoding="utf-8")
    fit_cmds, hold_cmds = conditions(spec.structure, quick)
    fit_paths: list[Path] = []
    hold_paths: list[Path] = []
    start_speeds: dict[str, float] = {}
    for kind, cmds, paths in (("fit", fit_cmds, fit_paths), ("heldout", hold_cmds, hold_paths)):
        for stem, x in cmds:
            rec = _moving_start_index(x) if spec.moving_start else 0
            cols = simulate(spec.structure, truth_phys, x, noise_seed(name, seed, kind, stem),
                            record_from=rec, channel_shift=spec.channel_shift,
                            f_ext=external_force(spec.structure, stem, len(x)))
            if spec.moving_start:
                start_speeds[f"{kind}_{stem}"] = float((x[rec] - x[rec - 1]) / truth_phys["position_cycle_s"])
            path = out_dir / f"{kind}_{stem}.csv"
            _write_csv(path, cols)
            paths.append(path)
    params = dict(spec.params)
    main = dict(spec.main_param)
    if spec.moving_start:
        vmax = max(start_speeds.values(), key=abs)
        params["moving_start/start_velocity_m_s"] = vmax
        main["moving_start"] = "moving_start/start_velocity_m_s"
    truth = {"effects": list(spec.effects), "params": params, "main_param": main, "notes": spec.notes,
             "structure": spec.structure, "seed": seed, "quick": quick}
    if spec.moving_start:
        truth["start_velocity_per_trace_m_s"] = start_speeds
    (out_dir / "truth.json").write_text(json.dumps(truth, indent=2), encoding="utf-8")
    return CaseFiles(name=name, config_path=cfg_path, fit=fit_paths, holdout=hold_paths, truth=truth)


def write_axis_case(out_dir: Path, structure: str, truth: dict, config: dict, fit: list[tuple[str, np.ndarray]],
                    holdout: list[tuple[str, np.ndarray]], seed: int = 0, name: str = "axis") -> CaseFiles:
    """Write an axis outside the case list: ``config.toml`` from the physical parameters ``config`` (the nominal a
    user states) and ``fit_<stem>.csv`` / ``heldout_<stem>.csv`` simulated with ``truth`` (both: overrides on the
    structure's nominal parameters, ``axes.NOMINAL``) on the (stem, 1 kHz position) commands. ``truth.json`` lists
    the truth's physical parameters."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    truth_phys = {**A.NOMINAL[structure], **truth}
    config_phys = {**A.NOMINAL[structure], **config}
    cfg_path = out_dir / "config.toml"
    cfg_path.write_text(A.config_toml(structure, config_phys, name, f"Reference axis {name} (virtualaxis.refaxis)"),
                        encoding="utf-8")
    paths: dict[str, list[Path]] = {"fit": [], "heldout": []}
    for kind, cmds in (("fit", fit), ("heldout", holdout)):
        for stem, x in cmds:
            cols = simulate(structure, truth_phys, x, noise_seed(name, seed, kind, stem))
            path = out_dir / f"{kind}_{stem}.csv"
            _write_csv(path, cols)
            paths[kind].append(path)
    record = {"structure": structure, "truth": truth_phys, "config": config_phys, "seed": seed}
    (out_dir / "truth.json").write_text(json.dumps(record, indent=2), encoding="utf-8")
    return CaseFiles(name=name, config_path=cfg_path, fit=paths["fit"], holdout=paths["heldout"], truth=record)
