"""Pieces of the fitting machinery: the quantisation floor of the channel weights, combined effects for the
joint refit, and the derivative-free polish on a cost whose slope is mostly roughness."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

from virtualaxis.diagnosis import effects as fx
from virtualaxis.diagnosis.bench import nominal_config
from virtualaxis.diagnosis.data import TraceData, Weights, channel_quanta, quantum


def test_quantum_finds_the_grid_of_an_encoder_and_none_on_analog_data():
    rng = np.random.default_rng(0)
    q = 2 * math.pi / 131072  # a 17-bit motor encoder [rad]
    angle = np.round(np.cumsum(rng.normal(0, 3e-3, 5000)) / q) * q
    assert quantum(angle) == pytest.approx(q, rel=1e-6)
    scale = np.round(rng.uniform(-0.05, 0.05, 5000) / 5e-8) * 5e-8 + 0.1  # 50 nm scale with an offset
    assert quantum(scale) == pytest.approx(5e-8, rel=1e-6)
    assert quantum(rng.normal(0, 1, 5000)) == 0.0  # an analog current: not on a grid
    assert quantum(np.exp(np.linspace(0, 1, 1000))) == 0.0  # smooth, steps not multiples of one another
    assert quantum(np.zeros(100)) == 0.0


def test_a_channel_residual_of_a_fraction_of_one_count_is_weighted_as_noise():
    """The position loop closes on the motor encoder, so its residual is mostly 0 with rare one-count
    flips: without the floor its sigma would be far below a count and the flips would dominate the cost."""
    rng = np.random.default_rng(1)
    q = 1e-6
    flips = (rng.uniform(size=4000) < 0.02) * q * rng.choice([-1, 1], 4000)
    res = [{"motor_pos": flips, "pos_meas": rng.normal(0, 1e-7, 4000) + 5e-7 * np.sin(np.arange(4000) / 100)}]
    w0 = Weights.from_residuals(res)
    w1 = Weights.from_residuals(res, {"motor_pos": q, "pos_meas": 0.0})
    assert w0.sigma["motor_pos"] < 0.2 * q / math.sqrt(12)
    assert w1.sigma["motor_pos"] == pytest.approx(q / math.sqrt(12))
    assert w1.sigma["pos_meas"] == w0.sigma["pos_meas"]
    td = TraceData("t", np.arange(10.0), np.zeros(10), None, {"motor_pos": np.arange(10) * q, "pos_meas": res[0]
                                                             ["pos_meas"][:10]})
    assert channel_quanta([td]) == {"motor_pos": pytest.approx(q), "pos_meas": 0.0}


def test_combined_effect_applies_like_its_parts_in_order():
    cfg = nominal_config("ballscrew")
    joint = fx.effect_of("backlash+coulomb_friction")
    names = [p.name for p in joint.params(cfg)]
    assert names == ["backlash/gap_m", "coulomb_friction/coulomb_n"]
    seq = fx.EFFECTS["coulomb_friction"].apply(fx.EFFECTS["backlash"].apply(cfg, {"gap_m": 12e-6}),
                                               {"coulomb_n": 95.0})
    both = joint.apply(cfg, {"backlash/gap_m": 12e-6, "coulomb_friction/coulomb_n": 95.0})
    assert both == seq
    assert both.backlash.gap_m == 12e-6 and both.friction.coulomb_n == 95.0
    assert fx.split_joint({"a/x": 1.0, "b/y": 2.0, "a/z": 3.0}) == {"a": {"x": 1.0, "z": 3.0}, "b": {"y": 2.0}}
    assert fx.is_discrete("torque_ripple/cogging_periods_per_rev") and not fx.is_discrete("backlash/gap_m")
    with pytest.raises(KeyError):
        fx.effect_of("backlash+nonsense")
    with pytest.raises(KeyError):
        fx.effect_of("nonsense")


def test_polish_reaches_the_minimum_where_a_secant_slope_is_mostly_roughness():
    """A residual linear in x (zero at 1.7) plus a rough, non-reproducible ripple that changes completely
    with any step: the secant Jacobian is mostly ripple, so Gauss-Newton creeps; the polish (Brent line
    searches on the cost) does not need a slope."""
    from virtualaxis.diagnosis import fit as F

    class Toy:
        free = [fx.Param("x", "1", 0.0, 10.0, 1.0)]
        job = SimpleNamespace(settings=F.FitSettings())
        secant_jacobian = F._Model.secant_jacobian  # the fitter's own finite differences
        jacobian_steps = F._Model.jacobian_steps

        def __init__(self):
            self.calls = 0

        def bounds(self):
            return np.array([0.0]), np.array([10.0])

        def residual_vector(self, u):
            self.calls += 1
            x = float(u[0])
            return np.full(200, 1.2 * (x - 1.7)) + 0.7 * np.sin(np.arange(200) * (1 + 37.0 * x))

    u0 = np.array([0.9])  # trust region 0 .. 1.8 (linear parameter: up to twice the value)
    g = F.gauss_newton(Toy(), u0, np.array([0.0]), np.array([10.0]), 5)[0]
    toy = Toy()
    u = F.polish(toy, u0, np.array([0.0]), np.array([10.0]), 40)
    assert abs(g[0] - 1.7) > 0.1  # the secant steps creep (1.51)
    assert abs(u[0] - 1.7) < 0.05  # the polish lands at the minimum (1.71)
    assert toy.calls <= 60


def test_symmetric_friction_asymmetry_reduces_to_coulomb_friction():
    same = fx.reduce_nested("friction_asymmetry", {"coulomb_n": 112.3, "coulomb_negative_n": 112.28},
                            {"coulomb_n": 1.4, "coulomb_negative_n": 1.4})
    assert same == ("coulomb_friction", {"coulomb_n": pytest.approx(112.29)})
    within_noise = fx.reduce_nested("friction_asymmetry", {"coulomb_n": 100.0, "coulomb_negative_n": 108.0},
                                    {"coulomb_n": 3.0, "coulomb_negative_n": 3.0})
    assert within_noise is not None  # 8 N apart, 2 sigma of the difference is 8.5 N
    assert fx.reduce_nested("friction_asymmetry", {"coulomb_n": 48.6, "coulomb_negative_n": 95.7},
                            {"coulomb_n": 3.0, "coulomb_negative_n": 4.0}) is None
    assert fx.reduce_nested("coulomb_friction", {"coulomb_n": 50.0}, {"coulomb_n": 1.0}) is None
    # a few per cent apart, however small the standard errors: below the change an effect must make to pay its
    # way (fx.MIN_RELATIVE_CHANGE), no asymmetry (55.05 / 57.14 N, +-0.7 N, on a symmetric 55 N)
    assert fx.reduce_nested("friction_asymmetry", {"coulomb_n": 55.05, "coulomb_negative_n": 57.14},
                            {"coulomb_n": 0.70, "coulomb_negative_n": 0.75}) == (
        "coulomb_friction", {"coulomb_n": pytest.approx(56.095)})
    assert fx.reduce_nested("friction_asymmetry", {"coulomb_n": 55.0, "coulomb_negative_n": 60.0},
                            {"coulomb_n": 0.7, "coulomb_negative_n": 0.7}) is None  # 9 %: an asymmetry


def test_chaos_floor_is_the_models_own_irreproducible_part():
    """The quantised, friction-stick seed 000 loop: an unmeasurably small change of the command changes the
    current chatter by a sizeable fraction of its level; the same axis with ideal encoders and no stick
    (no friction) answers with (almost) exactly the same prediction."""
    from virtualaxis.diagnosis.data import chaos_floor, default_simulate

    cfg = nominal_config("ballscrew")
    t = np.arange(1500) * 1e-3
    pos = 0.005 * (1 - np.cos(2 * math.pi * 1.0 * t))
    td = TraceData("sine", t, pos, None, {"current_q": np.zeros_like(t), "pos_meas": np.zeros_like(t)})
    chaotic = chaos_floor(cfg, [td], default_simulate)
    ideal = cfg.replace(sensors={"motor_encoder_counts_per_rev": 0, "linear_scale_resolution_m": 0.0},
                        friction={"enabled": False})
    smooth = chaos_floor(ideal, [td], default_simulate)
    assert chaotic["current_q"] > 0.01  # A
    assert smooth["current_q"] < 1e-3 * chaotic["current_q"]
    assert smooth["pos_meas"] < 1e-9  # m: a 1e-12 m command change moves the ideal table by ~1e-12 m
