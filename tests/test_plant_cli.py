"""The plant's command-line interfaces: outputs other parts rely on, and clear errors."""

import csv
import json
import subprocess
import sys

from plant_helpers import SEED000, SEED004

from virtualaxis.cli.main import main

TRACE_COLUMNS = ["t", "pos_cmd", "pos_meas", "pos_fb", "motor_pos", "vel_meas", "torque_meas", "current_q",
                 "force_ext"]


def test_simulate_writes_trace_format_and_summary(tmp_path):
    out, js = tmp_path / "trace.csv", tmp_path / "s.json"
    rc = main(["simulate", "--config", str(SEED000), "--profile", "sine:stroke_mm=100,feed_mm_min=6000",
               "--duration", "0.5", "--out", str(out), "--json", str(js)])
    assert rc == 0
    with out.open() as fh:
        rows = list(csv.reader(fh))
    assert rows[0][: len(TRACE_COLUMNS)] == TRACE_COLUMNS
    assert len(rows) == 1 + 501
    s = json.loads(js.read_text())
    for key in ("rmse_tracking_error_m", "max_tracking_error_m", "simulated_s", "wall_s"):
        assert key in s
    assert s["simulated_s"] == 0.5
    assert 0 < s["rmse_tracking_error_m"] < s["max_tracking_error_m"] < 1e-3


def test_every_profile_kind_runs(tmp_path):
    moves = tmp_path / "moves.csv"
    moves.write_text("t,pos\n0,0\n0.1,0.001\n0.3,0.002\n")
    for spec in ("ptp:distance_mm=50,feed_mm_min=10000,accel_m_s2=2,jerk_m_s3=50", "step:distance_um=10",
                 "chirp:amplitude_um=5,f0_hz=1,f1_hz=500", f"file:{moves}"):
        assert main(["simulate", "--config", str(SEED000), "--profile", spec, "--duration", "0.3",
                     "--out", str(tmp_path / "t.csv"), "--force"]) == 0, spec
    r = subprocess.run([sys.executable, "-m", "virtualaxis.cli.main", "simulate", "--config", str(SEED000),
                        "--profile", "circle:radius_mm=50,omega_rad_min=120", "--duration", "0.3",
                        "--out", str(tmp_path / "c.csv")], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert (tmp_path / "c_x.csv").exists() and (tmp_path / "c_y.csv").exists()
    assert f"-> {tmp_path / 'c_x.csv'}, {tmp_path / 'c_y.csv'}" in r.stdout  # (the files written, not --out)
    assert not (tmp_path / "c.csv").exists()


def test_demo_and_serve_refuse_what_they_would_not_do(tmp_path):
    """demo: a stroke beyond the software position limit 0x607D (the target would be clamped, the comparison with
    the offline simulation would fail) is refused; serve: --node-id with --axis and no --config names no axis."""
    r = subprocess.run([sys.executable, "-m", "virtualaxis.cli.main", "demo", "--stroke-mm", "297.5", "--no-pace",
                        "--out", str(tmp_path / "d")], capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "(0, 297]" in r.stderr and "0x607D" in r.stderr, r.stderr
    assert "Traceback" not in r.stderr
    r = subprocess.run([sys.executable, "-m", "virtualaxis.cli.main", "serve", "--can", "virtual:cli-test",
                        "--node-id", "3", "--axis", f"X=2:{SEED000}", "--duration", "0.2"],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "--node-id 3" in r.stderr and "--config" in r.stderr, r.stderr
    assert "Traceback" not in r.stderr


def test_move_file_errors_name_row_and_column(tmp_path):
    moves = tmp_path / "moves.csv"
    moves.write_text("t,pos\n0,0\n0.1,abc\n")
    r = subprocess.run([sys.executable, "-m", "virtualaxis.cli.main", "simulate", "--config", str(SEED000),
                        "--profile", f"file:{moves}", "--out", str(tmp_path / "t.csv")], capture_output=True, text=True)
    assert r.returncode == 2
    assert "moves.csv: row 3: column pos: not a number" in r.stderr
    moves.write_text("t,pos\n0,0\n0.2,0.001\n0.1,0.002\n")
    r = subprocess.run([sys.executable, "-m", "virtualaxis.cli.main", "simulate", "--config", str(SEED000),
                        "--profile", f"file:{moves}", "--out", str(tmp_path / "t.csv")], capture_output=True, text=True)
    assert r.returncode == 2 and "row 4: column t: time must increase" in r.stderr


def test_modal_json(tmp_path):
    js = tmp_path / "m.json"
    assert main(["modal", "--config", str(SEED004), "--positions", "0.1,0.5,0.9", "--json", str(js)]) == 0
    res = json.loads(js.read_text())["results"]
    assert [r["stroke_fraction"] for r in res] == [0.1, 0.5, 0.9]
    for r in res:
        assert r["natural_frequencies_hz"] == sorted(r["natural_frequencies_hz"])
        assert len(r["damping_ratios"]) == len(r["natural_frequencies_hz"])
        assert "nut_position_m" in r
    assert abs(res[1]["natural_frequencies_hz"][0] - 152.0) < 1.0
    js2 = tmp_path / "m2.json"
    assert main(["modal", "--config", str(SEED004), "--json", str(js2)]) == 0
    assert json.loads(js2.read_text())["results"][0]["stroke_fraction"] == 0.5


def test_frf_and_studies_write_tables_and_plots(tmp_path):
    assert main(["frf", "--config", str(SEED000), "--out", str(tmp_path / "frf"), "--points", "100"]) == 0
    assert (tmp_path / "frf" / "frf.csv").exists() and (tmp_path / "frf" / "frf.png").exists()
    assert json.loads((tmp_path / "frf" / "frf.json").read_text())["speed_loop_bandwidth_hz"] > 10
    assert main(["study", "support-stiffness", "--config", str(SEED004), "--out", str(tmp_path / "s")]) == 0
    rows = json.loads((tmp_path / "s" / "support_stiffness.json").read_text())["rows"]
    f = [r["first_natural_frequency_hz"] for r in rows]
    assert f == sorted(f) and f[0] < 152.0 < f[-1]
    assert main(["study", "kv-sweep", "--config", str(SEED004), "--out", str(tmp_path / "k"),
                 "--values", "1000,2725,5000"]) == 0
    doc = json.loads((tmp_path / "k" / "kv_sweep.json").read_text())
    e = [r["energy_per_cycle_j"] for r in doc["rows"]]
    tau = [r["response_time_s"] for r in doc["rows"]]
    assert e[0] < e[-1] and tau[0] > tau[-1]
    assert main(["study", "feed-sweep", "--config", str(SEED000), "--out", str(tmp_path / "f"),
                 "--values", "1000,6000"]) == 0
    assert (tmp_path / "f" / "feed_sweep.csv").exists()
    # every study gives CSV + JSON + PNG (the README's promise)
    assert main(["study", "inverter", "--config", str(SEED000), "--out", str(tmp_path / "i"),
                 "--values", "1000"]) == 0
    for folder, stem in (("s", "support_stiffness"), ("k", "kv_sweep"), ("f", "feed_sweep"), ("i", "inverter")):
        names = {p.name for p in (tmp_path / folder).iterdir()}
        assert {f"{stem}.csv", f"{stem}.json"} <= names and any(n.endswith(".png") for n in names), (stem, names)


def test_the_command_parser_loads_neither_numba_nor_scipy() -> None:
    """Building the parser of every command (``virtualaxis --help``, and the start of each command) imports no
    compiler or optimiser: a command loads its model stack when it runs, so each CLI process starts quickly."""
    code = ("import sys; from virtualaxis.cli.main import build_parser; build_parser(); "
            "print(sorted(m for m in ('numba', 'scipy', 'scipy.optimize', 'canopen', 'matplotlib') "
            "if m in sys.modules))")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert proc.stdout.strip() == "[]", proc.stdout


def test_python_m_virtualaxis_is_the_command():
    import subprocess
    import sys

    p = subprocess.run([sys.executable, "-m", "virtualaxis", "--help"], capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stderr
    assert "serve" in p.stdout and "diagnose" in p.stdout
    p = subprocess.run([sys.executable, "-m", "virtualaxis", "no-such-command"], capture_output=True, text=True,
                       timeout=120)
    assert p.returncode == 2 and "no-such-command" in p.stderr and "Traceback" not in p.stderr
