"""Measured-FRF CSV import and mode-table import: formats and their bad-input cases."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from virtualaxis.config import load_axis_config
from virtualaxis.config.errors import InputError
from virtualaxis.rcsa.measured import (
    modes_from_frfs,
    read_frf_csv,
    read_mode_table_csv,
    synthetic_frfs,
    write_frf_csv,
)
from virtualaxis.rcsa.params import JointParams, rcsa_model_from_config
from virtualaxis.rcsa.peaks import measured_modes

CONFIG = Path(__file__).resolve().parents[1] / "configs" / "seed002-usst.toml"
LIGHT = JointParams(4.28e7, 2.94e7, 7.09e8, 5.53e3, 100.0, 100.0, 500.0, 0.1)


@pytest.fixture(scope="module")
def model():
    return rcsa_model_from_config(load_axis_config(CONFIG)).with_joints(LIGHT)


def _write(tmp_path: Path, text: str, name: str = "frf.csv") -> Path:
    p = tmp_path / name
    p.write_text(text)
    return p


def test_complex_csv_round_trip_and_modes(tmp_path, model):
    freq = np.arange(5.0, 1000.0, 0.25)
    frfs = synthetic_frfs(
        model, [0.6, 1.0], freq, magnitude_noise=0.0, phase_noise_deg=0.0, noise_floor_m_per_n=0.0
    )
    path = tmp_path / "frf.csv"
    write_frf_csv(path, frfs)
    back = read_frf_csv(path)
    assert [b.position_m for b in back] == [0.6, 1.0]
    np.testing.assert_allclose(back[1].h_m_per_n, frfs[1].h_m_per_n, rtol=1e-12)
    modes = modes_from_frfs(back, model)
    assert np.all(np.isfinite(modes.frequencies_hz[0]))  # all four modes at 0.6 m


def test_polar_csv_reads_magnitude_and_phase(tmp_path):
    p = _write(
        tmp_path, "position_m,freq_hz,mag,phase_deg\n0.6,10,2e-7,90\n0.6,11,3e-7,180\n0.6,12,1e-7,-90\n"
    )
    (frf,) = read_frf_csv(p)
    np.testing.assert_allclose(frf.h_m_per_n, [2e-7j, -3e-7, -1e-7j], atol=1e-20)


@pytest.mark.parametrize(
    "body, row, column, words",
    [
        ("0.6,10,1e-7,0\n0.6,11,nan,0\n0.6,12,1e-7,0\n", 3, "re", "not a finite number"),
        ("0.6,10,1e-7,0\n0.6,11,abc,0\n0.6,12,1e-7,0\n", 3, "re", "not a number"),
        ("0.6,10,1e-7,0\n0.6,12,1e-7,0\n0.6,11,1e-7,0\n", 4, "freq_hz", "unsorted"),
        ("0.6,10,1e-7,0\n0.6,10,1e-7,0\n0.6,12,1e-7,0\n", 3, "freq_hz", "duplicate frequency 10"),
        ("0.6,0,1e-7,0\n0.6,10,1e-7,0\n0.6,12,1e-7,0\n", 2, "freq_hz", "must be > 0"),
        ("0.6,10,1e-7\n", 2, None, "expected 4 columns"),
    ],
)
def test_bad_frf_rows_name_file_row_and_column(tmp_path, body, row, column, words):
    p = _write(tmp_path, "position_m,freq_hz,re,im\n" + body)
    with pytest.raises(InputError) as err:
        read_frf_csv(p)
    assert err.value.row == row
    assert err.value.column == column
    assert words in str(err.value)
    assert str(err.value).startswith(str(p))


def test_bad_frf_header_and_missing_file(tmp_path):
    with pytest.raises(InputError, match="header must hold"):
        read_frf_csv(_write(tmp_path, "position,f,re,im\n0.6,10,1,0\n"))
    with pytest.raises(InputError, match="file not found"):
        read_frf_csv(tmp_path / "nope.csv")
    with pytest.raises(InputError, match="empty file"):
        read_frf_csv(_write(tmp_path, ""))


def test_mode_table_with_gap_and_amplitudes(tmp_path):
    p = _write(
        tmp_path,
        "position_m,order,freq_hz,amplitude_m_per_n\n"
        "1.3,1,24,\n1.3,2,116,\n1.3,3,—,\n1.3,4,717,\n0.6,1,24,2.44e-4\n0.6,2,118,2.62e-5\n",
        "modes.csv",
    )
    m = read_mode_table_csv(p, 4)
    assert list(m.positions_m) == [0.6, 1.3]
    assert math.isnan(m.frequencies_hz[1, 2]) and m.frequencies_hz[1, 3] == 717.0
    assert m.amplitudes_m_per_n[0, 0] == 2.44e-4 and math.isnan(m.amplitudes_m_per_n[1, 0])
    assert math.isnan(m.frequencies_hz[0, 3])  # order 4 not given at 0.6 m: a gap


@pytest.mark.parametrize(
    "body, words",
    [
        ("0.6,5,24\n", "order must be an integer 1..4"),
        ("0.6,1,24\n0.6,1,25\n", "duplicate order 1"),
        ("0.6,1,nan\n", "not a finite number"),
        ("0.6,1,118\n0.6,2,24\n", "must increase with the order"),
    ],
)
def test_bad_mode_tables(tmp_path, body, words):
    p = _write(tmp_path, "position_m,order,freq_hz\n" + body, "modes.csv")
    with pytest.raises(InputError, match=words):
        read_mode_table_csv(p, 4)


def test_band_without_a_peak_is_a_gap_not_the_band_edge():
    freq = np.linspace(10.0, 100.0, 901)
    mass_line = 1.0 / freq**2  # monotonic: the maximum sits on the band edge
    f, a = measured_modes(freq, mass_line, np.array([[20.0, 40.0], [40.0, 80.0]]))
    assert np.all(np.isnan(f)) and np.all(np.isnan(a))
    bump = mass_line * (1 + 2.0 * np.exp(-(((freq - 60.0) / 1.0) ** 2)))
    f, a = measured_modes(freq, bump, np.array([[20.0, 40.0], [40.0, 80.0]]))
    assert math.isnan(f[0]) and f[1] == pytest.approx(60.0, abs=0.2)
