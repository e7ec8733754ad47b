"""How a trace records the model's channels (``TraceData.post``, decided by :mod:`virtualaxis.diagnosis.alignment`):
a channel moved by whole samples, the speed estimator's form, start samples excluded from every cost. Applied to
every prediction of the trace by :func:`virtualaxis.diagnosis.data.simulate_trace`; needs nothing of the diagnosis
but the trace's arrays."""

from __future__ import annotations

import math
from typing import Protocol

import numpy as np


class RecordedTrace(Protocol):
    """What :func:`apply_post` reads of a trace (a :class:`virtualaxis.diagnosis.data.TraceData`)."""

    post: dict  # velocity estimator form, shift per channel, start samples excluded
    t: np.ndarray  # sample times [s]
    measured: dict[str, np.ndarray]  # the measured channels


def shift_samples(x: np.ndarray, s: int) -> np.ndarray:
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


def estimate_velocity(pos: np.ndarray, dt: float, form: str) -> np.ndarray:
    if form == "one_sample":
        v = np.diff(pos, prepend=pos[0]) / dt
    else:  # two_sample
        v = np.empty_like(pos)
        v[2:] = (pos[2:] - pos[:-2]) / (2 * dt)
        v[:2] = (pos[1] - pos[0]) / dt if pos.size > 1 else 0.0
    return v


def apply_post(td: RecordedTrace, pred: dict[str, np.ndarray], lead_m: float = 0.0) -> dict[str, np.ndarray]:
    """The prediction as the trace records it (``td.post``: ``velocity`` estimator form, ``shift`` per channel,
    ``exclude_start`` samples replaced by the measurement so they cost nothing)."""
    post = td.post
    if not post:
        return pred
    out = dict(pred)
    form = post.get("velocity")
    if form and "vel_meas" in out:
        p = position_for_velocity(out, lead_m)
        if p is not None:
            out["vel_meas"] = estimate_velocity(p, float(td.t[1] - td.t[0]), form)
    for ch, s in post.get("shift", {}).items():
        if ch in out:
            out[ch] = shift_samples(out[ch], int(s))
    n0 = int(post.get("exclude_start", 0))
    if n0 > 0:
        for ch in out:
            if ch in td.measured:
                out[ch] = out[ch].copy()
                out[ch][:n0] = td.measured[ch][:n0]
    return out


def position_for_velocity(pred: dict[str, np.ndarray], lead_m: float) -> np.ndarray | None:
    for ch in ("pos_meas", "pos_fb"):
        if ch in pred:
            return pred[ch]
    if "motor_pos" in pred and lead_m > 0:
        return pred["motor_pos"] * lead_m / (2 * math.pi)
    return None
