"""Seed 004 cost function C(k_v) (studies/seeds.py): the reconstructed form and its weight sensitivity, on
synthetic metric curves whose optimum is known in closed form."""

from __future__ import annotations

import numpy as np
import pytest

from virtualaxis.studies.seeds import kv_cost_weight_sensitivity


def _rows(kv: np.ndarray, err: np.ndarray, energy: np.ndarray, tau: np.ndarray) -> list[dict]:
    return [{"kv_per_min": float(k), "static_position_error_m": float(e), "max_following_error_m": float(e),
             "energy_per_cycle_j": float(en), "response_time_s": float(t)}
            for k, e, en, t in zip(kv, err, energy, tau, strict=True)]


def test_terms_linear_in_inverse_kv_give_corner_optima_only() -> None:
    # energy deficit and response time both ~ following error ~ 1/kv: any weighted sum of min-max normalised
    # terms is linear in 1/kv, so the optimum is an end of the sweep whatever the weights
    kv = np.arange(1000.0, 5001.0, 125.0)
    rows = _rows(kv, 1.0 / kv, 230.0 - 1e4 / kv, 0.98 + 100.0 / kv)
    s = kv_cost_weight_sensitivity(rows, step=0.05)
    for g in s["grid"]:
        slope = g["w_precision"] - g["w_energy"] + g["w_response_time"]  # d C / d(1/kv), up to a positive factor
        if abs(slope) > 1e-9:  # (a zero slope is a flat cost: every kv is optimal)
            assert g["optimum_kv_per_min_static_position_error"] == (5000.0 if slope > 0 else 1000.0)
    assert s["readings"]["static_position_error"]["share_of_weights_within_tolerance"] == 0.0


def test_interior_optimum_and_weights_found() -> None:
    # precision error convex in kv (quadratic well), energy linear: C = w_e e~ + w_E E~ + w_t t~ has its optimum
    # where the slopes balance; with w_E = 0 and w_e > 0 it is the error minimum at 2750
    kv = np.arange(1000.0, 5001.0, 125.0)
    err = (kv - 2750.0) ** 2
    rows = _rows(kv, err, kv, np.ones_like(kv))
    s = kv_cost_weight_sensitivity(rows, step=0.05)
    pure = next(g for g in s["grid"] if g["w_precision"] == 1.0)
    assert pure["optimum_kv_per_min_static_position_error"] == 2750.0
    r = s["readings"]["static_position_error"]
    assert 0.0 < r["share_of_weights_within_tolerance"] < 1.0
    w = r["closest_weights_within_tolerance"]
    assert w is not None and 2475.0 <= w["optimum_kv_per_min_static_position_error"] <= 2997.5
    # the bounds: 3 (w.x) - 2 spans [-2, 1] for weights summing to 1
    assert sum(w[k] for k in ("w_precision", "w_energy", "w_response_time")) == pytest.approx(1.0)


def test_timing_sensitivity_reads_the_error_at_each_delay() -> None:
    from virtualaxis.studies.seeds import kv_cost_timing_sensitivity

    kv = np.arange(1000.0, 5001.0, 125.0)
    delays = np.array([0.0, 0.1])
    # at delay 0 the error is a well centred on 2750 (optimum there); at 0.1 s it is flat (corner optimum)
    rows = [{"kv_per_min": float(k), "energy_per_cycle_j": 0.0, "response_time_s": 1.0,
             "error_after_move_m": [(k - 2750.0) ** 2, 1.0]} for k in kv]
    s = kv_cost_timing_sensitivity(rows, delays)
    assert s["optimum_kv_per_min"][0] == 2750.0
    assert s["delays_within_tolerance_s"] == [0.0]
