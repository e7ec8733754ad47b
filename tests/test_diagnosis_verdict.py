"""Per-channel verdicts and the plausibility of a fitted effect (unit level, no simulation)."""

from __future__ import annotations

import math

from test_diagnosis_controller import RIGID

from virtualaxis.config import load_axis_config
from virtualaxis.diagnosis import effects as fx
from virtualaxis.diagnosis.verdict import channel_verdict, rmse_tolerance


def test_an_average_that_improves_does_not_hide_a_channel_that_got_worse():
    # two channels 3x better, one 1.45x worse: the mean ratio is < 1, the verdict is not "improves"
    v = channel_verdict({"a": 1.0, "b": 1.0, "pos_meas": 1.0}, {"a": 0.33, "b": 0.33, "pos_meas": 1.45},
                        {"a": 500, "b": 500, "pos_meas": 500})
    assert not v["improves"] and v["worse_channels"] == ["pos_meas"]
    assert v["channels"]["pos_meas"]["worse"] and math.isclose(v["channels"]["pos_meas"]["ratio"], 1.45)


def test_a_change_within_the_noise_is_neither_better_nor_worse():
    tol = rmse_tolerance(1.0, 50)  # 2 standard errors of an rmse from 50 independent samples: 0.2
    assert math.isclose(tol, 2 / math.sqrt(100))
    v = channel_verdict({"a": 1.0, "b": 1.0}, {"a": 0.5, "b": 1.0 + 0.9 * tol}, {"a": 50, "b": 50})
    assert v["improves"] and v["worse_channels"] == [] and v["better_channels"] == ["a"]
    v = channel_verdict({"a": 1.0}, {"a": 1.0 - 0.5 * tol}, {"a": 50})
    assert not v["improves"]  # nothing better beyond its noise


def test_a_heavily_damped_mode_is_not_a_resonance():
    cfg = load_axis_config(RIGID)
    why = fx.implausible("resonance", cfg, {"resonance_frequency_hz": 15.0, "resonance_mass_kg": 100.0,
                                            "resonance_damping_ratio": 0.3},
                         {"resonance_mass_kg": 1.0}, [])
    assert any("not a resonance" in w for w in why)
    ok = fx.implausible("resonance", cfg, {"resonance_frequency_hz": 45.0, "resonance_mass_kg": 20.0,
                                           "resonance_damping_ratio": 0.03}, {"resonance_mass_kg": 0.2}, [])
    assert ok == []


def test_a_parameter_at_its_bound_or_not_determined_is_no_answer():
    cfg = load_axis_config(RIGID)
    m0 = cfg.mechanics.table_mass_kg
    at = fx.implausible("mass_error", cfg, {"table_mass_kg": 5 * m0}, {"table_mass_kg": 1.0}, ["table_mass_kg"])
    assert at and "bound" in at[0]
    assert fx.implausible("mass_error", cfg, {"table_mass_kg": 1.3 * m0}, {"table_mass_kg": math.inf}, [])
    # within 3 standard errors of the model's value: not distinguishable from it
    assert fx.implausible("mass_error", cfg, {"table_mass_kg": 1.05 * m0}, {"table_mass_kg": 0.03 * m0}, [])
    assert fx.implausible("mass_error", cfg, {"table_mass_kg": 1.3 * m0}, {"table_mass_kg": 0.01 * m0}, []) == []
    # a physical zero (no backlash, no heating) at the lower bound is fine
    assert fx.implausible("coulomb_friction", cfg, {"coulomb_n": 0.0}, {"coulomb_n": 1.0}, ["coulomb_n"]) == [] or \
        all("bound" not in w for w in fx.implausible("coulomb_friction", cfg, {"coulomb_n": 0.0}, {"coulomb_n": 1.0},
                                                     ["coulomb_n"]))


def test_a_force_offset_is_a_load_against_plus_x():
    import numpy as np

    from virtualaxis.sim import simulate_command

    cfg = load_axis_config(RIGID).replace(friction={"enabled": False})
    t = np.arange(1500) * 1e-3
    pos = np.zeros_like(t)
    base = simulate_command(cfg, t, pos, seed=0)
    off = simulate_command(fx.EFFECTS["force_offset"].apply(cfg, {"force_offset_n": 60.0}), t, pos, seed=0)
    # at standstill the drive holds the load: its force settles about +60 N above the nominal's
    assert abs(np.mean(off["force_drive"][-100:] - base["force_drive"][-100:]) - 60.0) < 3.0


def test_a_gap_a_learned_model_predicts_held_out_is_concluded_systematic_not_no_effect():
    """No library effect accepted: a learned residual model that removes most of a position channel's held-out
    residual shows a systematic gap ("unexplained systematic gap"), one that removes a little does not, and one
    judged on its own fit trace proves nothing."""
    from virtualaxis.diagnosis.pipeline import _unexplained_gap

    def hyb(ratio: float, judged_on: str = "holdout", better: tuple = ("pos_meas",)) -> dict:
        ch = {"pos_meas": {"before": 65.5e-6, "after": 65.5e-6 * ratio, "ratio": ratio, "worse": False}}
        return {"model": "mlp_lagged", "judged_on": judged_on, "improves": bool(better),
                "verdict": {"channels": ch, "better_channels": list(better), "worse_channels": []}}

    gap = _unexplained_gap(hyb(0.066))
    assert gap and gap["channel"] == "pos_meas" and "65.5 -> 4.32 um" in gap["description"], gap
    assert _unexplained_gap(hyb(0.92)) is None  # (a clean axis: the learned model takes 8 %)
    assert _unexplained_gap(hyb(0.066, judged_on="fit")) is None  # (one trace: fitted and judged on itself)
    assert _unexplained_gap(hyb(0.066, better=())) is None
    assert _unexplained_gap(None) is None
