"""The controller's timing as part of the nominal a user states: ``control.output_delay_s`` (the speed loop applies
its output that long after its samples; one speed cycle = "sample at k, compute, apply at k+1") and
``control.speed_estimator``. Checked on traces of the independent reference axis (``virtualaxis.refaxis``, rigid
P/P cascade with both loops at 1 kHz, its own output-delay implementation): the simulator, the controller check's
replay and ``virtualaxis diagnose`` (CLI in a subprocess)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import background
import numpy as np
import pytest

from virtualaxis.config import load_axis_config
from virtualaxis.diagnosis.controller import check_controller
from virtualaxis.diagnosis.data import TraceData, default_simulate, noiseless, simulate_trace
from virtualaxis.diagnosis.trace import read_trace
from virtualaxis.refaxis import cases as C


def _case(root: Path, delay_cycles: int, stated: bool, estimator_samples: int = 1) -> C.CaseFiles:
    """Clean reference traces (10 mm sines F1000 / F6000, the rapid; held out F2000 / F4000) of a controller with
    that output delay and speed estimator; the config states the estimator, and the delay when ``stated``."""
    fit, hold = C.conditions("rigid_pp", True)
    truth = {"output_delay_cycles": float(delay_cycles), "speed_estimator_samples": float(estimator_samples)}
    config = dict(truth, output_delay_cycles=float(delay_cycles) if stated else 0.0)
    return C.write_axis_case(root, "rigid_pp", truth, config, fit[:2] + fit[3:], hold[:2], seed=5,
                             name=f"timing-{delay_cycles}-{estimator_samples}")


@pytest.fixture(scope="module")
def delayed(tmp_path_factory) -> C.CaseFiles:
    return _case(tmp_path_factory.mktemp("delay1"), 1, stated=True)


def _diagnose(cf: C.CaseFiles, out: Path) -> tuple[int, str, str]:
    p = subprocess.run([sys.executable, "-m", "virtualaxis.cli.main", "diagnose", "--config", str(cf.config_path),
                        *map(str, cf.fit), "--holdout", *map(str, cf.holdout), "--out", str(out), "--no-hybrid"],
                       capture_output=True, text=True, timeout=900)
    return p.returncode, p.stdout, p.stderr


def test_output_delay_not_a_whole_number_of_speed_cycles_is_an_error(delayed, tmp_path: Path):
    text = delayed.config_path.read_text().replace("output_delay_s = { value = 0.001",
                                                   "output_delay_s = { value = 0.0015")
    assert text != delayed.config_path.read_text()
    bad = tmp_path / "bad.toml"
    bad.write_text(text)
    rc, out, err = _diagnose(C.CaseFiles("bad", bad, delayed.fit, delayed.holdout, {}), tmp_path / "d")
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert rc == 2 and len(lines) == 1 and lines[0].startswith("error:"), err
    assert "control.output_delay_s" in lines[0] and "whole speed cycles" in lines[0] and "Traceback" not in err


def test_the_simulator_with_the_stated_delay_follows_the_reference(delayed):
    """Our simulator with ``output_delay_s`` = one speed cycle reproduces the reference's following error and
    force to the sensor level; without it the gap is many times larger (the loop is one cycle slower)."""
    cfg = noiseless(load_axis_config(delayed.config_path))
    assert cfg.control.output_delay_s == pytest.approx(cfg.control.speed_cycle_s)
    tr = read_trace(str(delayed.fit[1]), cfg.axis.name)  # sine F6000
    td = TraceData.from_trace(tr)
    gaps = {}
    for name, c in (("stated", cfg), ("none", cfg.replace(control={"output_delay_s": 0.0}))):
        pred = simulate_trace(c, td, default_simulate)
        gaps[name] = {ch: float(np.sqrt(np.mean((pred[ch] - td.measured[ch]) ** 2)))
                      for ch in ("pos_meas", "force_drive")}
    assert gaps["stated"]["pos_meas"] < 0.5e-6, gaps
    assert gaps["none"]["pos_meas"] > 3 * gaps["stated"]["pos_meas"], gaps


@pytest.mark.parametrize("estimator_samples", [1, 2])
def test_the_controller_replay_uses_the_stated_timing(tmp_path: Path, estimator_samples: int):
    """The controller check replays the config's law with its output delay and speed estimator: the config's own
    gains explain the force of a delayed controller when the delay is stated, and clearly worse when it is not."""
    cf = _case(tmp_path, 1, stated=True, estimator_samples=estimator_samples)
    cfg = load_axis_config(cf.config_path)
    tr = read_trace(str(cf.fit[0]), cfg.axis.name)
    stated = check_controller(cfg, tr.name, tr.t, tr.pos_cmd, tr.columns)
    unstated = check_controller(cfg.replace(control={"output_delay_s": 0.0}), tr.name, tr.t, tr.pos_cmd, tr.columns)
    assert stated is not None and unstated is not None
    assert stated.unexplained_config < 0.02, stated.as_dict()
    assert unstated.unexplained_config > 5 * stated.unexplained_config, (stated.as_dict(), unstated.as_dict())
    assert stated.used == "config"


def diagnose_delayed(root: Path) -> dict:
    """``virtualaxis diagnose`` on a clean trace of a controller with a one-cycle output delay stated in the
    config (a background job of the suite: tests/background.py)."""
    rc, out, err = _diagnose(_case(root / "delay1", 1, stated=True), root / "d")
    return {"rc": rc, "stderr": err, "out": root / "d"}


@pytest.mark.background("diagnose_delayed")
def test_a_clean_trace_of_a_delayed_controller_stated_in_the_config_shows_no_effect(request):
    job = background.result(request.config, "diagnose_delayed")
    assert job["rc"] == 0, job["stderr"]
    tmp_path = job["out"].parent
    rep = json.loads((tmp_path / "d" / "report.json").read_text())
    assert rep["accepted"] == [] or not rep["accepted"], rep["conclusion"]
    assert not [e["name"] for e in rep["effects"] if e["accepted"]], rep["conclusion"]
    cal = (tmp_path / "d" / "calibrated.toml").read_text()
    assert "output_delay_s" in cal


def test_the_gain_a_sensor_can_resolve():
    """``Weights.resolution`` is what the sensor resolves, sqrt(noise^2 + quantum^2 / 12); a model change is judged
    by the rms it removes in those units: a 20 nm grid with 40 nm white noise (a linear scale) -> 40.4 nm; a residual
    of 30 nm rms cut to 10 nm removes 28 nm (< 1: not resolved), one of 300 nm cut to 100 nm removes 283 nm (7x)."""
    from virtualaxis.diagnosis.data import Weights, weighted_ssr
    from virtualaxis.diagnosis.selection import MIN_RESOLVED_REMOVAL

    rng = np.random.default_rng(0)
    n = 20000
    noise = rng.normal(0.0, 40e-9, n)
    q = 2e-8
    measured = np.round(noise / q) * q + 1e-6 * np.sin(np.arange(n) / 500)  # white noise on a grid + a smooth gap
    w = Weights.from_residuals([{"pos_meas": measured}], {"pos_meas": q})
    assert w.resolution["pos_meas"] == pytest.approx(np.hypot(40e-9, q / np.sqrt(12)), rel=0.15)
    counts = {"pos_meas": n}
    for before_rms, after_rms, resolved in ((30e-9, 10e-9, False), (300e-9, 100e-9, True)):
        b = weighted_ssr([{"pos_meas": np.full(n, before_rms)}], w)
        a = weighted_ssr([{"pos_meas": np.full(n, after_rms)}], w)
        ratio = w.resolved_removal(b, a, counts)["pos_meas"]
        assert ratio == pytest.approx(np.sqrt(before_rms**2 - after_rms**2) / w.resolution["pos_meas"], rel=1e-9)
        assert (ratio >= MIN_RESOLVED_REMOVAL) == resolved
