"""Trace reading and validation: every bad-input case names file, row and column."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from virtualaxis.config import load_axis_config
from virtualaxis.config.errors import InputError
from virtualaxis.diagnosis.trace import check_units, read_trace

ROOT = Path(__file__).resolve().parents[1]
CFG = ROOT / "configs" / "seed000-hust.toml"


def _write(path: Path, header: str, rows: np.ndarray | list) -> Path:
    lines = [header] + [",".join(f"{x:.10g}" if isinstance(x, float) else str(x) for x in r) for r in rows]
    path.write_text("\n".join(lines) + "\n")
    return path


def _good_rows(n: int = 200, dt: float = 1e-3) -> np.ndarray:
    t = np.arange(n) * dt
    cmd = 0.01 * (1 - np.cos(2 * np.pi * t / (n * dt)))
    meas = cmd - 1e-5
    mp = meas * 2 * np.pi / 0.016
    return np.column_stack([t, cmd, meas, mp])


HEADER = "t,pos_cmd,pos_meas,motor_pos"


def test_good_trace_reads(tmp_path):
    p = _write(tmp_path / "a.csv", HEADER, _good_rows())
    tr = read_trace(p)
    assert tr.t.size == 200 and tr.dt_s == pytest.approx(1e-3)
    assert tr.channels() == ["pos_meas", "motor_pos"]
    assert tr.warnings == []
    check_units(tr, load_axis_config(CFG))


def test_drive_words_read_silently_other_unknown_columns_warned(tmp_path):
    """A drive recording's statusword / controlword (the live page's recordings carry the statusword) are read
    without a warning; a column nobody knows is named in one."""
    rows = np.column_stack([_good_rows(), np.full(200, 0x1637), np.full(200, 0x0F), np.zeros(200)])
    tr = read_trace(_write(tmp_path / "a.csv", HEADER + ",statusword,controlword,spindle_load", rows))
    assert tr.warnings == ["extra columns ignored: spindle_load"]


def test_missing_required_column(tmp_path):
    p = _write(tmp_path / "a.csv", "t,pos_meas", _good_rows()[:, [0, 2]])
    with pytest.raises(InputError, match=r"a\.csv: row 1: column pos_cmd: required column 'pos_cmd' missing"):
        read_trace(p)


def test_no_position_channel(tmp_path):
    p = _write(tmp_path / "a.csv", "t,pos_cmd", _good_rows()[:, :2])
    with pytest.raises(InputError, match="at least one of the columns pos_meas, pos_fb, motor_pos"):
        read_trace(p)


def test_non_monotonic_time_names_row(tmp_path):
    rows = _good_rows()
    rows[50, 0] = rows[48, 0]
    p = _write(tmp_path / "a.csv", HEADER, rows)
    with pytest.raises(InputError) as ei:
        read_trace(p)
    assert ei.value.row == 52 and ei.value.column == "t"  # data row 50 is line 52 (header = line 1)
    assert "not increasing" in str(ei.value)


def test_gap_in_time_names_row(tmp_path):
    rows = _good_rows()
    rows[120:, 0] += 0.05
    p = _write(tmp_path / "a.csv", HEADER, rows)
    with pytest.raises(InputError, match=r"row 122: column t: time gap of 0.051 s") as ei:
        read_trace(p)
    assert ei.value.row == 122


def test_jitter_is_resampled_with_warning(tmp_path):
    rows = _good_rows()
    rng = np.random.default_rng(0)
    rows[1:-1, 0] += rng.uniform(-1e-4, 1e-4, rows.shape[0] - 2)
    p = _write(tmp_path / "a.csv", HEADER, rows)
    tr = read_trace(p)
    assert np.allclose(np.diff(tr.t), np.diff(tr.t)[0])
    assert any("jitter" in w and "resampled" in w for w in tr.warnings)


def test_isolated_nan_interpolated_long_run_rejected(tmp_path):
    rows = _good_rows().astype(object)
    rows[30, 2] = "nan"
    tr = read_trace(_write(tmp_path / "a.csv", HEADER, rows))
    assert np.isfinite(tr.columns["pos_meas"]).all()
    assert any("interpolated" in w and "row 32" in w for w in tr.warnings)
    rows = _good_rows().astype(object)
    rows[40:60, 2] = ""
    with pytest.raises(InputError) as ei:
        read_trace(_write(tmp_path / "b.csv", HEADER, rows))
    assert ei.value.row == 42 and ei.value.column == "pos_meas"


def test_nan_in_command_is_an_error(tmp_path):
    rows = _good_rows().astype(object)
    rows[10, 1] = "nan"
    with pytest.raises(InputError, match=r"row 12: column pos_cmd: missing value"):
        read_trace(_write(tmp_path / "a.csv", HEADER, rows))


def test_not_a_number(tmp_path):
    rows = _good_rows().astype(object)
    rows[7, 2] = "abc"
    with pytest.raises(InputError, match=r"row 9: column pos_meas: not a number: 'abc'"):
        read_trace(_write(tmp_path / "a.csv", HEADER, rows))


def test_position_in_mm_is_rejected(tmp_path):
    rows = _good_rows()
    rows[:, 2] *= 1e4  # 100 "metres"
    rows[:, 1] *= 1e4
    tr = read_trace(_write(tmp_path / "a.csv", HEADER, rows))
    with pytest.raises(InputError, match=r"column pos_cmd: position .* is not plausible .* in metres"):
        check_units(tr, load_axis_config(CFG))


def test_measured_position_in_other_unit(tmp_path):
    rows = _good_rows()
    rows[:, 2] *= 10.0  # cm
    tr = read_trace(_write(tmp_path / "a.csv", HEADER, rows))
    with pytest.raises(InputError, match=r"column pos_meas: .*times as far as pos_cmd"):
        check_units(tr, load_axis_config(CFG))


def test_motor_angle_of_another_axis(tmp_path):
    rows = _good_rows()
    rows[:, 3] *= 0.016 / 0.010  # a 10 mm lead screw
    tr = read_trace(_write(tmp_path / "a.csv", HEADER, rows))
    with pytest.raises(InputError, match=r"column motor_pos: .*another axis"):
        check_units(tr, load_axis_config(CFG))


def test_sidecar_names_another_axis(tmp_path):
    p = _write(tmp_path / "run1.csv", HEADER, _good_rows())
    (tmp_path / "run1.toml").write_text('axis = "y-axis-of-mill-2"\nnotes = "x"\n')
    with pytest.raises(InputError, match=r"run1\.toml: key axis: the trace belongs to axis 'y-axis-of-mill-2'"):
        read_trace(p, axis_name="seed000-hust")
    tr = read_trace(p)  # without an axis to compare with, the metadata is just kept
    assert tr.metadata["notes"] == "x"


def test_ragged_row(tmp_path):
    """A row with more or fewer fields than the header names its line and the column concerned."""
    p = tmp_path / "a.csv"
    p.write_text("t,pos_cmd,pos_meas\n0,0,0\n0.001,0,0,5\n")
    with pytest.raises(InputError, match=r"row 3: column pos_meas: has 4 fields, the header has 3: 1 beyond"):
        read_trace(p)
    p.write_text("t,pos_cmd,pos_meas\n0,0,0\n0.001,0,0\n0.002,0\n")
    with pytest.raises(InputError, match=r"row 4: column pos_meas: has 2 fields, the header has 3: no value for "
                       r"pos_meas"):
        read_trace(p)


def test_missing_file():
    with pytest.raises(InputError, match="file not found"):
        read_trace("/nonexistent/trace.csv")


def test_streamed_reader_names_the_line_after_the_first_chunk(tmp_path):
    """The reader parses 50 000-line chunks in C; a bad value deep in the file still gets its line."""
    rows = _good_rows(120_000)
    p = _write(tmp_path / "long.csv", HEADER, rows)
    tr = read_trace(p)
    assert tr.t.size == 120_000
    np.testing.assert_allclose(tr.columns["pos_meas"], rows[:, 2], rtol=1e-9, atol=1e-15)
    lines = p.read_text().splitlines()
    lines[100_002] = lines[100_002].replace(",", ",x", 1)  # line 100 003 of the file
    p.write_text("\n".join(lines) + "\n")
    with pytest.raises(InputError, match=r"long.csv: row 100003: column pos_cmd: not a number"):
        read_trace(p)


def test_trace_over_the_sample_bound_is_refused_before_it_is_read(tmp_path, monkeypatch):
    import virtualaxis.diagnosis.trace as trace_mod

    monkeypatch.setattr(trace_mod, "MAX_TRACE_SAMPLES", 1000)
    monkeypatch.setattr(trace_mod, "_CHUNK_LINES", 500)
    p = _write(tmp_path / "big.csv", HEADER, _good_rows(2000))
    with pytest.raises(InputError, match=r"about [12],\d{3} samples .* at most 1,000 samples per trace"):
        read_trace(p)
    p = _write(tmp_path / "huge.csv", HEADER, _good_rows(20_000))  # over 512 bytes per allowed sample: unread
    with pytest.raises(InputError, match=r"huge.csv: [\d.]+ MiB; the diagnosis reads at most 1,000 samples"):
        read_trace(p)
    p = _write(tmp_path / "edge.csv", HEADER, _good_rows(1000))
    assert read_trace(p).t.size == 1000


def test_bom_header_and_missing_line_end(tmp_path):
    p = _write(tmp_path / "b.csv", HEADER, _good_rows())
    p.write_bytes(b"\xef\xbb\xbf" + p.read_bytes()[:-1])  # BOM, and the last row without its line end
    tr = read_trace(p)
    assert tr.t.size == 199
    assert any("no line end" in w for w in tr.warnings)
