"""How the recorded channels relate to the model's: sample alignment, the speed estimator's form, and a start
transient. Found from the nominal model's prediction before any effect is fitted, applied to every later
prediction of the trace (``TraceData.post``, see :func:`apply_post`), and reported.

- **Sample alignment of a channel**: drive traces differ in which sample a value belongs to (force row ``k`` =
  force applied during ``[k-1, k)`` or ``[k, k+1)``). A controller-output or velocity channel whose residual energy
  falls by more than :data:`SHIFT_Z` standard errors when the prediction is moved by one sample (and not further
  at two, and by less than half as much when moved the other way) on the pooled traces is aligned, with a
  warning, unless a position channel prefers a move too (then it is a dead time, an effect the library fits).
  Position channels are never shifted.
- **Speed estimator's form**: the model's ``vel_meas`` is the table's velocity; a drive reports an estimate, e.g.
  ``(q[k] - q[k-1]) / T`` or ``(q[k] - q[k-2]) / 2T`` of its position. When the estimate formed from the model's
  position leaves at most :data:`ESTIMATOR_RATIO` of the state's residual, that form is used (an unexpressed
  two-sample difference shows up as a few-percent "mass error").
- **Start transient**: the model starts at rest on the command; an axis already moving (or displaced) at the
  first sample leaves a transient the plant effects cannot explain. It is detected (first samples' speed or
  offset against the command) and the samples until the nominal residual settles are excluded from every cost.
"""

from __future__ import annotations

import math

import numpy as np

from virtualaxis.diagnosis.data import TraceData, correlation_time
from virtualaxis.diagnosis.recording import (
    apply_post,
    estimate_velocity,
    position_for_velocity,
    shift_samples,
)

#: an estimator form replaces the model's velocity state when it leaves at most this share of the residual
ESTIMATOR_RATIO = 0.8
#: channels that may be shifted: controller outputs and velocity (positions: a lag is a dead time, an effect)
SHIFTABLE = ("force_drive", "torque_meas", "current_q", "vel_meas")
ESTIMATORS = ("one_sample", "two_sample")


def _rms(x: np.ndarray) -> float:
    return float(np.sqrt(np.mean(x * x))) if x.size else 0.0


def find_alignment(tds: list[TraceData], preds: list[dict[str, np.ndarray]], lead_m: float = 0.0) -> list[dict]:
    """Decide the post-processing of every trace from the nominal predictions; sets ``td.post`` and returns the
    findings (``report.json["alignment"]``)."""
    findings: list[dict] = []
    # speed estimator's form (one decision for all traces: one drive)
    with_vel = [(td, p) for td, p in zip(tds, preds, strict=True) if "vel_meas" in td.measured and "vel_meas" in p]
    if with_vel:
        base = np.concatenate([td.measured["vel_meas"] - p["vel_meas"] for td, p in with_vel])
        best, best_r = None, _rms(base)
        for form in ESTIMATORS:
            parts = []
            for td, p in with_vel:
                pos = position_for_velocity(p, lead_m)
                if pos is None:
                    break
                parts.append(td.measured["vel_meas"] - estimate_velocity(pos, float(td.t[1] - td.t[0]), form))
            else:
                r = _rms(np.concatenate(parts))
                if r < best_r * (ESTIMATOR_RATIO if best is None else 1.0):
                    best, best_r = form, r
        if best:
            for td, _ in with_vel:
                td.post["velocity"] = best
            findings.append({"kind": "speed_estimator", "form": best, "rmse_state": _rms(base), "rmse_form": best_r,
                             "note": f"vel_meas is a {best.replace('_', '-')} difference of the position (residual "
                                     f"{_rms(base):.3g} -> {best_r:.3g} m/s against the model's velocity state); "
                                     "the model's velocity is formed the same way"})
    # one-sample alignment per channel, the same on every trace: the residual energy with the prediction moved by
    # one sample against unmoved, in standard errors of that difference; two samples must not be better still
    preds2 = [apply_post(td, p, lead_m) for td, p in zip(tds, preds, strict=True)]
    for ch in ("pos_meas", "pos_fb"):
        s_pos, z_pos = _best_shift(tds, preds2, ch)
        if s_pos and z_pos > SHIFT_Z:
            return findings  # the positions lag too: a dead time (an effect), not a recording convention
    for ch in SHIFTABLE:
        s, z = _best_shift(tds, preds2, ch)
        if s:
            items = [td for td, p in zip(tds, preds2, strict=True) if ch in td.measured and ch in p]
            for td in items:
                td.post.setdefault("shift", {})[ch] = s
            findings.append({"kind": "channel_shift", "channel": ch, "samples": s, "z": z,
                             "note": f"{ch} is recorded one sample {'later' if s > 0 else 'earlier'} than the "
                                     f"model's convention (row k holds the model's value of sample k{-s:+d}; the "
                                     f"residual energy falls by {z:.0f} standard errors); aligned"})
    return findings


#: a channel shift must be this many standard errors from zero
SHIFT_Z = 5.0


def _best_shift(tds: list[TraceData], preds: list[dict[str, np.ndarray]], ch: str) -> tuple[int, float]:
    """(+-1, z) when moving the prediction of ``ch`` by one sample lowers the pooled residual energy by more than
    :data:`SHIFT_Z` standard errors of that difference (the residual's correlation time allowed for), a move by
    two samples does not lower it further and a move the other way gains less than half as much; else (0, best
    z)."""
    ssr = {k: 0.0 for k in (-2, -1, 0, 1, 2)}
    dd = {k: 0.0 for k in (-1, 1)}
    n = 0
    taus = []
    for td, p in zip(tds, preds, strict=True):
        if ch not in td.measured or ch not in p:
            continue
        m, x = td.measured[ch][4:-4], p[ch]
        for k in ssr:
            r = m - shift_samples(x, k)[4:-4]
            ssr[k] += float(r @ r)
            if k == 0:
                taus.append(correlation_time(r))
        for k in dd:
            d = shift_samples(x, k)[4:-4] - x[4:-4]
            dd[k] += float(d @ d)
        n += m.size
    if n < 100:
        return 0, 0.0
    best, best_z = 0, 0.0
    tau = float(np.mean(taus))  # residual correlation time [samples]
    for k in (-1, 1):
        if dd[k] <= 0:
            continue
        sigma = math.sqrt(ssr[k] / n)
        z = (ssr[0] - ssr[k]) / (2.0 * sigma * math.sqrt(dd[k]) * math.sqrt(tau))
        if z > best_z:
            best, best_z = k, z
    # a recording convention moves the channel one way: the other way must gain less than half as much (a
    # chatter of the prediction that either move lines up with the recorded one gains alike both ways)
    one_way = best and (ssr[0] - ssr[-best]) < 0.5 * (ssr[0] - ssr[best])
    if best and best_z > SHIFT_Z and ssr[2 * best] >= ssr[best] and one_way:
        return best, best_z
    return 0, best_z


#: start transient: the first samples' speed above this share of the trace's top command speed ...
START_SPEED_SHARE = 0.05
#: ... or the first sample's position off the command by more than this many times the trace's median |residual|
START_OFFSET_FACTOR = 20.0


def find_start_transient(td: TraceData, pred: dict[str, np.ndarray]) -> dict | None:
    """An axis already moving or displaced at the first sample (the model starts at rest on the command): the
    samples until the nominal residual settles (its 50 ms running rms below 3 x its median) are excluded from
    every cost. Sets ``td.post["exclude_start"]``; returns the finding or None."""
    ch = next((c for c in ("pos_meas", "pos_fb") if c in td.measured and c in pred), None)
    if ch is None or td.t.size < 200:
        return None
    dt = float(td.t[1] - td.t[0])
    x = td.measured[ch]
    vcmd = np.abs(np.gradient(td.pos_cmd, dt))
    vmax = float(vcmd.max()) or 1e-12
    v0 = abs(float(x[5] - x[0])) / (5 * dt)
    r = x - pred[ch]
    off0 = abs(float(x[0] - td.pos_cmd[0]))
    med = float(np.median(np.abs(r))) or 1e-300
    moving = v0 > START_SPEED_SHARE * vmax  # the model starts at rest whatever the command does
    displaced = off0 > START_OFFSET_FACTOR * med and off0 > 5 * float(np.median(np.abs(x - td.pos_cmd)))
    if not (moving or displaced):
        return None
    w = max(1, int(round(0.05 / dt)))
    run = np.sqrt(np.convolve(r * r, np.ones(w) / w, mode="same"))
    settled = np.flatnonzero(run < 3.0 * float(np.median(run)))
    n0 = int(settled[0]) + w if settled.size else td.t.size // 5
    n0 = min(n0, td.t.size // 5)
    td.post["exclude_start"] = n0
    why = (f"moving at {v0 * 1e3:.3g} mm/s" if moving else f"{off0 * 1e6:.3g} um off the command")
    return {"kind": "start_transient", "trace": td.name, "samples": n0, "seconds": n0 * dt,
            "note": f"the axis starts {why} at the first sample (the model starts at rest on the command): the first "
                    f"{n0 * dt:.3g} s are excluded from every cost"}
