"""Force against speed, per direction: the measured drive force beyond inertia, binned over the measured speed,
with the calibrated model's friction law over it (``report.json["force_vs_speed"]``).

A friction effect fitted alone absorbs whatever else depends on speed: Coulomb friction fitted on an axis with
Coulomb and viscous friction takes the viscous force at the traces' speeds (1.8x the Coulomb value on a lab axis
whose viscous force at top speed is about its Coulomb force). The binned data show it: a straight line through
them per direction has an intercept (Coulomb) and a slope (viscous); a law that is flat where the data rise, or
rises where they are flat, is the sum of two mechanisms. :func:`force_vs_speed` returns the bins, the law at the
bin centres, the line through the bins and a note when the law misses a clear intercept or slope.

The force beyond inertia is ``F_drive - m a + F_ext`` (``m`` the calibrated moving mass, reflected motor inertia
included on a screw axis; ``a`` from the measured position, smoothed over :data:`SMOOTH_S`); samples within
:data:`REVERSAL_S` of a reversal and slower than :data:`MIN_SPEED_SHARE` of the top speed are left out (pre-sliding,
stick-slip).
"""

from __future__ import annotations

import math

import numpy as np

from virtualaxis.config import AxisConfig
from virtualaxis.diagnosis.data import TraceData

#: speed and acceleration are taken from the measured position smoothed over this window [s]
SMOOTH_S = 0.01
#: samples slower than this share of the top measured speed are left out (stiction, pre-sliding)
MIN_SPEED_SHARE = 0.05
#: samples within this time of a reversal are left out [s]
REVERSAL_S = 0.05
#: speed bins per direction
N_BINS = 10
#: a line term (intercept or slope x top speed) the law misses by more than this share of the binned force, and by
#: more than 3 standard errors, is reported
MISSED_SHARE = 0.25


def _effective_mass_kg(cfg: AxisConfig) -> float:
    m = cfg.mechanics.table_mass_kg
    lead = cfg.mechanics.lead_m
    if cfg.actuator.kind != "force" and lead > 0:
        r = lead / (2 * math.pi)
        m += (cfg.mechanics.motor_inertia_kg_m2 + cfg.mechanics.coupling_inertia_kg_m2
              + cfg.mechanics.screw_end_inertia_kg_m2) / r**2
    return m


def _drive_force(cfg: AxisConfig, channels: dict[str, np.ndarray]) -> np.ndarray | None:
    """The axial drive force [N] of a trace's channels (measured or the model's): the force channel, else the
    torque or the q current through the lead (ideal screw); None without any of them."""
    if "force_drive" in channels:
        return channels["force_drive"]
    lead = cfg.mechanics.lead_m
    if lead <= 0:
        return None
    if "torque_meas" in channels:
        return channels["torque_meas"] * 2 * math.pi / lead
    if "current_q" in channels:
        return channels["current_q"] * cfg.motor.kt_nm_per_a * 2 * math.pi / lead
    return None


def _damping_n_s_per_m(cfg: AxisConfig) -> float:
    """The model's viscous damping outside the friction law, as a force on the table [N s/m]: the linear guide's,
    and on a screw axis the motor bearings' (B_m reflected through the lead: B_m / r^2)."""
    mech = cfg.mechanics
    c = mech.table_viscous_n_s_per_m
    if cfg.actuator.kind != "force" and mech.lead_m > 0:
        c += mech.motor_viscous_nm_s_per_rad / (mech.lead_m / (2 * math.pi)) ** 2
    return c


def friction_law_n(cfg: AxisConfig, v: np.ndarray) -> np.ndarray:
    """The config's speed-dependent force at speeds ``v`` [N]: the friction law (Coulomb, Stribeck, viscous; per
    direction) and the viscous damping of the guide and the motor bearings, all of which the drive force carries."""
    f = cfg.friction
    damping = _damping_n_s_per_m(cfg) * v
    if not f.enabled:
        return damping
    pos = v >= 0
    fc = np.where(pos, f.coulomb_n, f.coulomb_negative_n if f.coulomb_negative_n >= 0 else f.coulomb_n)
    fvn = f.viscous_negative_n_s_per_m if f.viscous_negative_n_s_per_m >= 0 else f.viscous_n_s_per_m
    fv = np.where(pos, f.viscous_n_s_per_m, fvn)
    vs = max(f.stribeck_velocity_m_s, 1e-9)
    st = f.stribeck_n * np.exp(-np.abs(v / vs) ** f.stribeck_exponent)
    return np.sign(v) * (fc + st) + fv * v + damping


def _line(v: np.ndarray, y: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Weighted least-squares line y = a + b v: (a, b) and their standard errors."""
    a = np.column_stack([np.ones_like(v), v]) * np.sqrt(w)[:, None]
    coef, *_ = np.linalg.lstsq(a, y * np.sqrt(w), rcond=None)
    res = y * np.sqrt(w) - a @ coef
    dof = max(len(v) - 2, 1)
    cov = np.linalg.pinv(a.T @ a) * float(res @ res) / dof
    return coef, np.sqrt(np.maximum(np.diag(cov), 0.0))


def _beyond_inertia(cfg: AxisConfig, td: TraceData, channels: dict[str, np.ndarray], m: float
                    ) -> tuple[np.ndarray, np.ndarray] | None:
    """(speed, force beyond inertia) of one trace's ``channels`` (the measured ones or the model's prediction of
    them), reversals and the smoothing's edges left out; None without a drive force or a position."""
    force = _drive_force(cfg, channels)
    pos = channels.get("pos_meas", channels.get("pos_fb"))
    if force is None or pos is None or td.t.size < 50:
        return None
    dt = float(td.t[1] - td.t[0])
    n = max(1, int(round(SMOOTH_S / dt)))
    k = np.ones(n) / n
    x = np.convolve(pos, k, mode="same")
    v = np.gradient(x, dt)
    a = np.gradient(np.convolve(v, k, mode="same"), dt)
    f_ext = td.force_ext if td.force_ext is not None else 0.0
    y = np.convolve(force, k, mode="same") - m * a + f_ext
    sgn = np.sign(v)
    rev = np.zeros(v.size, dtype=bool)
    half = int(round(REVERSAL_S / dt))
    for i in np.flatnonzero(np.diff(sgn) != 0):
        rev[max(0, i - half):i + half + 1] = True
    keep = ~rev
    keep[:n] = keep[-n:] = False
    return v[keep], y[keep]


def _binned(v: np.ndarray, y: np.ndarray, sign: float, edges: np.ndarray) -> list[dict]:
    """The samples of one direction (``sign`` +1 / -1) binned over |speed| on ``edges``: mean speed, mean force
    (in the direction of motion), its standard error and the sample count of every bin with 5 samples or more."""
    sel = v >= edges[0] if sign > 0 else v <= -edges[0]
    sp, fo = np.abs(v[sel]), sign * y[sel]
    idx = np.clip(np.digitize(sp, edges) - 1, 0, len(edges) - 2)
    bins = []
    for b in range(len(edges) - 1):
        mask = idx == b
        if mask.sum() < 5:
            continue
        vals = fo[mask]
        bins.append({"speed_m_s": float(sp[mask].mean()), "force_n": float(vals.mean()),
                     "stderr_n": float(vals.std(ddof=1) / math.sqrt(mask.sum())), "samples": int(mask.sum())})
    return bins


def _bin_line(bins: list[dict]) -> tuple[np.ndarray, np.ndarray]:
    """The weighted line through ``bins``: (intercept, slope) and their standard errors."""
    bv = np.array([b["speed_m_s"] for b in bins])
    bf = np.array([b["force_n"] for b in bins])
    bw = np.array([1.0 / max(b["stderr_n"], 1e-9) ** 2 for b in bins])
    return _line(bv, bf, bw)


def force_vs_speed(cfg: AxisConfig, traces: list[TraceData], accepted: list[str] | None = None,
                   predictions: list[dict[str, np.ndarray]] | None = None) -> dict | None:
    """The binned force beyond inertia per direction and the friction law of ``cfg`` (the calibrated model) over
    it; None when the traces have no drive force or no measured position. ``accepted``: the accepted effects (the
    note names them). ``predictions``: the calibrated model's prediction of each trace's channels (in the order
    of ``traces``); the same estimate run on them is what the data are judged against (``model_line``), so that
    what the estimate itself makes of an axis (its compliance, the smoothing, the reflected inertia) is not
    taken for a missed mechanism. Without them the data are judged against the law."""
    m = _effective_mass_kg(cfg)
    data, model = [], []
    for i, td in enumerate(traces):
        got = _beyond_inertia(cfg, td, td.measured, m)
        if got is None:
            continue
        data.append(got)
        if predictions is not None:
            pred = _beyond_inertia(cfg, td, predictions[i], m)
            if pred is not None:
                model.append(pred)
    if not data:
        return None
    v, y = np.concatenate([d[0] for d in data]), np.concatenate([d[1] for d in data])
    vm = np.concatenate([d[0] for d in model]) if model else None
    ym = np.concatenate([d[1] for d in model]) if model else None
    vmax = float(np.max(np.abs(v))) if v.size else 0.0
    if vmax <= 0:
        return None
    out: dict = {"mass_kg": m, "directions": {}, "judged_against": "model" if model else "law"}
    notes: list[str] = []
    gaps: dict[str, tuple[float, float]] = {}  # direction -> (data's intercept - the reference's, its standard error)
    edges = np.linspace(MIN_SPEED_SHARE * vmax, vmax, N_BINS + 1)
    for name, sign in (("positive", 1.0), ("negative", -1.0)):
        if int((v >= edges[0]).sum() if sign > 0 else (v <= -edges[0]).sum()) < 4 * N_BINS:
            continue
        bins = _binned(v, y, sign, edges)
        if len(bins) < 3:
            continue
        bv = np.array([b["speed_m_s"] for b in bins])
        bf = np.array([b["force_n"] for b in bins])
        law = np.abs(friction_law_n(cfg, sign * bv))
        (a0, b0), (sa, sb) = _bin_line(bins)
        (la, lb), _ = _line(bv, law, np.ones_like(bv))
        d = {"bins": bins, "law_n": law.tolist(), "line": {"intercept_n": float(a0), "intercept_stderr_n": float(sa),
             "slope_n_s_per_m": float(b0), "slope_stderr_n_s_per_m": float(sb)},
             "law_line": {"intercept_n": float(la), "slope_n_s_per_m": float(lb)}}
        ref_name, (ra, rb), (rsa, rsb) = "the law's", (la, lb), (0.0, 0.0)
        if vm is not None:
            mbins = _binned(vm, ym, sign, edges)
            if len(mbins) >= 3:
                (ra, rb), (rsa, rsb) = _bin_line(mbins)
                ref_name = "the model's"
                d["model_bins"] = mbins
                d["model_line"] = {"intercept_n": float(ra), "intercept_stderr_n": float(rsa),
                                   "slope_n_s_per_m": float(rb), "slope_stderr_n_s_per_m": float(rsb)}
        out["directions"][name] = d
        gaps[name] = (a0 - ra, math.hypot(sa, rsa))
        scale = max(float(np.abs(bf).mean()), 1e-9)
        top = float(bv.max())
        se_a, se_b = math.hypot(sa, rsa), math.hypot(sb, rsb)
        if abs(a0 - ra) > MISSED_SHARE * scale and abs(a0 - ra) > 3 * se_a:
            notes.append(f"{name} direction: the data's force at zero speed is {a0:.3g} N, {ref_name} {ra:.3g} N")
        if abs(b0 - rb) * top > MISSED_SHARE * scale and abs(b0 - rb) > 3 * se_b:
            notes.append(f"{name} direction: the data's force rises by {b0 * top:.3g} N up to {top:.3g} m/s, "
                         f"{ref_name} by {rb * top:.3g} N")
    if not out["directions"]:
        return None
    offset = _constant_force(gaps, out["directions"])
    if offset is not None:
        out["constant_force_n"] = offset
    if notes:
        fitted = [a for a in accepted or [] if "friction" in a]
        text = ("force vs speed: the calibrated model's friction law misses a mechanism the binned data show ("
                + "; ".join(notes) + ")")
        if offset is not None:
            text += (f": the two directions' gaps at zero speed differ by 2 x {offset['value_n']:.3g} N, a constant "
                     f"force of {offset['value_n']:+.3g} N +- {offset['stderr_n']:.2g} N along +x in every motion (a "
                     "load the model does not have, or an offset of the current / torque / force channel), with "
                     f"{offset['symmetric_n']:+.3g} N of friction at zero speed in both directions")
        elif fitted:
            text += f": the value of {', '.join(fitted)} may be the sum of two mechanisms"
        out["note"] = text
    return out


def _constant_force(gaps: dict[str, tuple[float, float]], directions: dict) -> dict | None:
    """A constant force along +x shows at zero speed as +F in the positive direction's force and -F in the
    negative's (each taken in its direction of motion), friction as the same amount in both: from the two
    directions' intercept gaps ``gaps`` (data - reference, standard error), F = (g+ - g-) / 2 and the symmetric
    part (g+ + g-) / 2; None unless both directions were binned and F is beyond 3 standard errors and
    :data:`MISSED_SHARE` of the binned force."""
    if "positive" not in gaps or "negative" not in gaps:
        return None
    (gp, sp), (gn, sn) = gaps["positive"], gaps["negative"]
    f, se = 0.5 * (gp - gn), 0.5 * math.hypot(sp, sn)
    scale = max(np.mean([abs(b["force_n"]) for d in directions.values() for b in d["bins"]]), 1e-9)
    if abs(f) <= 3 * se or abs(f) <= MISSED_SHARE * scale:
        return None
    return {"value_n": float(f), "stderr_n": float(se), "symmetric_n": float(0.5 * (gp + gn))}


def plot_png(data: dict) -> bytes:
    """Force vs speed per direction: the binned data (mean +- 2 standard errors) and the law over them."""
    import io

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    dirs = data["directions"]
    fig, axes = plt.subplots(1, len(dirs), figsize=(5 * len(dirs), 3.5), squeeze=False)
    for ax, (name, d) in zip(axes[0], dirs.items(), strict=True):
        v = [b["speed_m_s"] for b in d["bins"]]
        f = [b["force_n"] for b in d["bins"]]
        e = [2 * b["stderr_n"] for b in d["bins"]]
        ax.errorbar(v, f, yerr=e, fmt="o", label="measured, binned")
        ax.plot(v, d["law_n"], "-", label="fitted law")
        if d.get("model_bins"):  # the calibrated model's simulation through the same estimate
            ax.plot([b["speed_m_s"] for b in d["model_bins"]], [b["force_n"] for b in d["model_bins"]], "s--",
                    mfc="none", label="calibrated model, binned")
        ax.set_title(f"{name} direction")
        ax.set_xlabel("|speed| [m/s]")
        ax.set_ylabel("force beyond inertia [N]")
        ax.set_xlim(left=0)
        ax.set_ylim(bottom=0)
        ax.legend()
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=80)
    plt.close(fig)
    return buf.getvalue()
