"""Plausibility of measured traces before any fit: the diagnosis must never conclude on data that cannot be right.

:func:`check_plausibility` runs once, after the traces are read and their units checked
(:func:`virtualaxis.diagnosis.trace.check_units`). It raises
:class:`~virtualaxis.config.errors.InputError` (naming file, row and column) for data that would make any
conclusion meaningless, and returns warnings (prefixed ``plausibility:``) for findings a person should look at:

- **time unit**: the sample interval must be one a drive records at (``trace.DT_RANGE_S``); a trace with
  ``t`` in milliseconds written as seconds has a 1 s interval and is refused. An interval far from the
  config's position cycle is a warning.
- **sign and scale of each channel against the command**: position channels must follow ``pos_cmd`` (delayed
  by up to five closed-loop time constants, the servo's lag) with a positive correlation (a sign-flipped channel
  is refused) and a slope near 1 (else a warning; a mm-for-m channel is already refused by the unit checks),
  ``vel_meas`` the command's derivative likewise, and the drive effort (``torque_meas``, ``current_q``,
  ``force_drive``) must push the way the command accelerates, with an inertia near the config's (a factor
  beyond :data:`EFFORT_SCALE_RANGE` warns).
- **the same data twice**: two inputs with the same content (SHA-256 of the parsed samples) are refused; a
  held-out trace identical to a fit trace would judge the fit on its own data.
- **absurd magnitudes**: an external or drive force beyond :data:`FORCE_FACTOR` times the axis' peak drive
  force (``force_ext = 1e300``) is refused.
- **the model's travel**: a commanded or measured position beyond the model's hard end stops
  (``+-(axis.stroke_m / 2 + over-travel)``), or one that puts a ball-screw nut off its screw, is refused naming
  the config key to change; beyond ``+-axis.stroke_m / 2`` but inside the end stops is a warning.

:func:`check_baseline` runs after the nominal model is simulated on every trace and before any effect is
fitted: a nominal model that does not follow the measured motion at all (its position misses the measurement
by far more than the measured following error and by a visible share of the move) leaves a gap no effect of
the library reaches, and is refused with the numbers in engineering units and what to check in the config.
"""

from __future__ import annotations

import hashlib
import math

import numpy as np

from virtualaxis.config.errors import InputError
from virtualaxis.diagnosis.trace import DT_RANGE_S, check_sample_interval  # noqa: F401 (DT_RANGE_S: documented)

#: accepted regression slope of a position channel on pos_cmd (servo tracking is within a few % in amplitude)
POSITION_SLOPE_RANGE = (0.7, 1.4)
#: accepted slope of vel_meas on the command's derivative
VELOCITY_SLOPE_RANGE = (0.5, 2.0)
#: the effort's inertia term vs the config's inertia: beyond this factor it is a unit or scale warning
EFFORT_SCALE_RANGE = (0.2, 5.0)
#: an external or drive force beyond this multiple of the peak drive force is not a measurement
FORCE_FACTOR = 20.0
PREFIX = "plausibility: "


def _slope(x: np.ndarray, y: np.ndarray) -> float:
    """Least-squares slope of y on x (both de-meaned)."""
    xc = x - x.mean()
    den = float(np.dot(xc, xc))
    return float(np.dot(xc, y - y.mean())) / den if den > 0 else math.nan


def content_hash(trace) -> str:
    """SHA-256 of a trace's samples (time and every column, in a fixed order)."""
    h = hashlib.sha256()
    h.update(np.ascontiguousarray(trace.t, dtype=float).tobytes())
    for name in sorted(trace.columns):
        h.update(name.encode())
        h.update(np.ascontiguousarray(trace.columns[name], dtype=float).tobytes())
    return h.hexdigest()


def peak_drive_force_n(cfg) -> float:
    """The largest force the drive can put on the table [N] (peak current through the screw, or the force
    actuator's limit); a fallback of 1e5 N where the config gives neither."""
    if cfg.actuator.kind == "force":
        return cfg.actuator.force_limit_n or 1e5
    m = cfg.motor
    i_peak = cfg.control.current_limit_a or 3.0 * m.rated_current_a
    lead = cfg.mechanics.lead_m
    return m.kt_nm_per_a * i_peak * 2 * math.pi / lead if lead > 0 else 1e5


def _inertia_per_acc(cfg, channel: str) -> float | None:
    """Expected effort per table acceleration for ``channel`` [N, N m or A per m/s^2]."""
    mech = cfg.mechanics
    mass = mech.table_mass_kg + mech.nut_mass_kg
    lead = mech.lead_m
    if cfg.actuator.kind == "pmsm" and lead > 0:
        r = lead / (2 * math.pi)
        j = mech.motor_inertia_kg_m2 + mech.coupling_inertia_kg_m2 + mech.screw_end_inertia_kg_m2
        screw = mech.screw_density_kg_m3 * math.pi * (mech.screw_root_diameter_m / 2) ** 4 / 2 * mech.screw_length_m
        m_eq = mass + (j + screw) / r**2
        torque = m_eq * r
        if channel == "torque_meas":
            return torque
        if channel == "current_q":
            kt = cfg.motor.kt_nm_per_a
            return torque / kt if kt > 0 else None
        if channel == "force_drive":
            return m_eq
        return None
    return mass if channel == "force_drive" else None


def _check_time(tr, cfg, warnings: list[str]) -> None:
    dt = tr.dt_s
    check_sample_interval(tr.path, dt)  # also done on reading, before the unit checks
    cyc = cfg.control.position_cycle_s
    if not 0.01 <= dt / cyc <= 100:
        warnings.append(f"{PREFIX}{tr.name}: sample interval {dt:g} s is {dt / cyc:.3g} x the config's position "
                        f"cycle {cyc:g} s: check the time unit of column t")


def _lagged_fit(ref: np.ndarray, x: np.ndarray, max_lag: int) -> tuple[float, float, float, float]:
    """Correlation of ``x`` with ``ref`` delayed by 0..max_lag samples: (best positive correlation, the slope of x
    on the delayed ref there, most negative correlation, the slope there). A servo channel follows its command
    with a lag; judging it at lag 0 would call a lagging channel mis-scaled."""
    n = x.size
    step = max(1, max_lag // 60)
    best = (-2.0, math.nan, 2.0, math.nan)
    for lag in range(0, min(max_lag, n // 2) + 1, step):
        r = ref[: n - lag] - ref[: n - lag].mean()
        y = x[lag:] - x[lag:].mean()
        den = math.sqrt(float(np.dot(r, r)) * float(np.dot(y, y)))
        if den <= 0:
            continue
        c = float(np.dot(r, y)) / den
        k = float(np.dot(r, y)) / float(np.dot(r, r))
        if c > best[0]:
            best = (c, k, best[2], best[3])
        if c < best[2]:
            best = (best[0], best[1], c, k)
    return best


def _max_lag_samples(tr, cfg) -> int:
    """Lags searched: up to five closed-loop time constants 1/kv (at least 0.2 s), at most a quarter trace."""
    kv = cfg.control.kv_1_per_s
    lag_s = max(0.2, 5.0 / kv) if kv > 0 else 0.5
    return max(1, min(int(lag_s / tr.dt_s), tr.t.size // 4))


def _check_positions(tr, cfg, warnings: list[str]) -> None:
    cmd = tr.pos_cmd
    if float(np.ptp(cmd)) <= 0:
        return
    max_lag = _max_lag_samples(tr, cfg)
    for col in ("pos_meas", "pos_fb"):
        x = tr.columns.get(col)
        if x is None:
            continue
        c_pos, k_pos, c_neg, k_neg = _lagged_fit(cmd, x, max_lag)
        if c_neg < -0.8 and c_pos < 0.5:
            raise InputError(tr.path, f"moves against pos_cmd (correlation {c_neg:.2f}, slope {k_neg:.3g}; expected "
                                      "about +1): a sign-flipped channel or encoder direction", None, col)
        lo, hi = POSITION_SLOPE_RANGE
        if c_pos > 0.8 and not lo <= k_pos <= hi:
            warnings.append(f"{PREFIX}{tr.name}: {col} follows pos_cmd with slope {k_pos:.3g} at its best lag "
                            f"(expected {lo:g} .. {hi:g}): check its scale and unit")


def _check_velocity(tr, cfg, warnings: list[str]) -> None:
    vel = tr.columns.get("vel_meas")
    if vel is None or tr.t.size < 3:
        return
    v_cmd = np.gradient(tr.pos_cmd, tr.t)
    if float(np.std(v_cmd)) <= 0:
        return
    c_pos, k_pos, c_neg, k_neg = _lagged_fit(v_cmd, vel, _max_lag_samples(tr, cfg))
    if c_neg < -0.8 and c_pos < 0.5:
        raise InputError(tr.path, f"runs against the command's velocity (correlation {c_neg:.2f}; expected about "
                                  "+1): sign-flipped", None, "vel_meas")
    lo, hi = VELOCITY_SLOPE_RANGE
    if c_pos > 0.8 and not lo <= k_pos <= hi:
        warnings.append(f"{PREFIX}{tr.name}: vel_meas follows the command's velocity with slope {k_pos:.3g} "
                        f"(expected {lo:g} .. {hi:g}): check its unit (m/s)")


def _measured_motion(tr, cfg) -> tuple[np.ndarray, np.ndarray] | None:
    """Velocity and acceleration of the table from the measured position (Savitzky-Golay, cubic, ~20 ms window
    against quantisation and noise), or None without a position channel. The effort answers the motion that
    happened, not the command: a loose loop lags its command by more than the effort's own dynamics."""
    from scipy.signal import savgol_filter

    x = tr.columns.get("pos_meas", tr.columns.get("pos_fb"))
    if x is None and "motor_pos" in tr.columns and cfg.mechanics.lead_m > 0:
        x = tr.columns["motor_pos"] * cfg.mechanics.lead_m / (2 * math.pi)
    if x is None:
        return None
    w = int(round(0.02 / tr.dt_s)) | 1
    w = min(max(w, 7), (x.size // 2) | 1 if (x.size // 2) % 2 else x.size // 2 - 1)
    if w < 5:
        return None
    v = savgol_filter(x, w, 3, deriv=1, delta=tr.dt_s, mode="interp")
    a = savgol_filter(x, w, 3, deriv=2, delta=tr.dt_s, mode="interp")
    return v, a


def _check_efforts(tr, cfg, warnings: list[str]) -> None:
    """Effort = c_a * a + c_c * sign(v) + c_v * v + c_0 on the measured motion: the inertia term c_a must be
    positive and near the config's inertia where the inertia is a visible part of the effort."""
    if tr.t.size < 16:
        return
    motion = _measured_motion(tr, cfg)
    if motion is None:
        return
    v, a = motion
    if float(np.std(a)) <= 0:
        return
    reg = np.column_stack([a, np.sign(v), v, np.ones_like(v)])
    for col in ("torque_meas", "current_q", "force_drive"):
        y = tr.columns.get(col)
        if y is None:
            continue
        coef, *_ = np.linalg.lstsq(reg, y, rcond=None)
        resid = y - reg @ coef
        # standard error of the inertia coefficient
        dof = max(y.size - reg.shape[1], 1)
        cov = np.linalg.pinv(reg.T @ reg) * float(np.dot(resid, resid)) / dof
        se = math.sqrt(max(float(cov[0, 0]), 0.0))
        c_a = float(coef[0])
        expected = _inertia_per_acc(cfg, col)
        if not expected or not c_a**2 > 25 * se**2:
            continue  # no inertia figure for this channel, or the inertia term is not determined
        # judged only where the inertia the config gives is a visible part of the effort (friction-dominated
        # slow moves say little about the sign of the inertia term)
        if expected * float(np.std(a)) < 0.2 * float(np.std(y)):
            continue
        if c_a < 0 and abs(c_a) > 0.5 * expected:
            raise InputError(tr.path, f"pushes against the command's acceleration (inertia term {c_a:.3g} per "
                                      f"m/s^2, the config gives {expected:.3g}): sign-flipped", None, col)
        ratio = c_a / expected
        lo, hi = EFFORT_SCALE_RANGE
        if not lo <= ratio <= hi:
            warnings.append(f"{PREFIX}{tr.name}: {col} has {ratio:.3g} x the inertia the config gives (expected "
                            f"{lo:g} .. {hi:g} x): check its unit and scale")


def _check_magnitudes(tr, cfg) -> None:
    f_peak = peak_drive_force_n(cfg)
    for col in ("force_ext", "force_drive"):
        x = tr.columns.get(col)
        if x is None:
            continue
        bad = np.abs(x) > FORCE_FACTOR * f_peak
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise InputError(tr.path, f"force {float(x[i]):g} N is over {FORCE_FACTOR:g} x the axis' peak drive force "
                                      f"{f_peak:.4g} N: not a measurement (unit?)", i + 2, col)


def _check_motion(tr) -> None:
    """A command that never moves carries no dynamics to diagnose (every effect is unidentifiable; it crashed the
    plots before): refused, naming the column."""
    x = tr.columns["pos_cmd"]
    if x.size and float(np.max(x) - np.min(x)) == 0.0:
        raise InputError(tr.path, f"the command does not move (constant {float(x[0]):g} m over {x.size} rows): "
                                  "nothing to diagnose; give traces of moves", None, "pos_cmd")


def _check_duplicates(traces, n_fit: int | None) -> None:
    seen: dict[str, int] = {}
    for i, tr in enumerate(traces):
        h = content_hash(tr)
        if h in seen:
            j = seen[h]
            roles = ""
            if n_fit is not None:
                roles = f" ({'fit' if j < n_fit else 'held-out'} and {'fit' if i < n_fit else 'held-out'})"
            raise InputError(tr.path, f"has the same content as {traces[j].path}{roles} (SHA-256 {h[:12]}); each "
                                      "trace must be given once, and held-out data must differ from the fit data")
        seen[h] = i


def _mm(x_m: float) -> str:
    return f"{1e3 * x_m:.4g} mm"


def _check_travel(tr, cfg, warnings: list[str]) -> None:
    """Positions the model's table can reach: inside its end stops (and, on a ball screw, with the nut on the
    screw). Table position 0 is the middle of the stroke in the model."""
    from virtualaxis.sim.simulator import end_stop_overtravel_m, end_stops

    lo, hi = end_stops(cfg)[:2]
    half = cfg.axis.stroke_m / 2
    over = end_stop_overtravel_m(cfg)
    screw = cfg.mechanics.model != "rigid" and cfg.mechanics.lead_m > 0 and cfg.mechanics.screw_length_m > 0
    worst: tuple[float, str, int, float] | None = None  # (how far past the stroke end, column, row, value)
    for col in ("pos_cmd", "pos_meas", "pos_fb"):
        x = tr.columns.get(col)
        if x is None or not x.size:
            continue
        i = int(np.argmax(np.abs(x)))
        v = float(x[i])
        if worst is None or abs(v) - half > worst[0]:
            worst = (abs(v) - half, col, i, v)
        if not lo <= v <= hi:
            need = 2 * (abs(v) + 1e-3)
            raise InputError(
                tr.path, f"the table reaches {v:+.4g} m (row {i + 2}) but the nominal model's end stops sit at "
                f"{lo:+.4g} / {hi:+.4g} m (axis.stroke_m {cfg.axis.stroke_m:g} m / 2 + {_mm(over)} over-travel; "
                "table position 0 is the middle of the stroke): the model cannot follow this trace. Set "
                f"axis.stroke_m to the axis' real travel (at least {need:.4g} m for this trace), or give the "
                "trace's positions relative to the middle of the stroke", i + 2, col)
        if screw:
            nut = cfg.axis.nut_offset_m + v
            if not 0.0 <= nut <= cfg.mechanics.screw_length_m:
                raise InputError(
                    tr.path, f"the table reaches {v:+.4g} m (row {i + 2}), which puts the nut at {nut:.4g} m from "
                    f"the fixed bearing, off the screw (mechanics.screw_length_m {cfg.mechanics.screw_length_m:g} m, "
                    f"axis.nut_offset_m {cfg.axis.nut_offset_m:g} m): the model cannot follow this trace. Check "
                    "axis.nut_offset_m, mechanics.screw_length_m and the trace's position origin", i + 2, col)
    if worst is not None and worst[0] > 1e-3 + 0.01 * half:
        warnings.append(f"{PREFIX}{tr.name}: {worst[1]} reaches {worst[3]:+.4g} m (row {worst[2] + 2}), "
                        f"{_mm(worst[0])} beyond the usable stroke +-{half:.4g} m (axis.stroke_m): inside the "
                        "model's end stops, but check the config's stroke and the trace's position origin")


#: the nominal model does not follow the measured motion when its position misses the measurement by more than
#: this multiple of the measured following error (the model's residual is the difference of two following
#: errors, so a model that follows the same command stays of that order whatever plant effect it lacks) ...
BASELINE_FOLLOWING_FACTOR = 5.0
#: ... and by more than this share of the commanded move (peak to peak): far beyond any effect of the library
#: (backlash, lead error, thermal growth: tens of micrometres)
BASELINE_MOTION_SHARE = 0.05


def _rms(x: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(x)))) if x.size else 0.0


def _position_channels(cfg, td, pred: dict) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """(channel, measured, model) in metres of the table for every position channel both have."""
    out = []
    for ch in ("pos_meas", "pos_fb", "motor_pos"):
        if ch not in td.measured or ch not in pred:
            continue
        scale = 1.0
        if ch == "motor_pos":
            if cfg.mechanics.lead_m <= 0:
                continue
            scale = cfg.mechanics.lead_m / (2 * math.pi)
        out.append((ch, np.asarray(td.measured[ch]) * scale, np.asarray(pred[ch]) * scale))
    return out


def _channel_gap(ch: str, rms: float) -> str:
    from virtualaxis.diagnosis.trace import CHANNEL_UNITS

    unit = CHANNEL_UNITS.get(ch, "")
    if unit == "m":
        return f"{ch} {_mm(rms)} RMS"
    return f"{ch} {rms:.4g} {unit} RMS".replace("  ", " ")


#: the model's drive effort counts as saturated when it sits within this share of its limit ...
SATURATION_LEVEL = 0.98
#: ... for at least this share of the samples
SATURATION_SHARE = 0.2


def _saturation(cfg, td, pred: dict, n: int) -> str:
    """Why the model cannot follow when its drive sits at its limit: the limit, its config key and how long."""
    if cfg.actuator.kind == "force":
        ch, limit, key, unit = "force_drive", cfg.actuator.force_limit_n, "actuator.force_limit_n", "N"
    else:
        ch, limit, unit = "current_q", cfg.control.current_limit_a or 3.0 * cfg.motor.rated_current_a, "A"
        key = "control.current_limit_a" if cfg.control.current_limit_a else "control.current_limit_a (0: 3 x rated)"
    x = pred.get(ch)
    if x is None or not limit or limit <= 0:
        return ""
    share = float(np.mean(np.abs(np.asarray(x)[:n]) >= SATURATION_LEVEL * limit))
    if share < SATURATION_SHARE:
        return ""
    meas = td.measured.get(ch)
    peak = f", the measured {ch} peaks at {float(np.max(np.abs(meas))):.4g} {unit}" if meas is not None else ""
    return (f"The model's drive sits at its limit {key} = {limit:.4g} {unit} for {100 * share:.0f} % of the "
            f"trace{peak}: set it to the drive's real limit")


def check_baseline(cfg, tds: list, preds: list[dict]) -> None:
    """Refuse to diagnose when the nominal model cannot follow the measured motion (see the module doc):
    raises InputError naming the config, the trace, the gap in engineering units and what to check."""
    from virtualaxis.sim.simulator import end_stops

    lo, hi = end_stops(cfg)[:2]
    for td, pred in zip(tds, preds, strict=True):
        cmd = np.asarray(td.pos_cmd)
        move = float(np.ptp(cmd)) if cmd.size else 0.0
        for ch, meas, model in _position_channels(cfg, td, pred):
            n = min(meas.size, model.size, cmd.size)
            gap = _rms(meas[:n] - model[:n])
            fe_meas = _rms(cmd[:n] - meas[:n])
            if not (gap > BASELINE_FOLLOWING_FACTOR * fe_meas and gap > BASELINE_MOTION_SHARE * move):
                continue
            fe_model = _rms(cmd[:n] - model[:n])
            others = [_channel_gap(c, _rms(np.asarray(td.measured[c]) - np.asarray(pred[c])))
                      for c in sorted(td.measured) if c in pred and c != ch
                      and np.size(pred[c]) == np.size(td.measured[c])]
            reach = (float(np.min(model[:n])), float(np.max(model[:n])))
            causes = []
            if reach[1] >= hi - 0.01 * (hi - lo) or reach[0] <= lo + 0.01 * (hi - lo):
                causes.append(f"the model's table stops at its end stop ({lo:+.4g} / {hi:+.4g} m: axis.stroke_m "
                              f"{cfg.axis.stroke_m:g} m / 2 + over-travel) while the command goes to "
                              f"{float(np.min(cmd)):+.4g} .. {float(np.max(cmd)):+.4g} m: set axis.stroke_m to the "
                              "axis' real travel")
            else:
                sat = _saturation(cfg, td, pred, n)
                if sat:
                    causes.append(sat)
                causes.append("Check the config's units and sizes that set whether the axis can follow this "
                              "command at all: axis.stroke_m, the masses ([mechanics]), the drive's force or "
                              "current limit ([actuator] / [control]) and the control gains ([control])")
            raise InputError(
                cfg.path or "config",
                f"{td.name}: the nominal model does not follow the measured motion, so no effect can be diagnosed: "
                f"its {ch} misses the measurement by {_mm(gap)} RMS over a {_mm(move)} move, while the measured "
                f"following error is {_mm(fe_meas)} RMS and the model's own {_mm(fe_model)} RMS (the model's table "
                + (f"stays at {reach[0]:+.4g} m" if reach[1] - reach[0] < 0.01 * max(move, 1e-12) else
                   f"moves {reach[0]:+.4g} .. {reach[1]:+.4g} m, the command {float(np.min(cmd)):+.4g} .. "
                   f"{float(np.max(cmd)):+.4g} m") + ")"
                + (f"; also {', '.join(others)}" if others else "") + f". {'. '.join(causes)}")


def check_plausibility(cfg, traces: list, fit_paths: list[str], holdout_paths: list[str]) -> list[str]:
    """Run every check on every trace (see the module doc). Returns warnings; raises InputError to stop."""
    warnings: list[str] = []
    for tr in traces:
        _check_motion(tr)
        _check_travel(tr, cfg, warnings)
        _check_time(tr, cfg, warnings)
        _check_magnitudes(tr, cfg)
        _check_positions(tr, cfg, warnings)
        _check_velocity(tr, cfg, warnings)
        _check_efforts(tr, cfg, warnings)
    _check_duplicates(traces, len(fit_paths) if holdout_paths else None)
    return warnings
