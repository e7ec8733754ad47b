"""The trace writer (sim/trace_io.py): compiled CSV formatter against Python's own '%.10g', NPZ round trip,
and the ``simulate`` command's traces read back by the diagnosis reader."""

from __future__ import annotations

import json

import numpy as np
import pytest

from virtualaxis.cli.main import main
from virtualaxis.config.errors import InputError
from virtualaxis.diagnosis.trace import read_trace
from virtualaxis.resources import project_file
from virtualaxis.sim.trace_io import CSV_RELATIVE_PRECISION, TraceWriter, format_csv_rows, read_trace_csv


def _values() -> np.ndarray:
    rng = np.random.default_rng(17)
    wide = rng.standard_normal(20000) * 10.0 ** rng.integers(-15, 16, 20000)
    specials = [0.0, -0.0, 1.0, -1.0, 0.1, 1e-4, 9.99999e-5, 1e-5, 123456789.0, 1234567890.0, 12345678901.0,
                1e10, 9999999999.0, 0.00012345, 2.5, 1e-300, 5e-324, 1.7e308, 100.0, -120.5]
    grid = np.arange(0, 21001) * 0.001  # the time column of a 1 kHz trace
    return np.concatenate([wide, specials, grid, rng.integers(-10**7, 10**7, 2000) * 1e-9])


def test_formatter_matches_python_g10_and_precision_bound() -> None:
    x = _values()
    ours = format_csv_rows(x[:, None]).decode("ascii").split("\n")
    assert ours[-1] == ""
    ours = ours[:-1]
    ref = ["%.10g" % v for v in x]  # noqa: UP031 -- exactly what numpy.savetxt(fmt="%.10g") wrote
    mismatches = [i for i, (a, b) in enumerate(zip(ours, ref, strict=True)) if a != b]
    # digits may differ only at near-ties of the tenth digit (documented); none expected in this sample
    assert len(mismatches) <= 2, [(ours[i], ref[i]) for i in mismatches[:5]]
    back = np.array([float(s) for s in ours])
    nz = x != 0
    assert np.max(np.abs(back[nz] - x[nz]) / np.abs(x[nz])) <= CSV_RELATIVE_PRECISION
    assert np.array_equal(np.signbit(back), np.signbit(x))


def test_formatter_nonfinite_and_layout() -> None:
    block = np.array([[np.nan, np.inf, -np.inf], [0.5, -2.0, 3e-7]])
    assert format_csv_rows(block) == b"nan,inf,-inf\n0.5,-2,3e-07\n"


def test_npz_roundtrip_is_bit_exact_and_parquet_refused(tmp_path) -> None:
    rng = np.random.default_rng(3)
    data = {"t": np.arange(50) * 1e-3, "pos_cmd": rng.standard_normal(50), "pos_meas": rng.standard_normal(50)}
    with TraceWriter(tmp_path / "a.npz", ["pos_cmd", "pos_meas"]) as w:
        w.write({k: v[:20] for k, v in data.items()})
        w.write({k: v[20:] for k, v in data.items()})
    back = read_trace_csv(tmp_path / "a.npz")
    assert list(back) == ["t", "pos_cmd", "pos_meas"]
    for k in data:
        assert np.array_equal(back[k], data[k])
    with pytest.raises(InputError, match="Parquet"):
        TraceWriter(tmp_path / "a.parquet", ["pos_cmd"])


def test_simulate_csv_and_npz_read_by_diagnosis(tmp_path, capsys) -> None:
    cfg = str(project_file("configs/seed000-hust.toml"))
    prof = "sine:stroke_mm=100,feed_mm_min=6000"
    for ext in ("csv", "npz"):
        rc = main(["simulate", "--config", cfg, "--profile", prof, "--duration", "1.5",
                   "--out", str(tmp_path / f"t.{ext}"), "--json", str(tmp_path / f"s_{ext}.json")])
        assert rc == 0
    header = (tmp_path / "t.csv").read_text().splitlines()[0].split(",")
    assert header == ["t", "pos_cmd", "pos_meas", "pos_fb", "motor_pos", "vel_meas", "torque_meas", "current_q",
                      "force_ext", "following_error"]
    a = read_trace(tmp_path / "t.csv")
    b = read_trace(tmp_path / "t.npz")
    assert a.t.size == b.t.size == 1501
    for k in ("pos_cmd", "pos_meas", "torque_meas"):
        scale = np.max(np.abs(b.columns[k]))
        assert np.max(np.abs(a.columns[k] - b.columns[k])) <= CSV_RELATIVE_PRECISION * scale
    s = json.loads((tmp_path / "s_npz.json").read_text())
    assert s["startup_s"] >= 0 and s["real_time_factor"] > 0 and "writing" in s["real_time_factor_definition"]
    # both files describe the same run: the summary's error comes from the trace that was written
    err = b.columns["pos_meas"] - b.columns["pos_cmd"]
    assert np.max(np.abs(err)) == pytest.approx(s["max_tracking_error_m"], rel=1e-12)
    rc = main(["simulate", "--config", cfg, "--profile", prof, "--duration", "1", "--out", str(tmp_path / "t.parquet")])
    assert rc == 2
    assert "Parquet" in capsys.readouterr().err


def _blocks(rng, n_blocks=5, rows=3000):
    for k in range(n_blocks):
        t = np.arange(k * rows, (k + 1) * rows) * 1e-3
        yield {"t": t, "a": rng.standard_normal(rows), "b": rng.standard_normal(rows) * 1e-7}


def test_threaded_csv_writer_writes_the_same_bytes(tmp_path) -> None:
    """The writer thread (simulate's) gives byte for byte the file of the plain writer, blocks in order."""
    for threaded in (False, True):
        with TraceWriter(tmp_path / f"{threaded}.csv", ["a", "b"], threaded=threaded) as w:
            for data in _blocks(np.random.default_rng(7)):
                w.write(data)
        assert w.rows == 15000
    assert (tmp_path / "True.csv").read_bytes() == (tmp_path / "False.csv").read_bytes()
    assert (tmp_path / "True.csv").read_bytes().count(b"\n") == 15001
    # read back by a reader of its own (Python's csv module, float()): every value within the documented precision
    import csv

    with (tmp_path / "True.csv").open(newline="") as fh:
        rows = list(csv.reader(fh))
    assert rows[0] == ["t", "a", "b"]
    got = np.array([[float(v) for v in r] for r in rows[1:]])
    want = np.concatenate([np.column_stack([d["t"], d["a"], d["b"]]) for d in _blocks(np.random.default_rng(7))])
    np.testing.assert_allclose(got, want, rtol=CSV_RELATIVE_PRECISION, atol=0)


def test_threaded_csv_writer_reports_a_full_disk() -> None:
    """A write error in the writer thread (ENOSPC of /dev/full) is raised in the caller, naming the path, and
    nothing after it is written."""
    w = TraceWriter("/dev/full", ["a", "b"], threaded=True)
    with pytest.raises(OSError, match="/dev/full: writing the trace failed"):
        for data in _blocks(np.random.default_rng(1), n_blocks=50):
            w.write(data)
        w.close()
    w.close()  # closing again after the error: nothing left to do, no hang


def test_threaded_csv_writer_thread_never_compiles(tmp_path) -> None:
    """The writer thread runs compiled code only: in a fresh interpreter (nothing compiled in memory yet) numba's
    compiler lock is taken by the constructing thread, never by ``trace-writer`` (a compilation there, minutes on
    a busy host, left ``close`` waiting in ``join``)."""
    import subprocess
    import sys
    import textwrap

    code = textwrap.dedent(f"""
        import threading
        import numpy as np
        from numba.core import event
        from virtualaxis.sim.trace_io import TraceWriter

        class Threads(event.Listener):
            seen = set()
            def on_start(self, ev):
                self.seen.add(threading.current_thread().name)
            def on_end(self, ev):
                pass

        listener = Threads()
        with event.install_listener("numba:compiler_lock", listener):
            with TraceWriter({str(tmp_path / "t.csv")!r}, ["a"], threaded=True) as w:
                for k in range(3):
                    w.write({{"t": np.arange(5.0) + 5 * k, "a": np.ones(5)}})
        print(sorted(listener.seen))
        """)
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    seen = proc.stdout.strip().splitlines()[-1]
    assert "MainThread" in seen and "trace-writer" not in seen, seen
    assert (tmp_path / "t.csv").read_text().count("\n") == 16
