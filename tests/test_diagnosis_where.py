"""Residual localisation on synthetic residuals whose answer is known."""

from __future__ import annotations

import numpy as np
import pytest

from virtualaxis.diagnosis.where import MotionScale, localise, motion_labels, signature_overlap

DT = 1e-3


def _sine(duration_s: float = 6.0, amp_m: float = 0.05, period_s: float = 3.0):
    t = np.arange(int(duration_s / DT)) * DT
    cmd = amp_m * (1 - np.cos(2 * np.pi * t / period_s))
    return t, cmd


def _share(loc, ch, dim, name):
    return loc.shares(ch, dim)[name]


def test_phase_labels_of_a_sine_and_a_dwell():
    t, cmd = _sine()
    cmd = np.concatenate([cmd, np.full(1000, cmd[-1])])
    t = np.arange(cmd.size) * DT
    lab = motion_labels(t, cmd, MotionScale.from_commands([(t, cmd)]))
    # the end dwell is standstill, reversals sit at the top of the sine (t = 1.5 s, 4.5 s)
    assert np.all(lab["phase"][-500:] == 0)
    assert lab["phase"][1500] == 3 and lab["phase"][4500] == 3
    assert lab["direction"][700] == 0 and lab["direction"][2300] == 1


def test_residual_at_reversals_is_found_there():
    t, cmd = _sine()
    v = np.gradient(cmd, DT)
    r = np.zeros_like(t)
    r[(np.abs(t - 1.5) < 0.03) | (np.abs(t - 4.5) < 0.03)] = 1e-5  # lost motion at the top reversals
    loc = localise([("a", t, cmd, {"pos_meas": r})])
    assert _share(loc, "pos_meas", "phase", "reversal") > 0.99
    assert loc.concentrations("pos_meas")[0]["bin"] == "reversal"
    assert v.max() > 0


def test_direction_and_speed_and_position():
    t, cmd = _sine()
    v = np.gradient(cmd, DT)
    r_dir = np.where(v < 0, 3.0, 0.0)  # a force offset only when moving negative
    r_speed = v * 1000.0  # viscous-like
    r_pos = np.where(cmd > 0.08, 1.0, 0.0)  # near the far end of the stroke
    loc = localise([("a", t, cmd, {"force_drive": r_dir, "torque_meas": r_speed, "pos_meas": r_pos})])
    assert _share(loc, "force_drive", "direction", "negative") > 0.99
    speed = loc.shares("torque_meas", "speed")
    assert list(speed.values())[-1] > 0.5  # the fastest bin holds most of a velocity-proportional residual
    pos = loc.shares("pos_meas", "position")
    assert list(pos.values())[-1] > 0.99


def test_frequency_band_and_coherence():
    t, cmd = _sine(duration_s=8.0)
    rng = np.random.default_rng(1)
    r_mode = 1e-6 * np.sin(2 * np.pi * 45.0 * t)  # a 45 Hz mode, not coherent with the 0.33 Hz command
    r_lin = 1e-3 * (cmd - cmd.mean()) + 1e-8 * rng.standard_normal(t.size)  # a gain error: coherent
    loc = localise([("a", t, cmd, {"pos_meas": r_mode, "pos_fb": r_lin})])
    bands = loc.shares("pos_meas", "frequency")
    assert bands["20-100 Hz"] > 0.95
    assert loc.spectra["pos_meas"]["peak_hz_above_2hz"] == pytest.approx(45.0, abs=1.0)
    assert bands_low(loc.shares("pos_fb", "frequency")) > 0.95
    assert loc.spectra["pos_fb"]["coherence_with_command"]["0-1 Hz"] > 0.9
    assert loc.spectra["pos_meas"]["coherence_with_command"]["20-100 Hz"] < 0.3


def bands_low(b: dict) -> float:
    return b["0-1 Hz"] + b["1-5 Hz"]


def test_time_dimension_and_trace_shares_sum_to_one():
    t, cmd = _sine()
    r = t / t[-1]  # a drift growing with time
    loc = localise([("a", t, cmd, {"pos_meas": r}), ("b", t, cmd, {"pos_meas": 0.1 * r})])
    q = loc.shares("pos_meas", "time")
    assert q["quarter 4"] > q["quarter 3"] > q["quarter 2"] > q["quarter 1"]
    for dim in ("phase", "direction", "speed", "position", "time", "trace", "frequency"):
        assert sum(loc.shares("pos_meas", dim).values()) == pytest.approx(1.0, abs=1e-6)
    assert loc.shares("pos_meas", "trace")["a"] == pytest.approx(1 / 1.01, rel=1e-6)


def test_signature_overlap_distinguishes():
    t, cmd = _sine()
    at_rev = np.where((np.abs(t - 1.5) < 0.03) | (np.abs(t - 4.5) < 0.03), 1.0, 0.0)
    v = np.gradient(cmd, DT)
    a = localise([("a", t, cmd, {"x": at_rev})])
    b = localise([("a", t, cmd, {"x": 2 * at_rev})], a.scale)
    c = localise([("a", t, cmd, {"x": v})], a.scale)
    assert signature_overlap(a, b, "x") == pytest.approx(1.0, abs=1e-9)
    assert signature_overlap(a, c, "x") < signature_overlap(a, b, "x") - 0.2
