"""How the recorded channels relate to the model's: sample alignment, the speed estimator's form, and a start
transient. Found from the nominal model's prediction before any effect is fitted, applied to every later
prediction of the trace (``TraceData.post``, see :func:`apply_post`), and reported.

- **Sample alignment of a channel**: drive traces differ in which sample a value belongs to (force row ``k`` =
  force applied during ``[k-1, k)`` or ``[k, k+1)``). A controller-output or velocity channel whose residual
  falls to :data:`SHIFT_RATIO` of its value when the prediction is moved by one sample — and not further at two
  (that would be a delay, an effect, not a convention) — on every trace is shifted, with a warning. Position
  channels are never shifted (a position lag is a dead time the effect library fits).
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

from virtualaxis.diagnosis.data import TraceData

#: a one-sample shift of a channel is taken when it leaves at most this share of the residual rms on every trace
SHIFT_RATIO = 0.7
#: an estimator form replaces the model's velocity state when it leaves at most this share of the residual
ESTIMATOR_RATIO = 0.8
#: channels that may be shifted: controller outputs and velocity (positions: a lag is a dead time, an effect)
SHIFTABLE = ("force_drive", "torque_meas", "current_q", "vel_meas")
ESTIMATORS = ("one_sample", "two_sample")


def _shift(x: np.ndarray, s: int) -> np.ndarray:
    """``y[k] = x[k - s]`` (edges held)."""
    if s == 0:
        return x
    y = np.empty_like(x)
    if s > 0:
        y[s:] = x[:-s]
        y[:s] = x[0]
    else:
        y[:s] = x[-s:]
        y[s:] = x[-1]
    return y


def _estimate(pos: np.ndarray, dt: float, form: str) -> np.ndarray:
    if form == "one_sample":
        v = np.diff(pos, prepend=pos[0]) / dt
    else:  # two_sample
        v = np.empty_like(pos)
        v[2:] = (pos[2:] - pos[:-2]) / (2 * dt)
        v[:2] = (pos[1] - pos[0]) / dt if pos.size > 1 else 0.0
    return v


def apply_post(td: TraceData, pred: dict[str, np.ndarray], lead_m: float = 0.0) -> dict[str, np.ndarray]:
    """The prediction as the trace records it (``td.post``: ``velocity`` estimator form, ``shift`` per channel,
    ``exclude_start`` samples replaced by the measurement so they cost nothing)."""
    post = td.post
    if not post:
        return pred
    out = dict(pred)
    form = post.get("velocity")
    if form and "vel_meas" in out:
        p = _position_for_velocity(out, lead_m)
        if p is not None:
            out["vel_meas"] = _estimate(p, float(td.t[1] - td.t[0]), form)
    for ch, s in post.get("shift", {}).items():
        if ch in out:
            out[ch] = _shift(out[ch], int(s))
    n0 = int(post.get("exclude_start", 0))
    if n0 > 0:
        for ch in out:
            if ch in td.measured:
                out[ch] = out[ch].copy()
                out[ch][:n0] = td.measured[ch][:n0]
    return out


def _position_for_velocity(pred: dict[str, np.ndarray], lead_m: float) -> np.ndarray | None:
    for ch in ("pos_meas", "pos_fb"):
        if ch in pred:
            return pred[ch]
    if "motor_pos" in pred and lead_m > 0:
        return pred["motor_pos"] * lead_m / (2 * math.pi)
    return None


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
                pos = _position_for_velocity(p, lead_m)
                if pos is None:
                    break
                parts.append(td.measured["vel_meas"] - _estimate(pos, float(td.t[1] - td.t[0]), form))
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
    # one-sample alignment per channel, the same on every trace
    preds2 = [apply_post(td, p, lead_m) for td, p in zip(tds, preds, strict=True)]
    for ch in SHIFTABLE:
        items = [(td, p) for td, p in zip(tds, preds2, strict=True) if ch in td.measured and ch in p]
        if not items:
            continue
        ratios: dict[int, list[float]] = {-2: [], -1: [], 1: [], 2: []}
        for td, p in items:
            r0 = _rms(td.measured[ch][4:-4] - p[ch][4:-4])
            for s in ratios:
                ratios[s].append(_rms(td.measured[ch][4:-4] - _shift(p[ch], s)[4:-4]) / max(r0, 1e-300))
        for s in (-1, 1):
            worst = max(ratios[s])
            if worst <= SHIFT_RATIO and max(ratios[2 * s]) >= 0.9 * worst:
                for td, _ in items:
                    td.post.setdefault("shift", {})[ch] = s
                findings.append({"kind": "channel_shift", "channel": ch, "samples": s,
                                 "residual_ratio": worst,
                                 "note": f"{ch} is recorded one sample {'later' if s > 0 else 'earlier'} than the "
                                         f"model's convention (row k holds the value of sample k{-s:+d}); aligned "
                                         f"(residual rms x {worst:.2f} on every trace)"})
                break
    return findings


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
    moving = v0 > START_SPEED_SHARE * vmax and v0 > 5 * abs(float(td.pos_cmd[5] - td.pos_cmd[0])) / (5 * dt)
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
