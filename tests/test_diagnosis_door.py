"""The gap diagnosis as a user runs it: ``virtualaxis diagnose`` in a subprocess, on a terminal (a pty via
``script``) and in a log (no terminal), on cases made by the independent reference axis (``virtualaxis.refaxis``).
"""

from __future__ import annotations

import json
import os
import re
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import background
import numpy as np
import pytest

from virtualaxis.config import load_axis_config
from virtualaxis.diagnosis.trace import read_trace, write_trace
from virtualaxis.refaxis import make_case

SRC = str(Path(__file__).resolve().parents[1] / "src")


def _env() -> dict:
    env = dict(os.environ)
    env["PYTHONPATH"] = SRC + os.pathsep + env.get("PYTHONPATH", "")
    env.pop("VIRTUALAXIS_DEBUG", None)
    return env


def _diagnose_cmd(case, out: Path, *extra: str) -> list[str]:
    return [sys.executable, "-m", "virtualaxis.cli.main", "diagnose", "--config", str(case.config_path),
            *[str(p) for p in case.fit], "--holdout", *[str(p) for p in case.holdout], "--out", str(out), *extra]


def run_pair(root: Path) -> dict:
    """A withheld Coulomb + viscous friction pair on the reference's rigid P/P axis (10 mm stroke): both are
    accepted, so the diagnosis refits them jointly. ``virtualaxis diagnose`` on it twice at once (each on one
    core): in a log (no terminal) and on a terminal (a pty through ``script -qec``). Mass error is a third
    candidate that is screened, not fitted. (Run as a background job of the suite: tests/background.py.)"""
    case = make_case("rigid_pp/coulomb_friction+viscous_friction", root / "pair", seed=5, quick=True)
    if shutil.which("script") is None:
        return {"case": case, "skip": "needs script(1) for a pty"}
    opts = ("--effects", "coulomb_friction,viscous_friction,mass_error", "--no-hybrid", "--jobs", "1")
    log = subprocess.Popen(_diagnose_cmd(case, root / "log", *opts), stdin=subprocess.DEVNULL,
                           stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=_env())
    tty = subprocess.Popen(["script", "-qec", shlex.join(_diagnose_cmd(case, root / "tty", *opts)), "/dev/null"],
                           stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                           env=_env())  # bytes: a bar's carriage returns kept as written
    log_out, log_err = log.communicate(timeout=900)
    tty_out = tty.communicate(timeout=900)[0].decode("utf-8", "replace")
    return {"case": case, "log": (log.returncode, log_out, log_err, root / "log"),
            "tty": (tty.returncode, tty_out, root / "tty")}


@pytest.fixture(scope="module")
def pair(request):
    return background.result(request.config, "door_pair_runs")


@pytest.fixture(scope="module")
def pair_case(pair):
    return pair["case"]


@pytest.fixture(scope="module")
def pair_runs(pair):
    if "skip" in pair:
        pytest.skip(pair["skip"])
    return pair


@pytest.mark.background("door_pair_runs")
def test_a_joint_refit_runs_through_the_cli_on_a_terminal_and_in_a_log(pair_runs):
    rc, log_out, log_err, log_dir = pair_runs["log"]
    trc, tty_out, tty_dir = pair_runs["tty"]
    assert rc == 0, log_err
    assert trc == 0, tty_out
    for d in (log_dir, tty_dir):
        rep = json.loads((d / "report.json").read_text())
        assert rep["accepted"][:1] == ["coulomb_friction"] and "viscous_friction" in rep["accepted"], rep["accepted"]
        assert rep["joint_refit"], "both effects accepted: they are refitted jointly"
    assert "conclusion: coulomb_friction + viscous_friction" in log_out
    assert "conclusion: coulomb_friction + viscous_friction" in tty_out
    # where the nominal model's gap concentrates: the report's most concentrated bin per channel, on the console
    rep = json.loads((log_dir / "report.json").read_text())
    assert any(rep["where_summary"].values()), rep["where_summary"]
    for ch, bins in rep["where_summary"].items():
        if bins:
            assert f"{ch} {100 * bins[0]['share']:.0f} % in {bins[0]['dimension']} {bins[0]['bin']}" in log_out, log_out
    # in a log: a line per stage, none per candidate, no carriage-return bar
    lines = log_err.splitlines()
    assert "\r" not in log_err
    assert "diagnose: round 1: screening 3 candidates" in lines, log_err
    assert any(re.match(r"diagnose: round \d+: joint refit of coulomb_friction \+ viscous_friction", ln)
               for ln in lines), log_err
    assert not any(re.search(r"\d+/\d+", ln) for ln in lines), log_err
    assert len([ln for ln in lines if ln.startswith("diagnose: ")]) <= 16, log_err
    # on a terminal: a bar that advances per candidate
    assert "\r" in tty_out and re.search(r"screening 3 candidates: +100%", tty_out), tty_out


@pytest.mark.background("door_pair_runs")
def test_the_report_shows_each_stage_of_the_diagnosis_in_order(pair_runs):
    """report.json["stages"]: load -> check -> baseline -> localise -> per round screen, refine, judge (and the
    pair or refit that accepted) -> verify -> report, each with what it decided; nothing private in the file."""
    rc, _, log_err, d = pair_runs["log"]
    assert rc == 0, log_err
    rep = json.loads((d / "report.json").read_text())
    stages = rep["stages"]
    names = [s["stage"] for s in stages]
    assert names[:4] == ["load", "check", "baseline", "localise"], names
    assert names[-2:] == ["verify", "report"], names
    assert names[4:7] == ["screen", "refine", "judge"], names
    assert stages[0]["fit"] == [t["name"] for t in rep["traces"] if t["role"] == "fit"]
    assert stages[0]["holdout"] == [t["name"] for t in rep["traces"] if t["role"] == "holdout"]
    screen1 = stages[4]
    assert screen1["round"] == 1
    assert set(screen1["candidates"]) == {"coulomb_friction", "viscous_friction", "mass_error"}
    # every round's stages carry its number, rounds in order
    rounds = [s["round"] for s in stages if "round" in s]
    assert rounds == sorted(rounds) and rounds[0] == 1
    # each accepted effect was chosen by a stage: a judgement's best, a pair, or a joint refit kept
    chosen = ({s["best"] for s in stages if s["stage"] == "judge"}
              | {e for s in stages if s["stage"] == "pair" for e in s["accepted"]}
              | {s["effect"] for s in stages if s["stage"] == "joint_refit" and s["kept"]})
    assert set(rep["accepted"]) <= chosen, stages
    refits = [s for s in stages if s["stage"] == "refit"]
    assert all(set(s["effects"]) <= set(rep["accepted"]) | set(s["removed"]) for s in refits), refits
    assert stages[-1]["conclusion"] == rep["conclusion"]
    assert not [k for k in rep if k.startswith("_")]


@pytest.mark.background("door_pair_runs")
def test_the_report_reads_in_engineering_units_and_edits_only_the_fitted_values(pair_case, pair_runs):
    rc, out, err, d = pair_runs["log"]
    assert rc == 0, err
    # headline: the config's value -> fitted +- standard error in the parameter's unit, the held-out position
    # error change (the withheld total is 20 N + 200 N s/m)
    nominal = load_axis_config(pair_case.config_path).friction
    assert re.search(rf"^  coulomb_friction: coulomb_n {nominal.coulomb_n:.3g} -> (19|20|21)(\.\d+)? \+- [0-9.]+ N; "
                     r"held-out position error -\d+ %$", out, re.M), out
    assert re.search(rf"^  viscous_friction: viscous_n_s_per_m {nominal.viscous_n_s_per_m:.3g} -> \d+(\.\d+)? "
                     r"\+- [0-9.]+ N s/m; held-out position error -\d+ %$", out, re.M), out
    assert re.search(r"pos_meas \d[0-9.]* -> \d[0-9.]* [un]m", out), out  # RMSE in um / nm, not 1.48e-04
    assert "e-0" not in out, out
    rep = json.loads((d / "report.json").read_text())
    # a candidate that was only screened shows no fitted values
    mass = next(e for e in rep["effects"] if e["name"] == "mass_error")
    assert mass["fitted"] is False and mass["params"] == {} and mass["heldout"]["gain"] is None, mass
    assert mass["relative_change"] is None and "screened only" in mass["not_fitted"]
    html = (d / "report.html").read_text()
    row = re.search(r"<tr><td>\d+</td><td>mass_error</td>.*?</tr>", html).group(0)
    cells = re.findall(r"<td>(.*?)</td>", row)
    assert cells[2:7] == ["no", "-", "-", "-", "-"] and "screened only" in cells[7], cells  # no figures, no "new"
    assert " kg" not in row, row
    # calibrated.toml: the input's text with only the fitted lines changed, and it loads to the fitted values
    original = Path(pair_case.config_path).read_text().splitlines()
    calibrated = (d / "calibrated.toml").read_text().splitlines()
    assert len(calibrated) == len(original)
    changed = [(a, b) for a, b in zip(original, calibrated, strict=True) if a != b]
    assert {a.split("=")[0].strip() for a, _ in changed} == {"coulomb_n", "viscous_n_s_per_m"}, changed
    assert all(b.endswith("}") and "gap diagnosis" in b for _, b in changed), changed
    cal = load_axis_config(d / "calibrated.toml")
    fitted = {e["name"]: e["params"] for e in rep["effects"] if e["accepted"]}
    assert cal.friction.coulomb_n == pytest.approx(fitted["coulomb_friction"]["coulomb_n"]["value"], rel=1e-12)
    assert cal.friction.viscous_n_s_per_m == pytest.approx(
        fitted["viscous_friction"]["viscous_n_s_per_m"]["value"], rel=1e-12)
    diff = rep["calibrated_diff"]
    assert sum(1 for ln in diff if ln.startswith("+") and not ln.startswith("+++")) == 2, diff
    # a trace written by `virtualaxis simulate` draws no warning about its columns
    assert not [w for w in rep["warnings"] if "column" in w], rep["warnings"]


def _shift(src: Path, dst: Path, offset_m: float) -> None:
    tr = read_trace(str(src))
    cols = {"t": tr.t, **{k: (v + offset_m if k in ("pos_cmd", "pos_meas", "pos_fb") else v)
                          for k, v in tr.columns.items()}}
    write_trace(dst, cols)


def _run(cmd: list[str]) -> subprocess.CompletedProcess:
    return subprocess.run(cmd, stdin=subprocess.DEVNULL, capture_output=True, text=True, env=_env(), timeout=600,
                          check=False)


def beyond_the_end_stops(tmp_path: Path) -> dict:
    """``virtualaxis diagnose`` on traces that run 3 mm beyond the model's end stop (a background job of the
    suite: tests/background.py)."""
    case = make_case("rigid_pp/coulomb_friction", tmp_path / "case", seed=1, quick=True)
    cfg = load_axis_config(case.config_path)
    from virtualaxis.sim.simulator import end_stops

    hi = end_stops(cfg)[1]
    offset = hi + 0.003 - 0.005  # the +-5 mm moves end 3 mm beyond the end stop
    moved = tmp_path / "moved"
    moved.mkdir()
    for p in [*case.fit, *case.holdout]:
        _shift(Path(p), moved / Path(p).name, offset)
    fit = [str(moved / Path(p).name) for p in case.fit]
    hold = [str(moved / Path(p).name) for p in case.holdout]
    r = _run([sys.executable, "-m", "virtualaxis.cli.main", "diagnose", "--config", str(case.config_path), *fit,
              "--holdout", *hold, "--out", str(tmp_path / "o"), "--effects", "coulomb_friction", "--no-hybrid",
              "--jobs", "1"])
    return {"hi": hi, "rc": r.returncode, "stdout": r.stdout, "stderr": r.stderr, "out": tmp_path / "o"}


@pytest.mark.background("beyond_the_end_stops")
def test_traces_beyond_the_models_end_stops_are_refused_naming_the_stroke(request):
    """The axis ran to +0.40 m while the config's stroke puts the model's end stop at +0.39 m: the nominal
    model cannot follow, and the diagnosis says so instead of fitting effects to the difference."""
    job = background.result(request.config, "beyond_the_end_stops")
    hi = job["hi"]
    assert job["rc"] == 2, (job["stdout"], job["stderr"])
    err = [ln for ln in job["stderr"].splitlines() if ln.startswith("error:")]
    assert len(err) == 1 and "Traceback" not in job["stderr"], job["stderr"]
    msg = err[0]
    assert "axis.stroke_m" in msg and "end stops" in msg and "pos_cmd" in msg, msg
    assert f"{hi:+.4g}" in msg, msg  # the model's end stop in metres
    assert "conclusion" not in job["stdout"] and not (job["out"] / "report.json").exists()


def test_a_nominal_model_that_cannot_follow_the_motion_is_refused_before_any_fit(tmp_path):
    """The config's drive force limit is below its own Coulomb friction: the model's table does not move while
    the measured one follows its command. No effect reaches a gap of the whole move."""
    case = make_case("rigid_pp/coulomb_friction", tmp_path / "case", seed=2, quick=True)
    text = Path(case.config_path).read_text()
    weak = re.sub(r"force_limit_n = \{ value = [0-9.eE+-]+", "force_limit_n = { value = 20.0", text)
    assert weak != text
    cfg_path = tmp_path / "weak.toml"
    cfg_path.write_text(weak)
    r = _run([sys.executable, "-m", "virtualaxis.cli.main", "diagnose", "--config", str(cfg_path),
              *[str(p) for p in case.fit], "--holdout", *[str(p) for p in case.holdout], "--out",
              str(tmp_path / "o"), "--effects", "coulomb_friction,mass_error", "--no-hybrid", "--jobs", "1"])
    assert r.returncode == 2, (r.stdout, r.stderr)
    err = [ln for ln in r.stderr.splitlines() if ln.startswith("error:")]
    assert len(err) == 1 and "Traceback" not in r.stderr, r.stderr
    msg = err[0]
    assert str(cfg_path) in msg and "does not follow the measured motion" in msg, msg
    assert re.search(r"pos_meas misses the measurement by [0-9.]+ mm RMS", msg), msg
    assert re.search(r"force_drive [0-9.]+ N RMS", msg), msg
    assert re.search(r"drive sits at its limit actuator\.force_limit_n = 20 N for \d+ % of the trace", msg), msg
    assert not (tmp_path / "o" / "report.json").exists()


def simulate_then_diagnose(root: Path) -> dict:
    """Traces made with ``virtualaxis simulate`` (with ``--extras``: every internal signal), diagnosed against
    the config that made them (a background job of the suite: tests/background.py)."""
    case = make_case("rigid_pp/clean", root / "case", seed=3, quick=True)
    paths, simulated = [], []
    for feed, extras in ((1000, ()), (6000, ()), (3000, ("--extras",))):
        out = root / f"sine_F{feed}.csv"
        r = _run([sys.executable, "-m", "virtualaxis.cli.main", "simulate", "--config", str(case.config_path),
                  "--profile", f"sine:stroke_mm=10,feed_mm_min={feed}", "--duration", "1.5", "--out", str(out),
                  *extras])
        simulated.append((r.returncode, r.stderr))
        paths.append(str(out))
    r = _run([sys.executable, "-m", "virtualaxis.cli.main", "diagnose", "--config", str(case.config_path),
              paths[0], paths[1], "--holdout", paths[2], "--out", str(root / "o"), "--effects",
              "coulomb_friction", "--no-hybrid", "--jobs", "1"])
    return {"simulated": simulated, "paths": paths, "rc": r.returncode, "stdout": r.stdout, "stderr": r.stderr,
            "out": root / "o"}


@pytest.mark.background("simulate_then_diagnose")
def test_traces_written_by_virtualaxis_simulate_draw_no_column_warnings(request):
    """Traces made with ``virtualaxis simulate`` (with ``--extras``: every internal signal) are diagnosed
    against the config that made them: nothing is found, and no column the simulator writes is warned about."""
    job = background.result(request.config, "simulate_then_diagnose")
    for rc, err in job["simulated"]:
        assert rc == 0, err
    paths = job["paths"]
    assert job["rc"] == 0, job["stderr"]
    assert "conclusion: no significant effect" in job["stdout"], job["stdout"]
    assert "following_error" in Path(paths[0]).read_text().splitlines()[0]
    assert not [ln for ln in job["stderr"].splitlines() if ln.startswith("warning:") and "column" in ln], job["stderr"]
    rep = json.loads((job["out"] / "report.json").read_text())
    assert not [w for w in rep["warnings"] if "column" in w], rep["warnings"]


def test_calibrated_text_keeps_the_layout_and_loads_to_the_fitted_values(tmp_path):
    """The line edit behind calibrated.toml: a plain value keeps its comment, an inline table with a unit gets the
    SI value, a key and a section the input lacks are added; the rest of the text is unchanged."""
    from virtualaxis.diagnosis.calibrated import edit_config_text

    text = (Path(__file__).resolve().parents[1] / "configs" / "examples" / "rigid-force-axis.toml").read_text()
    text = re.sub(r"(?m)^coulomb_n = .*$", "coulomb_n = 25.0   # slow reversal test, both directions", text)
    text = re.sub(r"(?m)^viscous_n_s_per_m = .*$", 'viscous_n_s_per_m = { value = 0.15, unit = "N s/mm" }', text)
    assert "[effects]" not in text and "stribeck_n" not in text
    src = tmp_path / "in.toml"
    src.write_text(text)
    base = load_axis_config(src)
    assert base.friction.viscous_n_s_per_m == pytest.approx(150.0)
    changes = {"friction.coulomb_n": 31.25, "friction.viscous_n_s_per_m": 210.5,
               "friction.stribeck_n": 7.5, "effects.thermal_expansion_per_k": 1.15e-05}
    out = edit_config_text(text, changes, {k: "gap diagnosis (test)" for k in changes})
    a, b = text.splitlines(), out.splitlines()
    changed = [ln for ln in b if ln not in a]
    assert [ln for ln in a if ln not in b] == [ln for ln in a if ln.startswith(("coulomb_n ", "viscous_n_s_per_m "))]
    assert "coulomb_n = { value = 31.25, source = \"gap diagnosis (test)\" }   # slow reversal test, both " \
           "directions" in changed
    assert len(changed) == 5, changed  # two edited, stribeck_n added, [effects] and its key added
    cal_path = tmp_path / "cal.toml"
    cal_path.write_text(out)
    cal = load_axis_config(cal_path)
    assert cal.friction.coulomb_n == 31.25 and cal.friction.viscous_n_s_per_m == 210.5
    assert cal.friction.stribeck_n == 7.5 and cal.effects.thermal_expansion_per_k == 1.15e-05
    assert cal.mechanics == base.mechanics and cal.control == base.control


def test_a_trace_that_starts_moving_keeps_its_motor_encoder_zero(tmp_path):
    """A trace cut from a run while the axis moves (the model starts at rest on the command): the motor encoder's
    zero is found from the measured table position beside it, not from the model's angle at the first sample,
    which would take the following error there for the zero and leave motor_pos off by it for the whole trace.
    The case is the independent reference axis's (two-mass, Coulomb friction withheld)."""
    case = make_case("two_mass/coulomb_friction", tmp_path / "case", seed=4, quick=True)
    tr = read_trace(case.fit[0])
    v = np.gradient(tr.pos_cmd, tr.dt_s)
    k = int(np.argmax(np.abs(v) > 0.5 * np.abs(v).max()))  # the first sample at half the top speed
    moving = tmp_path / "moving.csv"
    write_trace(moving, {"t": tr.t[k:] - tr.t[k], **{c: x[k:] for c, x in tr.columns.items()}})
    r = _run([sys.executable, "-m", "virtualaxis.cli.main", "diagnose", "--config", str(case.config_path),
              str(moving), "--out", str(tmp_path / "o"), "--effects", "coulomb_friction", "--no-hybrid",
              "--jobs", "1"])
    assert r.returncode == 0, r.stderr
    assert "starts moving" in r.stderr and "offset" not in r.stderr, r.stderr
    baseline = json.loads((tmp_path / "o" / "report.json").read_text())["baseline"]
    # the nominal model's motor angle misses by its dynamics (~0.2 mrad here), not by the start's following
    # error taken for an encoder offset (6 mrad)
    assert baseline["motor_pos"]["rmse"] < 1e-3, baseline["motor_pos"]
    assert "fit RMSE per channel" in r.stdout and "held-out" not in r.stdout, r.stdout  # (one trace: no held-out)
