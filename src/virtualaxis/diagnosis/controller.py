"""Is the trace's controller the one the config describes? Replay the control law on the measured signals.

A controller maps measured signals to its output: the command, the position feedback and the speed
measured from it go in, a force or torque comes out. That law needs no plant model, so it can be checked
(and, when the config's is wrong, identified) from a trace alone, before anything is simulated. Without
this check an axis run by another controller than the config's — another vendor's P/P cascade, other gains
— shows the controller difference as a "gap", and the diagnosis would blame a plant effect for it.

The law replayed is the config's cascade (`virtualaxis.control`, the compiled kernel) sampled at the trace's
rate: at sample ``k`` the output is the speed controller's answer to the set-point of the previous
position-loop sample::

    r_k = g (Kv e_{k-1} + Kff vc_{k-1})                speed set-point [rad/s at the motor, or m/s]
    u_k = Kp (r_k - w_end_k) + Ki sum_{i<=k} (r_i - w_i) dt + Kt g ac_{k-1} + b

``e`` following error [m] (command - position feedback), ``vc``/``ac`` command velocity/acceleration,
``w_k`` the speed over the last sample (motor angle difference for a motor, feedback position for a force
actuator; its sum is the distance travelled, exact for the integral term), ``w_end_k`` the speed at the end of
that sample (second-order backward difference: what a speed loop much faster than the trace last acted on);
for a speed loop sampled at the trace's rate both are the speed over the sample before, ``w_{k-1}``.
Both sides are averaged over :data:`SMOOTH_S` (linear law: the average keeps it exact).
``g`` the gear factor (2 pi / lead [rad/m], 1 for a force actuator), ``u`` motor torque [N m]
or drive force [N], ``b`` the integrator's unknown initial state. ``Kp``: ``control.speed_kp_nm_s_per_rad``
or ``velocity_kp_n_s_per_m``; ``Ki = Kp / speed_ti_s`` (0 for a P speed loop); ``Kt = torque_ff_factor x
J_ref``. The check reports the share of the output's variance each law leaves unexplained; the identified
gains replace the config's for that trace only when the config's law leaves a clearly larger share
(:data:`SWITCH_RATIO`, :data:`SWITCH_MIN_UNEXPLAINED`), and the check says it is inconclusive where the speed
loop is far faster than the trace (:data:`MAX_BLUR`). It is meant to tell "other controller" from "same
controller" and recover a P/P(I) cascade's gains and speed-loop timing, not to replace a controller's
documentation.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from virtualaxis.config import AxisConfig
from virtualaxis.plant.mechanics import feedforward_inertia

#: use the identified law only if the config's leaves this many times its unexplained share ...
SWITCH_RATIO = 3.0
#: ... and at least this share of the controller output's variance unexplained
SWITCH_MIN_UNEXPLAINED = 0.05
#: warn (without switching) when the config's law leaves this share unexplained; an identified law must
#: leave less than this to be used
WARN_UNEXPLAINED = 0.2
#: the check is inconclusive when the P term's dependence on the instant the speed is taken within one sample
#: exceeds this share of the output's spread
MAX_BLUR = 0.3


@dataclass
class ControllerCheck:
    """Result for one trace (``report.json["controller_check"]``)."""

    trace: str
    channel: str
    unexplained_config: float  # share of var(u) the config's law leaves
    unexplained_identified: float  # share the identified law leaves
    config_gains: dict[str, float]
    identified_gains: dict[str, float]
    used: str  # "config" | "identified"
    overrides: dict = field(default_factory=dict)  # control.* keys used for this trace when "identified"
    note: str = ""
    resolution: float = 0.0  # P-term blur within one sample / spread of the output (<= MAX_BLUR: conclusive)
    confirm_ratio: float | None = None  # nominal residual with the identified / with the config's controller

    def as_dict(self) -> dict:
        return {"trace": self.trace, "channel": self.channel, "unexplained_config": self.unexplained_config,
                "unexplained_identified": self.unexplained_identified, "config_gains": self.config_gains,
                "identified_gains": self.identified_gains, "used": self.used,
                "overrides": self.overrides.get("control", {}), "resolution": self.resolution,
                "confirm_ratio": self.confirm_ratio,
                "note": self.note}


def _gear_and_output(cfg: AxisConfig, cols: dict[str, np.ndarray]) -> tuple[float, str, np.ndarray] | None:
    """Gear factor g [rad/m or 1], output channel name and output [N m or N]; None without an output channel."""
    if cfg.actuator.kind == "force":
        for ch in ("force_drive", "torque_meas"):
            if ch in cols:
                return 1.0, ch, cols[ch]
        return None
    lead = cfg.mechanics.lead_m
    if lead <= 0:
        return None
    g = 2 * math.pi / lead
    if "torque_meas" in cols:
        return g, "torque_meas", cols["torque_meas"]
    if "force_drive" in cols:  # the drive force at the table: torque through the lead
        return g, "force_drive", cols["force_drive"] / g
    if "current_q" in cols:
        return g, "current_q", cols["current_q"] * cfg.motor.kt_nm_per_a
    return None


def _feedback(cfg: AxisConfig, cols: dict[str, np.ndarray], g: float) -> tuple[np.ndarray, np.ndarray] | None:
    """(position feedback at the table [m], speed-loop coordinate [rad or m]) as the controller saw them."""
    motor = cfg.actuator.kind != "force"
    lead_ok = cfg.mechanics.lead_m > 0
    scale = cols.get("pos_meas")
    if lead_ok and "motor_pos" in cols:
        enc = cols.get("pos_fb", cols["motor_pos"] / g)
    else:
        enc = cols.get("pos_fb")
    fb = scale if cfg.control.position_feedback == "linear_scale" or not lead_ok else enc
    if fb is None:
        fb = scale if scale is not None else enc
    if fb is None:
        return None
    if motor:
        coord = cols["motor_pos"] if "motor_pos" in cols else (enc if enc is not None else fb) * g
    else:
        coord = fb if not lead_ok or enc is None else enc
    return fb, coord


def _config_gains(cfg: AxisConfig) -> dict[str, float]:
    c = cfg.control
    kp = c.velocity_kp_n_s_per_m if cfg.actuator.kind == "force" else c.speed_kp_nm_s_per_rad
    jref = feedforward_inertia(cfg)
    return {"kp": kp, "ti_s": c.speed_ti_s, "kv_per_s": c.kv_1_per_s, "velocity_ff": c.velocity_ff_factor,
            "torque_ff_x_jref": c.torque_ff_factor * jref, "jref": jref}


@dataclass
class _Signals:
    u: np.ndarray  # output at samples 1..n-1
    e: np.ndarray  # g e_{k-1}
    vc: np.ndarray  # g vc_{k-1}
    w: np.ndarray  # w_k: mean speed over the last sample (its sum is the angle travelled: the integral term)
    w_end: np.ndarray  # speed at the end of the last sample (what the speed loop's P term last acted on)
    ac: np.ndarray  # g ac_{k-1}
    dt: float


#: both sides of the law are averaged over this window [s] before comparing: the output sampled at one instant
#: carries the speed loop's quantisation chatter (an encoder count per speed-loop cycle), which the law at the
#: trace's rate cannot replay; the law is linear, so the same moving average on both sides keeps it exact
SMOOTH_S = 0.01


def _smoothed(sig: _Signals, n: int) -> _Signals:
    if n <= 1:
        return sig
    k = np.ones(n) / n

    def f(x):
        return np.convolve(x, k, mode="valid")

    return _Signals(u=f(sig.u), e=f(sig.e), vc=f(sig.vc), w=f(sig.w), w_end=f(sig.w_end), ac=f(sig.ac), dt=sig.dt)


def _sampled_signals(cfg: AxisConfig, u: np.ndarray, e: np.ndarray, vc: np.ndarray, ac: np.ndarray, w: np.ndarray,
                     dt: float) -> _Signals:
    """The law's signals for a speed loop sampled at the trace's rate, with the config's timing: row k holds the
    output applied during [t_k-1, t_k), computed from the samples at t_k-1-d (d = ``control.output_delay_s`` in
    samples) with the speed estimate ``control.speed_estimator`` at that sample (one-sample difference
    w[k-2-d] = (x_k-1-d - x_k-2-d) / T, or the two-sample difference, the mean of w[k-2-d] and w[k-3-d])."""
    c = cfg.control
    delay = int(round(c.output_delay_s / dt)) if c.speed_cycle_s >= 0.99 * dt else 0
    lag = 1 + delay
    two = c.speed_estimator == "two_sample_difference"
    k = np.arange(lag + 1 + (1 if two else 0), u.size)
    wk = 0.5 * (w[k - 1 - lag] + w[k - 2 - lag]) if two else w[k - 1 - lag]
    return _Signals(u=u[k], e=e[k - lag], vc=vc[k - lag], w=wk, w_end=wk, ac=ac[k - lag], dt=dt)


def _law_columns(sig: _Signals, kv: float, kff: float) -> tuple[np.ndarray, np.ndarray]:
    """The columns the law multiplies by Kp and by Ki, given (Kv, Kff): r - w_end and sum(r - w) dt."""
    ref = kv * sig.e + kff * sig.vc
    return ref - sig.w_end, np.cumsum(ref - sig.w) * sig.dt


def _unexplained(sig: _Signals, kp: float, ki: float, kv: float, kff: float, kt: float) -> float:
    """Share of var(u) left by the law with these gains (the offset b fitted: the variance ignores it)."""
    p_col, i_col = _law_columns(sig, kv, kff)
    var = float(np.var(sig.u))
    return float(np.var(sig.u - kp * p_col - ki * i_col - kt * sig.ac)) / var if var > 0 else 0.0


#: the speed loop's timing relative to the trace: much faster (e.g. 8 kHz in a 1 kHz trace), or sampled at the
#: trace's rate (both loops at 1 kHz)
SPEED_LOOP_TIMING = {"fast": "faster than the trace", "sampled": "at the trace's rate"}

#: optional terms of the law, added one at a time while each cuts the unexplained share by :data:`TERM_GAIN`
#: (relative)
OPTIONAL_TERMS = ("ki", "kff", "kt")
TERM_GAIN = 0.9
#: ... and by at least this share of the output's variance (a law that already explains 99.99 % gains nothing
#: from a 0.002 feed-forward that fits the last digits)
TERM_MIN_ABS = 0.002


def _identify(sig: _Signals, terms: tuple[str, ...], start: dict[str, float]) -> tuple[float, dict[str, float]]:
    """Least-squares gains of the law with Kp, Kv and the optional ``terms``; returns (unexplained share, gains).

    Given Kv (and a velocity feed-forward) the law is linear in Kp, Ki, the torque feed-forward and the offset,
    so only Kv (and Kff) are searched (``scipy.optimize.least_squares``) and the rest solved by bounded linear
    least squares at every step (variable projection). On slow, smooth motion the following error is nearly
    proportional to the command velocity, so Kv and a velocity feed-forward (or Kp and a torque feed-forward)
    trade off along the trace; the caller therefore adds optional terms only while they pay their way
    (:func:`_select_law`)."""
    from scipy.optimize import least_squares, lsq_linear

    usc = float(np.std(sig.u)) or 1.0
    ones = np.ones(sig.u.size)

    def linear(x):
        p_col, i_col = _law_columns(sig, x[0], x[1] if "kff" in terms else 0.0)
        cols = [p_col]
        if "ki" in terms:
            cols.append(i_col)
        if "kt" in terms:
            cols.append(sig.ac)
        cols.append(ones)
        a = np.column_stack(cols)
        coef = np.linalg.lstsq(a, sig.u, rcond=None)[0]
        nonneg = 2 if "ki" in terms else 1  # Kp and Ki are not negative
        if (coef[:nonneg] < 0).any():
            lo = [0.0] * nonneg + [-np.inf] * (a.shape[1] - nonneg)
            with np.errstate(invalid="ignore"):  # scipy's reflective step computes 0 * inf for an unbounded side
                coef = lsq_linear(a, sig.u, bounds=(lo, np.inf)).x
        return coef, sig.u - a @ coef

    def resid(x):
        return linear(x)[1] / usc

    kv_lo, kv_hi = [0.0], [np.inf]
    if "kff" in terms:
        kv_lo.append(-2.0)
        kv_hi.append(2.0)
    starts = [max(start["kv_per_s"], 1e-3)]
    # a P/P law from a linear regression of u on (g e, -w) gives a second start for Kv
    c = np.linalg.lstsq(np.column_stack([sig.e, -sig.w_end, ones]), sig.u, rcond=None)[0]
    if c[1] > 0 and c[0] > 0:
        starts.append(float(c[0] / c[1]))
    best = None
    for kv0 in starts:
        x0 = [kv0] + ([min(max(start["velocity_ff"], -2.0), 2.0)] if "kff" in terms else [])
        sol = least_squares(resid, x0, bounds=(kv_lo, kv_hi), x_scale="jac", max_nfev=100)
        if best is None or sol.cost < best.cost:
            best = sol
    coef, r = linear(best.x)
    kp = float(coef[0])
    k = 1
    ki = 0.0
    if "ki" in terms:
        ki = float(coef[k])
        k += 1
    kt = float(coef[k]) if "kt" in terms else 0.0
    un = float(np.var(r)) / float(np.var(sig.u))
    return un, {"kp": kp, "ti_s": kp / ki if ki > 0 else 0.0, "kv_per_s": float(best.x[0]),
                "velocity_ff": float(best.x[1]) if "kff" in terms else 0.0, "torque_ff_x_jref": kt,
                "jref": start["jref"]}


def _select_law(sig: _Signals, start: dict[str, float]) -> tuple[float, dict[str, float]]:
    """P speed loop and position gain first; then forward selection of the optional terms (named in the gains'
    ``terms``)."""
    terms: tuple[str, ...] = ()
    un, gains = _identify(sig, terms, start)
    while True:
        trials = [(*_identify(sig, (*terms, t), start), t) for t in OPTIONAL_TERMS if t not in terms]
        if not trials:
            break
        u2, g2, t = min(trials, key=lambda x: x[0])
        if u2 >= TERM_GAIN * un or un - u2 < TERM_MIN_ABS:
            break
        un, gains, terms = u2, g2, (*terms, t)
    gains["terms"] = ",".join(terms)
    return un, gains


#: contiguous blocks of the trace for the jackknife standard errors of identified gains
JACKKNIFE_BLOCKS = 5


def _gain_stderr(sig: _Signals, terms: tuple[str, ...], start: dict[str, float]) -> dict[str, float]:
    """Standard errors of the identified gains by a block jackknife: the law identified again with each of
    :data:`JACKKNIFE_BLOCKS` contiguous blocks left out; ``se^2 = (B - 1) / B sum (g_b - mean)^2``. Blocks (not
    samples) because the residual of the law is correlated over many samples. NaN where a block fit fails."""
    n = sig.u.size
    b = JACKKNIFE_BLOCKS
    if n < 50 * b:
        return {}
    edges = np.linspace(0, n, b + 1).astype(int)
    est: list[dict[str, float]] = []
    for k in range(b):
        keep = np.r_[0:edges[k], edges[k + 1]:n]

        def cut(x, keep=keep):
            return x[keep]
        # the integral column is a cumulative sum: cutting a block leaves a step the offset cannot absorb, so
        # the jackknife is taken over the P-only part when an integral term is in the law (its error is then
        # that of the proportional gains)
        sub = _Signals(u=cut(sig.u), e=cut(sig.e), vc=cut(sig.vc), w=cut(sig.w), w_end=cut(sig.w_end),
                       ac=cut(sig.ac), dt=sig.dt)
        try:
            est.append(_identify(sub, tuple(t for t in terms if t != "ki"), start)[1])
        except (ValueError, np.linalg.LinAlgError):
            continue
    if len(est) < 3:
        return {}
    out = {}
    for key in ("kp", "kv_per_s", "velocity_ff", "torque_ff_x_jref"):
        v = np.array([e[key] for e in est], dtype=float)
        out[key] = float(math.sqrt((len(v) - 1) / len(v) * np.sum((v - v.mean()) ** 2)))
    return out


def check_controller(cfg: AxisConfig, name: str, t: np.ndarray, pos_cmd: np.ndarray,
                     cols: dict[str, np.ndarray]) -> ControllerCheck | None:
    """Replay the config's control law on one trace and identify the law that fits it. None when the trace
    has no controller output (force / torque / current) or no position feedback."""
    go = _gear_and_output(cfg, cols)
    if go is None or t.size < 200:
        return None
    g, ch, u = go
    fbc = _feedback(cfg, cols, g)
    if fbc is None:
        return None
    fb, coord = fbc
    dt = float(t[1] - t[0])
    vc = np.gradient(pos_cmd, dt)
    ac = np.gradient(vc, dt)
    e = pos_cmd - fb
    # the speed coordinate is a motor angle [rad] for a motor, a position [m] for a force actuator
    w = np.diff(coord) / dt
    w_end = np.concatenate([w[:1], 1.5 * w[1:] - 0.5 * w[:-1]])  # second-order backward difference
    nsm = max(1, int(round(SMOOTH_S / dt)))
    # two timings of the speed loop: much faster than the trace (its P term acts on the speed at the end of
    # the sample), or sampled at the trace's rate (output k answers the speed over the sample before k-1)
    fast = _smoothed(_Signals(u=u[1:], e=g * e[:-1], vc=g * vc[:-1], w=w, w_end=w_end, ac=g * ac[:-1], dt=dt), nsm)
    sampled = _smoothed(_sampled_signals(cfg, u, g * e, g * vc, g * ac, w, dt), nsm)
    finite = all(np.isfinite(x).all() for x in (fast.u, fast.e, fast.vc, fast.w))
    if not finite or float(np.var(fast.u)) == 0.0:
        return None
    cfg_sampled = cfg.control.speed_cycle_s >= 0.99 * dt
    cg = _config_gains(cfg)
    ki_cfg = cg["kp"] / cg["ti_s"] if cg["ti_s"] > 0 else 0.0
    gains_cfg = (cg["kp"], ki_cfg, cg["kv_per_s"], cg["velocity_ff"], cg["torque_ff_x_jref"])
    un_cfg = _unexplained(sampled if cfg_sampled else fast, *gains_cfg)
    # the config's own gains with the other timing of the speed loop: no fitted freedom, so a much better fit
    # there is evidence about the timing alone
    un_cfg_other = _unexplained(fast if cfg_sampled else sampled, *gains_cfg)
    cfg_timing = "sampled" if cfg_sampled else "fast"
    timing = cfg_timing
    if un_cfg_other * SWITCH_RATIO < un_cfg:
        timing = "fast" if cfg_sampled else "sampled"
    un_cfg_t = min(un_cfg, un_cfg_other)
    sig = sampled if timing == "sampled" else fast
    try:
        un_id, gid = _select_law(sig, cg)
    except (ValueError, np.linalg.LinAlgError):
        return None
    # how much the P term depends on *when* in the sample the speed is taken, per unit of Kp: a speed loop much
    # faster than the trace's sampling acts on a speed error far below the speed's change per sample, which the
    # trace cannot resolve — then the replay says nothing either way (a loop at the trace's rate is resolved)
    blur_per_kp = float(np.std(fast.w_end - fast.w)) / float(np.std(fast.u))
    blur_fast = max(cg["kp"], gid["kp"]) * blur_per_kp
    if un_cfg_t > SWITCH_MIN_UNEXPLAINED and un_cfg_t > SWITCH_RATIO * un_id and blur_fast <= MAX_BLUR:
        # the config's gains do not fit with either timing: its timing is no evidence, let the data choose
        # (only where the two timings can be told apart: not for a speed loop far faster than the trace)
        other = "fast" if timing == "sampled" else "sampled"
        try:
            un2, g2 = _select_law(fast if other == "fast" else sampled, cg)
        except (ValueError, np.linalg.LinAlgError):
            un2 = math.inf
        if un2 * SWITCH_RATIO < un_id:
            un_id, gid, timing = un2, g2, other
            sig = fast if other == "fast" else sampled
    gid["speed_loop"] = SPEED_LOOP_TIMING[timing]
    cg = {k: float(v) for k, v in cg.items()}
    cg["speed_loop"] = SPEED_LOOP_TIMING[cfg_timing]
    blur = max(blur_fast, gid["kp"] * blur_per_kp) if timing == "fast" else 0.0
    conclusive = blur <= MAX_BLUR
    switch = conclusive and un_cfg_t > SWITCH_MIN_UNEXPLAINED and un_cfg_t > SWITCH_RATIO * un_id \
        and un_id < WARN_UNEXPLAINED and gid["kp"] > 0 and gid["kv_per_s"] > 0
    retimed = conclusive and timing != cfg_timing
    retime = _retimed(cfg, timing, dt) if timing != cfg_timing else {}  # the speed-cycle change, if any
    if switch:  # its uncertainty, for the report (the jackknife costs 5 identifications: only where it is used)
        terms = tuple(t for t in str(gid.get("terms", "")).split(",") if t)
        gid["stderr"] = _gain_stderr(sig, terms, cg)
    chk = ControllerCheck(name, ch, float(un_cfg), float(un_id), cg, gid,
                          "identified" if (switch or retimed) else "config", resolution=float(blur))
    if not conclusive:
        chk.note = (f"controller not checked: its speed loop is too fast for the trace's sampling (the output "
                    f"depends on the speed within one sample by {blur:.0%} of its spread)")
    elif switch:
        chk.overrides = {"control": {**_to_config(cfg, gid), **retime}}
        chk.note = (f"the config's controller leaves {_share(un_cfg)} of {ch} unexplained, a law "
                    f"identified from the trace {_share(un_id)}: identified gains proposed for this trace "
                    f"({_describe(cfg, gid)}; the closed-loop check decides)")
    elif retimed:
        chk.overrides = {"control": retime}
        chk.note = (f"the config's gains explain {ch} {un_cfg / max(un_cfg_other, 1e-300):.3g} x better with the speed "
                    f"loop {SPEED_LOOP_TIMING[timing]} than {SPEED_LOOP_TIMING[cfg_timing]} (the config's "
                    f"control.speed_cycle_s {cfg.control.speed_cycle_s:g} s): speed loop timing changed for this "
                    f"trace ({', '.join(f'{k} = {v:g}' for k, v in chk.overrides['control'].items())})")
    elif un_cfg > WARN_UNEXPLAINED and un_cfg > 2 * un_id and un_id < WARN_UNEXPLAINED:  # a good other law
        chk.note = (f"the config's controller leaves {_share(un_cfg)} of {ch} unexplained (identified law: "
                    f"{_share(un_id)}); the controller may differ from the config's, kept")
    return chk


def _retimed(cfg: AxisConfig, timing: str, dt: float) -> dict[str, float]:
    """control.speed_cycle_s for a speed loop at the trace's rate, or (from one at the trace's rate) the
    current-loop multiple closest to 125 us (a common drive speed-loop cycle; the trace cannot tell which)."""
    c = cfg.control
    if timing == "sampled":
        out = {"speed_cycle_s": c.position_cycle_s if abs(c.position_cycle_s - dt) <= 0.01 * dt else dt}
    else:
        out = {"speed_cycle_s": max(1, round(125e-6 / c.current_cycle_s)) * c.current_cycle_s}
    if c.output_delay_s > 0:  # the same number of speed cycles from sample to output
        out["output_delay_s"] = round(c.output_delay_s / c.speed_cycle_s) * out["speed_cycle_s"]
    return out


def _share(x: float) -> str:
    if x >= 10:
        return f"{x:.3g} x the variance"
    return f"{x:.0%}" if x >= 0.01 else f"{100 * x:.2g} %"


def _to_config(cfg: AxisConfig, gains: dict) -> dict[str, float]:
    """control.* values of identified gains."""
    kp_key = "velocity_kp_n_s_per_m" if cfg.actuator.kind == "force" else "speed_kp_nm_s_per_rad"
    jref = gains["jref"]
    return {kp_key: gains["kp"], "speed_ti_s": gains["ti_s"], "kv_per_s": gains["kv_per_s"],
            "kv_1000_per_min": 0.0, "kv_per_min": 0.0, "velocity_ff_factor": max(gains["velocity_ff"], 0.0),
            "torque_ff_factor": max(gains["torque_ff_x_jref"] / jref, 0.0) if jref > 0 else 0.0}


def _describe(cfg: AxisConfig, gains: dict[str, float]) -> str:
    unit = "N s/m" if cfg.actuator.kind == "force" else "N m s/rad"
    ti = f"Ti {gains['ti_s'] * 1e3:.1f} ms" if gains["ti_s"] > 0 else "P speed loop"
    se = gains.get("stderr", {})

    def pm(key: str) -> str:
        return f" ± {se[key]:.2g}" if key in se and math.isfinite(se[key]) else ""

    return (f"Kv {gains['kv_per_s']:.3g}{pm('kv_per_s')} 1/s, Kp {gains['kp']:.4g}{pm('kp')} {unit}, {ti}, "
            f"velocity feed-forward {gains['velocity_ff']:.2f}, speed loop {gains['speed_loop']}")
