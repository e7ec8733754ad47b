"""Model-form conventions the diagnosis had to get right for data our simulator did not make: a settled
start, a resonance that is a part of the weighed moving mass, physical bounds (viscous friction up to the drive's
peak force at top speed) and a parameter within one standard error of a non-zero bound counting as at the bound."""

from __future__ import annotations

import math

import numpy as np
import pytest

from virtualaxis.diagnosis import effects as fx
from virtualaxis.diagnosis.bench import nominal_config
from virtualaxis.diagnosis.data import SETTLE_S, TraceData, default_simulate, noiseless, settled, simulate_trace
from virtualaxis.diagnosis.fit import _at_bound


def _warm(cfg):
    return cfg.replace(effects={"thermal_expansion_per_k": 11.5e-6, "initial_temperature_rise_k": 3.5})


def test_a_warm_screw_starts_settled():
    """3.5 K on the screw: the simulator's reset already puts the table where the thermal growth holds it (before:
    the contact spring carried the growth at t = 0 and the axis rang, its current ripple over five times that of
    the settled run); after :data:`SETTLE_S` of standstill it is still at rest, the nut displaced from the first
    sample on."""
    cfg = noiseless(_warm(nominal_config("ballscrew")))
    t = np.arange(300) * 1e-3
    pos = np.zeros_like(t)  # standstill
    raw = default_simulate(cfg, t, pos, None, 0)
    done = settled(default_simulate, cfg, t, pos, None, 0)
    assert set(done) >= {"pos_meas", "current_q"} and done["pos_meas"].shape == t.shape
    growth = cfg.effects.thermal_expansion_per_k * 3.5 * cfg.axis.nut_offset_m
    for run in (raw, done):
        assert float(np.ptp(run["current_q"][:50])) < 1e-3  # no ringing: the contact starts relaxed
        assert run["pos_meas"][0] == pytest.approx(growth, rel=0.2)  # displaced from the first sample on
    td = TraceData("standstill", t, pos, None, {"pos_meas": raw["pos_meas"]})
    assert simulate_trace(cfg, td, default_simulate)["pos_meas"] == pytest.approx(done["pos_meas"], abs=1e-9)
    assert SETTLE_S >= 0.1


def test_a_resonance_is_a_part_of_the_weighed_moving_mass():
    cfg = nominal_config("ballscrew")
    m = cfg.mechanics.table_mass_kg
    eff = fx.EFFECTS["resonance"]
    c1 = eff.apply(cfg, {"resonance_frequency_hz": 45.0, "resonance_mass_kg": 20.0, "resonance_damping_ratio": 0.03})
    assert c1.mechanics.table_mass_kg + c1.effects.resonance_mass_kg == pytest.approx(m)
    c2 = eff.apply(c1, {"resonance_frequency_hz": 45.0, "resonance_mass_kg": 30.0, "resonance_damping_ratio": 0.03})
    assert c2.mechanics.table_mass_kg + c2.effects.resonance_mass_kg == pytest.approx(m)  # refitted on top: same total
    mass_bound = {p.name: p for p in eff.params(c2)}["resonance_mass_kg"].upper
    assert mass_bound < m


def test_viscous_friction_may_reach_the_drives_peak_force_at_top_speed():
    cfg = nominal_config("ballscrew")
    p = fx.EFFECTS["viscous_friction"].params(cfg)[0]
    mo = cfg.motor
    i_max = cfg.control.current_limit_a or 3 * mo.rated_current_a
    peak = i_max * mo.torque_constant_nm_per_a * 2 * math.pi / cfg.mechanics.lead_m
    assert p.upper == pytest.approx(peak / cfg.limits.max_velocity_m_s)


def test_a_parameter_within_one_standard_error_of_a_non_zero_bound_is_at_it():
    p = fx.Param("stribeck_velocity_m_s", "m/s", 1e-4, 0.05, 2e-3, scale="log")
    lo, hi = p.internal_bounds()
    x = p.to_internal(0.0484)
    su = 0.0027 / 0.0484  # log scale: relative
    assert _at_bound(p, x, lo, hi, su)
    assert not _at_bound(p, p.to_internal(0.01), lo, hi, su)
    assert not _at_bound(p, x, lo, hi, math.inf)  # not determined: judged elsewhere
    z = fx.Param("gap_m", "m", 0.0, 300e-6, 20e-6)
    assert not _at_bound(z, z.to_internal(0.5e-6), *z.internal_bounds(), 0.1)  # near a physical zero: a value
    assert _at_bound(z, z.to_internal(0.0), *z.internal_bounds(), 0.1)  # on it: reported (implausible skips zero)


def test_an_undetermined_amplitude_beside_a_determined_one_is_no_veto():
    """Thermal growth: the initial temperature determined and significant, the heating per friction watt not
    determined by a few seconds of traces -> an answer (the loose one is reported as not determined); both loose ->
    no answer."""
    cfg = nominal_config("ballscrew")
    vals = {"initial_temperature_rise_k": 4.98, "thermal_resistance_k_per_w": 0.008}
    ok = fx.implausible("thermal_drift", cfg, vals, {"initial_temperature_rise_k": 0.05,
                                                     "thermal_resistance_k_per_w": math.inf}, [])
    assert ok == []
    bad = fx.implausible("thermal_drift", cfg, vals, {"initial_temperature_rise_k": math.inf,
                                                      "thermal_resistance_k_per_w": math.inf}, [])
    assert any("not determined" in w for w in bad)
    weak = fx.implausible("thermal_drift", cfg, vals, {"initial_temperature_rise_k": 3.0,
                                                       "thermal_resistance_k_per_w": math.inf}, [])
    assert any("not determined" in w for w in weak)  # the determined one is not significant either
