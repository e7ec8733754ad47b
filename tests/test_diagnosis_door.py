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


@pytest.fixture(scope="module")
def pair_case(tmp_path_factory):
    """A withheld Coulomb + viscous friction pair on the reference's rigid P/P axis (10 mm stroke): both are
    accepted, so the diagnosis refits them jointly."""
    return make_case("rigid_pp/coulomb_friction+viscous_friction", tmp_path_factory.mktemp("pair"), seed=5,
                     quick=True)


@pytest.mark.skipif(shutil.which("script") is None, reason="needs script(1) for a pty")
def test_a_joint_refit_runs_through_the_cli_on_a_terminal_and_in_a_log(pair_case, tmp_path):
    opts = ("--effects", "coulomb_friction,viscous_friction", "--no-hybrid", "--jobs", "1")
    log_cmd = _diagnose_cmd(pair_case, tmp_path / "log", *opts)
    tty_cmd = ["script", "-qec", shlex.join(_diagnose_cmd(pair_case, tmp_path / "tty", *opts)), "/dev/null"]
    # both at once (each fits on one core)
    log = subprocess.Popen(log_cmd, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                           text=True, env=_env())
    tty = subprocess.Popen(tty_cmd, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                           text=True, env=_env())
    log_out, log_err = log.communicate(timeout=600)
    tty_out, _ = tty.communicate(timeout=600)
    assert log.returncode == 0, log_err
    assert tty.returncode == 0, tty_out
    for d in ("log", "tty"):
        rep = json.loads((tmp_path / d / "report.json").read_text())
        assert rep["accepted"][:1] == ["coulomb_friction"] and "viscous_friction" in rep["accepted"], rep["accepted"]
        assert rep["joint_refit"], "both effects accepted: they are refitted jointly"
    assert "conclusion: coulomb_friction + viscous_friction" in log_out
    assert "conclusion: coulomb_friction + viscous_friction" in tty_out
    # in a log: a line per stage, none per candidate, no carriage-return bar
    lines = log_err.splitlines()
    assert "\r" not in log_err
    assert any(re.fullmatch(r"diagnose: round 1: screening 2 candidates", ln) for ln in lines), log_err
    assert any(ln.startswith("diagnose: round 2: joint refit of coulomb_friction + viscous_friction")
               for ln in lines), log_err
    assert not any(re.search(r"\d+/\d+", ln) for ln in lines), log_err
    stage_lines = [ln for ln in lines if ln.startswith("diagnose: ")]
    assert len(stage_lines) <= 16, log_err
    # on a terminal: a bar that advances per candidate
    assert "\r" in tty_out and re.search(r"screening 2 candidates: +100%", tty_out), tty_out


def _shift(src: Path, dst: Path, offset_m: float) -> None:
    tr = read_trace(str(src))
    cols = {"t": tr.t, **{k: (v + offset_m if k in ("pos_cmd", "pos_meas", "pos_fb") else v)
                          for k, v in tr.columns.items()}}
    write_trace(dst, cols)


def _run(cmd: list[str]) -> subprocess.CompletedProcess:
    return subprocess.run(cmd, stdin=subprocess.DEVNULL, capture_output=True, text=True, env=_env(), timeout=600,
                          check=False)


def test_traces_beyond_the_models_end_stops_are_refused_naming_the_stroke(tmp_path):
    """The axis ran to +0.40 m while the config's stroke puts the model's end stop at +0.39 m: the nominal
    model cannot follow, and the diagnosis says so instead of fitting effects to the difference."""
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
    assert r.returncode == 2, (r.stdout, r.stderr)
    err = [ln for ln in r.stderr.splitlines() if ln.startswith("error:")]
    assert len(err) == 1 and "Traceback" not in r.stderr, r.stderr
    msg = err[0]
    assert "axis.stroke_m" in msg and "end stops" in msg and "pos_cmd" in msg, msg
    assert f"{hi:+.4g}" in msg, msg  # the model's end stop in metres
    assert "conclusion" not in r.stdout and not (tmp_path / "o" / "report.json").exists()


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
    assert "force or current limit" in msg, msg
    assert not (tmp_path / "o" / "report.json").exists()
