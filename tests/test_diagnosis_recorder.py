"""Traces as a drive's recorder writes them, read through ``virtualaxis diagnose``: a standstill recorded with
time stamps that are not exactly uniform, the first rows of a move from rest, a channel named with its unit. Each
gets the answer that names what is wrong (or none), not a misleading one."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from trace_files import read_rows, simulated, write_rows

from virtualaxis.cli.main import main
from virtualaxis.diagnosis.bench import BALLSCREW_CONFIG
from virtualaxis.diagnosis.trace import read_trace

PTP = "ptp:distance_mm=20,feed_mm_min=6000,accel_m_s2=2,jerk_m_s3=50"


@pytest.fixture(scope="module")
def move(tmp_path_factory) -> Path:
    return simulated(tmp_path_factory.mktemp("rec") / "move.csv", PTP, 1)


def _diagnose_error(path: Path, tmp_path: Path, capsys) -> str:
    rc = main(["diagnose", "--config", str(BALLSCREW_CONFIG), str(path), "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and err[0].startswith("error: "), (rc, err)
    return err[0]


def test_a_standstill_with_uneven_time_stamps_is_a_command_that_does_not_move(move, tmp_path, capsys):
    """The time stamps of a recorder that starts at 13.345 s differ in their last bits; the command's speed from
    them must still be 0, not a rounding residue against which vel_meas looks 1e10 times too fast."""
    header, rows = read_rows(move)
    last = rows[-1]  # at rest at the end of the move (20 mm: a constant whose rounding residue is not 0)
    it = header.index("t")
    still = [[repr(13.345 + k * 1e-3) if i == it else v for i, v in enumerate(last)] for k in range(3000)]
    path = write_rows(tmp_path / "standstill.csv", header, still)
    assert read_trace(path).max_speed_m_s() == 0.0
    err = _diagnose_error(path, tmp_path, capsys)
    assert "column pos_cmd" in err and "the command does not move" in err, err


def test_the_first_rows_of_a_move_from_rest_are_not_taken_for_another_axis(move, tmp_path):
    """50 rows from rest: the motor lags the command by the loop's lag, a large share of so short a travel; the
    motor angle is judged against the measured position, so the lead is recognised."""
    from virtualaxis.config import load_axis_config
    from virtualaxis.diagnosis.trace import check_units

    header, rows = read_rows(move)
    moving = next(k for k, r in enumerate(rows) if float(r[header.index("pos_cmd")]) != float(rows[0][
        header.index("pos_cmd")]))
    path = write_rows(tmp_path / "short.csv", header, rows[max(0, moving - 5):moving + 45])
    check_units(read_trace(path), load_axis_config(BALLSCREW_CONFIG))


@pytest.mark.parametrize("name", ["pos_meas_m", "current_q_a", "vel_meas_rpm", "pos_meas [m]"])
def test_a_measured_channel_named_with_its_unit_is_refused_not_dropped(move, tmp_path, capsys, name):
    header, rows = read_rows(move)
    base = name.split(" ")[0].rsplit("_", 1)[0] if "[" not in name else name.split(" ")[0]
    header = [name if h == base else h for h in header]
    err = _diagnose_error(write_rows(tmp_path / "suffix.csv", header, rows), tmp_path, capsys)
    assert f"column {name}" in err and f"{base!r} is" in err and "without units" in err, err


def test_an_extra_channel_beside_the_named_one_is_only_a_warning(move):
    header, rows = read_rows(move)
    k = header.index("pos_meas")
    tr = read_trace(write_rows(move.with_name("extra.csv"), [*header, "pos_meas_mm"],
                           [[*r, str(float(r[k]) * 1e3)] for r in rows]))
    assert "pos_meas" in tr.columns and any("pos_meas_mm" in w for w in tr.warnings)
    assert np.isfinite(tr.columns["pos_meas"]).all()
