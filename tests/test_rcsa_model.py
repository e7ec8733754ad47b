"""Receptance-coupling model (seed 002 eqs. 1-24): physics limits and the independent FE cross-check."""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import tomllib
from scipy.signal import find_peaks

from virtualaxis.config import ConfigError, load_axis_config
from virtualaxis.rcsa import receptance as R
from virtualaxis.rcsa.fe_shaft import fe_matrices, fe_natural_frequencies_hz, fe_table_frf
from virtualaxis.rcsa.identify import predict_modes
from virtualaxis.rcsa.params import JointParams, rcsa_model_from_config, rcsa_model_from_dict
from virtualaxis.rcsa.reproduce import undamped

CONFIG = Path(__file__).resolve().parents[1] / "configs" / "seed002-usst.toml"
POSITIONS = (0.6, 0.8, 1.0, 1.3, 1.6, 1.9)


@pytest.fixture(scope="module")
def model():
    return rcsa_model_from_config(load_axis_config(CONFIG))


def test_config_loads_and_every_rcsa_value_has_a_source():
    cfg = load_axis_config(CONFIG)
    raw = tomllib.loads(CONFIG.read_text())["rcsa"]
    missing = []

    def walk(prefix, table):
        for k, v in table.items():
            if isinstance(v, dict) and "value" not in v:
                walk(f"{prefix}.{k}", v)
            elif k != "seed" and not (isinstance(v, dict) and v.get("source")):
                missing.append(f"{prefix}.{k}")

    walk("rcsa", raw)
    assert missing == []
    m = rcsa_model_from_config(cfg)
    assert m.screw.length_m == 2.6
    assert m.positions_m == POSITIONS


def test_rod_receptance_has_the_rigid_body_limit():
    # free-free rod at low frequency: h11 = h12 = -1 / (m omega^2)
    rigidity, slowness, length = 2e11 * 1.2566e-3, math.sqrt(7850 / 2e11), 1.3
    mass = 7850 * 1.2566e-3 * length
    omega = 2 * math.pi * 0.5
    h11, h12 = R._rod_receptances(omega * slowness, rigidity, length)
    assert h11 == pytest.approx(-1 / (mass * omega**2), rel=1e-4)
    assert h12 == pytest.approx(-1 / (mass * omega**2), rel=1e-4)


def test_table_frf_is_a_mass_line_far_below_the_first_mode(model):
    # rotor held: static compliance is finite; far above the last mode the table alone moves
    p = model.parameter_vector()
    h = np.empty(1, dtype=np.complex128)
    R.table_frf(np.array([20000.0]), 1.0, p, h)
    omega = 2 * math.pi * 20000.0
    assert abs(h[0]) == pytest.approx(1 / (model.parts.table_mass_kg * omega**2), rel=0.05)


@pytest.mark.parametrize("position_m", [0.6, 1.3, 1.9])
def test_damped_frf_matches_independent_fe_model(model, position_m):
    freq = np.geomspace(5.0, 1000.0, 300)
    for joints in (model.joints, JointParams(4.28e7, 2.94e7, 7.09e8, 5.53e3, 100.0, 100.0, 500.0, 0.1)):
        h_rcsa = np.empty(freq.size, dtype=np.complex128)
        R.table_frf(freq, position_m, model.parameter_vector(joints), h_rcsa)
        h_fe = fe_table_frf(model, position_m, freq, joints, elements_per_metre=30.0)
        err = np.abs(h_rcsa - h_fe) / np.abs(h_fe)
        assert np.max(err) < 0.02
        # what is left is the FE discretisation error: it shrinks when the mesh is refined
        worst = freq[[int(np.argmax(err))]]
        h_fine = fe_table_frf(model, position_m, worst, joints, elements_per_metre=90.0)
        h_exact = np.empty(1, dtype=np.complex128)
        R.table_frf(worst, position_m, model.parameter_vector(joints), h_exact)
        assert abs(h_exact[0] - h_fine[0]) / abs(h_fine[0]) < max(np.max(err) / 4, 1e-6)


def _rcsa_poles_hz(model, position_m):
    """All peaks of the (nearly) undamped RCSA table FRF below 1 kHz, found without the mode bands."""
    m = undamped(model)
    p = m.parameter_vector()
    p[R.JOINT_SLICE][4:] = 1e-9  # a whisker of damping keeps |h| finite on the poles
    freq = np.geomspace(2.0, 1000.0, 200000)
    h = np.empty(freq.size, dtype=np.complex128)
    R.table_frf(freq, position_m, p, h)
    idx, _ = find_peaks(np.log(np.abs(h)), prominence=1.0)
    return freq[idx]


@pytest.mark.parametrize("position_m", POSITIONS)
def test_natural_frequencies_below_1khz_agree_with_fe_within_2_percent(model, position_m):
    fe = fe_natural_frequencies_hz(model, position_m)
    fe = fe[(fe > 1.0) & (fe < 1000.0)]
    poles = _rcsa_poles_hz(model, position_m)
    assert len(poles) >= 4
    for f in poles:  # every RCSA resonance is an FE mode
        assert np.min(np.abs(fe - f) / fe) < 0.02, (f, fe)
    # every FE mode that moves the table shows up as an RCSA resonance
    fm = fe_matrices(model, position_m)
    import scipy.linalg

    w2, vec = scipy.linalg.eigh(fm.stiffness, fm.mass)
    f_all = np.sqrt(np.clip(w2, 0, None)) / (2 * math.pi)
    participation = vec[fm.table_dof, :] ** 2 / np.max(vec[fm.table_dof, :] ** 2)
    for f, part in zip(f_all, participation, strict=True):
        if 1.0 < f < 1000.0 and part > 1e-6:
            assert np.min(np.abs(poles - f) / f) < 0.02, (f, poles)


def test_mode_with_a_node_at_the_nut_is_a_gap_not_a_wrong_number(model):
    # l4 = 1.3 m is mid-screw: the FE model has a mode in the third band there, but it does not move
    # the table, so the FRF has no peak and the prediction reports a gap (the paper's "—" at l4)
    fe = fe_natural_frequencies_hz(model, 1.3)
    lo, hi = model.mode_bands_hz[2]
    assert np.any((fe > lo) & (fe < hi))
    pred = predict_modes(undamped(model), [1.3])[0]
    assert math.isnan(pred.natural_frequencies_hz[2])
    assert np.all(np.isfinite(pred.natural_frequencies_hz[[0, 1, 3]]))


def test_first_modes_follow_the_table_position_like_fig_10(model):
    preds = predict_modes(model, list(POSITIONS))
    f2 = np.array([p.natural_frequencies_hz[1] for p in preds])
    assert np.all(np.diff(f2) < 0)  # second order falls as l grows (Table 1, Fig. 10b)
    f1 = np.array([p.natural_frequencies_hz[0] for p in preds])
    assert np.all(np.abs(f1 - 24.0) < 1.0)


def _rcsa_raw():
    return tomllib.loads(CONFIG.read_text())["rcsa"]


@pytest.mark.parametrize(
    "mutate, key",
    [
        (lambda r: r.pop("joints"), "rcsa.joints"),
        (lambda r: r["joints"].pop("nut_stiffness_n_per_m"), "rcsa.joints.nut_stiffness_n_per_m"),
        (lambda r: r["joints"].update(nut_stiffness_n_per_m=-1.0), "rcsa.joints.nut_stiffness_n_per_m"),
        (
            lambda r: r["joints"].update(nut_stiffness_n_per_m=float("nan")),
            "rcsa.joints.nut_stiffness_n_per_m",
        ),
        (lambda r: r["screw"].update(lenght_m=2.0), "rcsa.screw.lenght_m"),
        (lambda r: r["screw"].update(length_m="2.6"), "rcsa.screw.length_m"),
        (lambda r: r["modes"].update(bands_hz=[[10.0, 60.0], [50.0, 300.0]]), "rcsa.modes.bands_hz[1]"),
        (lambda r: r["modes"].update(bands_hz=[[60.0, 10.0]]), "rcsa.modes.bands_hz[0]"),
        (lambda r: r.update(positions_m=[0.6, 3.0]), "rcsa.positions_m"),
        (lambda r: r.update(positions_m=[0.6, 0.6]), "rcsa.positions_m"),
        (
            lambda r: r["identification"]["upper"].update(nut_stiffness_n_per_m=1.0),
            "rcsa.identification.upper.nut_stiffness_n_per_m",
        ),
        (lambda r: r.update(colour="red"), "rcsa.colour"),
    ],
)
def test_bad_rcsa_section_names_file_and_key(mutate, key):
    raw = _rcsa_raw()
    mutate(raw)
    with pytest.raises(ConfigError) as err:
        rcsa_model_from_dict(raw, "x.toml")
    assert err.value.key == key
    assert str(err.value).startswith(f"x.toml: {key}: ")


def test_position_outside_the_screw_is_refused(model):
    with pytest.raises(ValueError, match="outside the screw"):
        predict_modes(model, [2.6])
    with pytest.raises(ValueError, match="outside the screw"):
        fe_natural_frequencies_hz(replace(model), float("nan"))


def test_public_frf_api_checks_its_input(model):
    from virtualaxis.rcsa import table_frf_m_per_n

    h = table_frf_m_per_n(model, 1.0, np.array([50.0, 100.0]))
    assert h.shape == (2,) and np.all(np.isfinite(h))
    for bad in (np.array([0.0, 10.0]), np.array([np.nan]), np.ones((2, 2))):
        with pytest.raises(ValueError, match="freq_hz"):
            table_frf_m_per_n(model, 1.0, bad)
