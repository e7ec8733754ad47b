"""Joint identification (seed 002 eqs. 25-26) on data with a known answer."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from virtualaxis.config import load_axis_config
from virtualaxis.rcsa.identify import (
    Eq26Objective,
    MeasuredModes,
    identify_joints,
    overall_error,
    predict_modes,
    relative_errors,
)
from virtualaxis.rcsa.measured import modes_from_frfs, synthetic_frfs
from virtualaxis.rcsa.params import JointParams, rcsa_model_from_config

CONFIG = Path(__file__).resolve().parents[1] / "configs" / "seed002-usst.toml"
# the known answer: Table 3 stiffnesses, light damping so that all four modes stand out of the FRF
TRUTH = JointParams(4.28e7, 2.94e7, 7.09e8, 880.0, 100.0, 100.0, 500.0, 0.1)  # Table 3, k_m read as in the config
ALL_POSITIONS = [0.6, 0.8, 1.0, 1.3, 1.6, 1.9]
TRAIN = [0.6, 1.0, 1.6]
HELD_OUT = [0.8, 1.3, 1.9]


@pytest.fixture(scope="module")
def model():
    return rcsa_model_from_config(load_axis_config(CONFIG))


@pytest.fixture(scope="module")
def measured(model):
    """'Measured' FRFs from the known joints: 1 % magnitude noise, 0.5 degree phase noise per line (an
    averaged hammer test), a noise floor, 0.1 Hz lines from 5 to 1000 Hz (10 s records), then peak
    picking as for real data."""
    freq = np.arange(5.0, 1000.0 + 1e-9, 0.1)
    frfs = synthetic_frfs(
        model.with_joints(TRUTH), ALL_POSITIONS, freq, magnitude_noise=0.01, phase_noise_deg=0.5, seed=3
    )
    return modes_from_frfs(frfs, model)


def test_peak_picking_on_noisy_frfs_finds_the_true_modes(model, measured):
    exact = predict_modes(model, ALL_POSITIONS, TRUTH)
    for i, pr in enumerate(exact):
        have = np.isfinite(measured.frequencies_hz[i])
        assert np.array_equal(have, np.isfinite(pr.natural_frequencies_hz))
        rel = relative_errors(measured.frequencies_hz[i][have], pr.natural_frequencies_hz[have])
        assert np.all(rel < 0.003)


def test_known_answer_three_positions_identify_and_predict_the_other_three(model, measured):
    train = measured.select(TRAIN)
    factor = np.array([3.0] * 4 + [10.0] * 4)  # a factor 3 (stiffness) / 10 (damping) either side
    res = identify_joints(
        model,
        train,
        lower=JointParams.from_array(TRUTH.as_array() / factor),
        upper=JointParams.from_array(TRUTH.as_array() * factor),
        population_per_parameter=8,
        generations=100,
        seed=0,
        workers=2,
        amplitude_weight=model.identification.amplitude_weight,
    )
    stiffness_error = np.abs(res.joints.as_array()[:4] / TRUTH.as_array()[:4] - 1.0)
    assert np.all(stiffness_error < 0.10), stiffness_error
    held = measured.select(HELD_OUT)
    for i, pr in enumerate(predict_modes(model, HELD_OUT, res.joints)):
        have = np.isfinite(held.frequencies_hz[i])
        assert np.array_equal(np.isfinite(pr.natural_frequencies_hz[have]), np.ones(have.sum(), bool))
        assert np.nanmax(relative_errors(pr.natural_frequencies_hz, held.frequencies_hz[i])) < 0.03


def test_objective_is_zero_at_the_answer_for_exact_frequency_data(model):
    exact = predict_modes(model, TRAIN, TRUTH)
    data = MeasuredModes(
        np.array(TRAIN),
        np.array([p.natural_frequencies_hz for p in exact]),
        np.array([p.amplitudes_m_per_n for p in exact]),
    )
    objective = Eq26Objective(model, data)
    assert objective.value_at(TRUTH) < 1e-6  # golden-section tolerance of the peak search
    wrong = JointParams.from_array(TRUTH.as_array() * np.array([1.3, 1, 1, 1, 1, 1, 1, 1]))
    assert objective.value_at(wrong) > 1e-3


def test_measured_mode_the_model_cannot_show_costs_a_full_error(model):
    # a mode measured in band 3 at l4, where the model has a node: penalty 1.0 (100 %), not zero
    data = MeasuredModes(
        np.array([1.3]), np.array([[np.nan, np.nan, 600.0, np.nan]]), np.full((1, 4), np.nan)
    )
    assert Eq26Objective(model, data).value_at(TRUTH) == pytest.approx(1.0)


def test_overall_error_is_eq_27_and_reports_a_missing_prediction():
    meas = np.array([24.0, 117.0, 536.0, 713.0])
    pred = np.array([24.0, 116.0, 549.0, 719.0])
    assert overall_error(pred, meas) == pytest.approx(0.0271, abs=5e-4)  # Table 4, l2
    assert overall_error(pred, np.array([24.0, 116.0, np.nan, 717.0])) < 0.02  # a measured gap is skipped
    assert math.isnan(overall_error(np.array([24.0, 116.0, np.nan, 719.0]), meas))


def test_select_names_a_missing_position(measured):
    with pytest.raises(ValueError, match=r"no data at position 1\.45 m"):
        measured.select([0.6, 1.45], "frf.csv")


def test_measured_data_with_a_different_number_of_orders_is_refused(model):
    data = MeasuredModes(np.array([0.6]), np.array([[24.0, 118.0]]), np.full((1, 2), np.nan))
    with pytest.raises(ValueError, match="mode orders"):
        Eq26Objective(model, data)
