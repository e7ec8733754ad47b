"""Per-channel verdicts: "better" only when no channel gets worse beyond what its noise explains.

An average of channel ratios can hide one channel that got clearly worse (a hybrid model whose mean held-out
ratio said "improves" while the held-out position channel was 1.45 x worse). Every verdict the diagnosis
prints is therefore made per channel: a channel counts as *worse* when its RMSE after exceeds its RMSE before
by more than two standard errors of an RMSE estimate (``rmse / sqrt(2 n_eff)`` with ``n_eff`` the decorrelated
sample count) and by more than :data:`MIN_RELATIVE_WORSE` of it.
"""

from __future__ import annotations

import math

#: a channel's RMSE must grow by more than this share to count as worse (whatever its sample count)
MIN_RELATIVE_WORSE = 0.01
#: ... and by more than this many standard errors of the RMSE estimate
WORSE_STDERRS = 2.0


def rmse_tolerance(rmse_before: float, n_eff: float) -> float:
    """How much an RMSE may grow [channel unit] before the change exceeds its noise: max(1 %, 2 standard errors
    ``rmse / sqrt(2 n_eff)``)."""
    se = rmse_before / math.sqrt(2.0 * max(n_eff, 1.0))
    return max(MIN_RELATIVE_WORSE * rmse_before, WORSE_STDERRS * se)


def channel_verdict(before: dict[str, float], after: dict[str, float], n_eff: dict[str, float] | None = None) -> dict:
    """Per channel ``{"before", "after", "ratio" (after / before), "worse"}`` plus ``improves`` (some channel
    better beyond its noise, none worse beyond it) and ``worse_channels``. ``n_eff``: decorrelated sample count
    per channel (default 1000)."""
    n_eff = n_eff or {}
    chans: dict[str, dict] = {}
    worse, better = [], []
    for ch, b in before.items():
        if ch not in after:
            continue
        a = float(after[ch])
        tol = rmse_tolerance(float(b), n_eff.get(ch, 1000.0))
        is_worse = a - b > tol
        is_better = b - a > tol
        chans[ch] = {"before": float(b), "after": a, "ratio": a / b if b > 0 else math.nan, "worse": bool(is_worse)}
        if is_worse:
            worse.append(ch)
        if is_better:
            better.append(ch)
    return {"channels": chans, "worse_channels": worse, "better_channels": better,
            "improves": bool(better) and not worse}


def describe(verdict: dict, units: dict[str, str] | None = None) -> str:
    """One line: ``pos_meas 3.1e-06 -> 1.2e-06 (0.39x), force_drive 12 -> 13 (1.08x, worse)``."""
    units = units or {}
    parts = []
    for ch, v in verdict["channels"].items():
        u = f" {units[ch]}" if units.get(ch) else ""
        flag = ", worse" if v["worse"] else ""
        parts.append(f"{ch} {v['before']:.3g} -> {v['after']:.3g}{u} ({v['ratio']:.2f}x{flag})")
    return ", ".join(parts)
