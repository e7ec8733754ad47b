"""A channel that wrapped around the integer range it was recorded in is refused through ``virtualaxis diagnose``
with one line naming the file, row and column; channels that only look alike (a two-level square wave, a spike,
the same trace before it wrapped) are read."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from trace_files import read_rows, simulated, write_rows

from virtualaxis.cli.main import main
from virtualaxis.diagnosis.bench import BALLSCREW_CONFIG
from virtualaxis.diagnosis.trace import read_trace

FAST_PTP = "ptp:distance_mm=100,feed_mm_min=12000,accel_m_s2=3,jerk_m_s3=60"


@pytest.fixture(scope="module")
def trace(tmp_path_factory) -> Path:
    return simulated(tmp_path_factory.mktemp("wrap") / "ptp.csv", FAST_PTP, 3)


def _wrapped(trace: Path, out: Path) -> tuple[Path, int]:
    """The trace with current_q held in a 16-bit counter whose 32767 counts are 80 % of the peak current; returns
    the file and the file line of the first wrapped sample."""
    header, rows = read_rows(trace)
    data = np.array(rows, dtype=float)
    k = header.index("current_q")
    q = 0.8 * float(np.max(np.abs(data[:, k]))) / 32767
    counts = np.round(data[:, k] / q).astype(np.int64)
    wrapped = (counts + 32768) % 65536 - 32768
    first = int(np.flatnonzero(wrapped != counts)[0])
    data[:, k] = wrapped * q
    return write_rows(out, header, data), first + 2  # (line 1: the header)


def test_a_wrapped_current_is_refused_naming_file_row_and_column(trace, tmp_path, capsys):
    bad, line = _wrapped(trace, tmp_path / "wrapped.csv")
    rc = main(["diagnose", "--config", str(BALLSCREW_CONFIG), str(bad), "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2
    assert len(err) == 1 and err[0].startswith("error: "), err
    assert str(bad) in err[0] and "column current_q" in err[0] and "wrapped around the integer range" in err[0]
    # the row named is the jump into the wrapped values (or, when noise crossed the edge first, one next to it)
    row = int(err[0].split("row ")[1].split(":")[0])
    assert abs(row - line) <= 3, (row, line)
    assert not (tmp_path / "out").exists()


def test_the_same_trace_before_it_wrapped_is_read(trace):
    read_trace(trace)


@pytest.mark.parametrize("shape", ["square", "spike"])
def test_a_square_wave_and_a_spike_are_no_wrap(trace, tmp_path, shape):
    header, rows = read_rows(trace)
    data = np.array(rows, dtype=float)
    t, k = data[:, header.index("t")], header.index("current_q")
    noise = np.random.default_rng(1).normal(0.0, 0.05, t.size)
    if shape == "square":  # a torque test switching between +-20 A every 0.25 s
        data[:, k] = np.where((t // 0.25) % 2 == 0, 20.0, -20.0) + noise
    else:  # one sample at 30 A on a trace within +-5 A
        data[:, k] = np.clip(data[:, k], -5.0, 5.0)
        data[t.size // 2, k] = 30.0
    read_trace(write_rows(tmp_path / f"{shape}.csv", header, data))
