"""The speed feed-forward form a drive uses: the command's derivative (our simulator's default) or the
difference of consecutive set-points held for the next position cycle (a CSP drive). Judged closed-loop on traces
of the independent reference axis (``virtualaxis.refaxis``, which uses the set-point difference) and on traces of
our own simulator (the derivative); no parameter is fitted, so the check cannot absorb a plant effect."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from virtualaxis.config import load_axis_config
from virtualaxis.diagnosis.data import TraceData, default_simulate
from virtualaxis.diagnosis.pipeline import check_feedforward_form
from virtualaxis.diagnosis.trace import read_trace
from virtualaxis.refaxis import make_case
from virtualaxis.sim.batch import backward_difference, simulate_command


def _tds(cfg, paths) -> list[TraceData]:
    return [TraceData.from_trace(read_trace(str(p), cfg.axis.name)) for p in paths]


def test_backward_difference_is_the_set_point_difference():
    x = np.array([0.0, 1e-3, 3e-3, 6e-3])
    assert backward_difference(x, 1e-3).tolist() == pytest.approx([0.0, 1.0, 2.0, 3.0])


@pytest.fixture(scope="module")
def backlash_case(tmp_path_factory):
    return make_case("two_mass/backlash", tmp_path_factory.mktemp("ff"), seed=3, quick=True)


def test_a_csp_drives_set_point_difference_is_found_beside_a_withheld_plant_effect(backlash_case):
    cf = backlash_case
    cfg = load_axis_config(cf.config_path)
    assert cfg.control.velocity_ff_form == "derivative" and cfg.control.velocity_ff_factor > 0
    fit, hold = cf.fit[:2] + cf.fit[3:], cf.holdout[:2]  # sines and the rapid; two held-out sines
    tds = _tds(cfg, fit + hold)
    out = check_feedforward_form(cfg, tds, default_simulate, list(range(len(fit))),
                                 list(range(len(fit), len(tds))))
    assert out["used"] == "setpoint_difference", out
    trial = out["trials"]["setpoint_difference"]
    # the backlash stays in the residual, the form's acceleration-proportional following error goes
    assert trial["ratio_fit"] < 0.7 and trial["ratio_heldout"] < 0.7
    assert trial["verdict_heldout"]["channels"]["pos_fb"]["ratio"] < 0.2
    assert all(td.overrides["control"]["velocity_ff_form"] == "setpoint_difference" for td in tds)


def test_our_own_simulators_derivative_is_kept(backlash_case, tmp_path: Path):
    """Traces made by our simulator with the config's form (the derivative): the other form is clearly worse."""
    cfg = load_axis_config(backlash_case.config_path)
    tds = []
    for k, p in enumerate(backlash_case.fit[:2] + backlash_case.holdout[:1]):
        tr = read_trace(str(p), cfg.axis.name)
        sim = simulate_command(cfg, tr.t, tr.pos_cmd, seed=k)
        tds.append(TraceData(tr.name, tr.t, tr.pos_cmd, None,
                             {ch: sim[ch] for ch in ("pos_meas", "pos_fb", "current_q") if ch in sim}))
    out = check_feedforward_form(cfg, tds, default_simulate, [0, 1], [2])
    assert out["used"] == "derivative", out
    assert out["trials"]["setpoint_difference"]["ratio_fit"] > 1.0
    assert all("control" not in td.overrides for td in tds)


def test_no_check_without_speed_feed_forward(backlash_case):
    cfg = load_axis_config(backlash_case.config_path).replace(control={"velocity_ff_factor": 0.0})
    assert check_feedforward_form(cfg, _tds(cfg, backlash_case.fit[:1]), default_simulate, [0], []) is None
