"""How a trace records the axis: one-sample channel shifts, the speed estimator's form and a start transient are
found from the nominal model's prediction, applied to every later prediction and reported.

The "measured" traces come from the small P/P-cascade simulator of ``test_diagnosis_controller`` (written apart
from virtualaxis); the model is our rigid force axis with that controller (the check would identify it)."""

from __future__ import annotations

import numpy as np
import pytest
from test_diagnosis_controller import RIGID, pp_cascade_trace

from virtualaxis.config import load_axis_config
from virtualaxis.diagnosis.alignment import apply_post, find_alignment, find_start_transient
from virtualaxis.diagnosis.data import TraceData, default_simulate, simulate_trace


@pytest.fixture(scope="module")
def model_and_trace():
    cfg = load_axis_config(RIGID).replace(control={"kv_per_s": 25.0, "velocity_kp_n_s_per_m": 5000.0,
                                                   "speed_ti_s": 0.0},
                                          friction={"enabled": True, "coulomb_n": 40.0, "viscous_n_s_per_m": 100.0},
                                          mechanics={"table_mass_kg": 80.0})
    cols = pp_cascade_trace(3000.0, 2.0)
    return cfg, cols


def _td(cols: dict, **extra) -> TraceData:
    measured = {k: np.asarray(v, float) for k, v in cols.items() if k not in ("t", "pos_cmd")}
    measured.update(extra)
    return TraceData("sine", cols["t"], cols["pos_cmd"], None, measured)


def test_a_force_channel_one_sample_out_of_step_is_found_and_aligned(model_and_trace):
    # the force recorded with the model's own convention plus chatter-sized noise, then moved by one sample: the
    # detector must find the move (and only where there is one); the position channel is the measured one
    cfg, cols = model_and_trace
    fast = pp_cascade_trace(8000.0, 1.5)
    td0 = _td(fast)
    pred = simulate_trace(cfg, td0, default_simulate)
    rng = np.random.default_rng(1)
    own = pred["force_drive"] + rng.normal(0.0, 1.0, pred["force_drive"].size)
    td = _td(fast, force_drive=own)
    assert not [f for f in find_alignment([td], [pred]) if f["kind"] == "channel_shift"]
    for s in (1, -1):
        shifted = np.roll(own, s)
        td = _td(fast, force_drive=shifted)
        found = find_alignment([td], [simulate_trace(cfg, td, default_simulate)])
        shift = [f for f in found if f["kind"] == "channel_shift"]
        assert shift and shift[0]["channel"] == "force_drive" and shift[0]["samples"] == s, found
        after = simulate_trace(cfg, td, default_simulate)  # td.post applies from now on
        r_before = np.std(shifted[5:-5] - pred["force_drive"][5:-5])
        r_after = np.std(shifted[5:-5] - after["force_drive"][5:-5])
        assert r_after < 0.7 * r_before


def test_a_chatter_that_either_move_lines_up_is_no_recording_shift(model_and_trace):
    """A quantised force loop chatters in the model and on the axis, one sample out of phase: a move of the
    prediction by one sample either way lines the chatter up and lowers the residual alike, which is no
    recording convention (a docs-only tester's own simulator drew "one sample earlier" on one set of traces and
    "one sample later" on another, at 12-16 standard errors); a real move still shows one way."""
    cfg, _cols = model_and_trace
    fast = pp_cascade_trace(8000.0, 1.5)
    td0 = _td(fast)
    pred = simulate_trace(cfg, td0, default_simulate)
    k = np.arange(pred["force_drive"].size)
    chatter = 20.0 * np.where(k % 2 == 0, 1.0, -1.0)
    chattering = dict(pred, force_drive=pred["force_drive"] + chatter)
    td = _td(fast, force_drive=pred["force_drive"] - chatter)
    assert not [f for f in find_alignment([td], [chattering]) if f["kind"] == "channel_shift"]


def test_an_axis_already_moving_at_the_first_sample_is_named_and_its_transient_excluded(model_and_trace):
    cfg, cols = model_and_trace
    k0 = 250  # start the recording mid-motion
    late = {k: (v[k0:] - v[k0] * (k == "t")) if k != "t" else v[k0:] - v[k0] for k, v in cols.items()}
    td = _td(late)
    pred = simulate_trace(cfg, td, default_simulate)
    st = find_start_transient(td, pred)
    assert st is not None and 0 < st["samples"] <= td.t.size // 5, st
    post = apply_post(td, pred)
    assert np.all(post["pos_meas"][: st["samples"]] == td.measured["pos_meas"][: st["samples"]])
    clean = _td(cols)
    assert find_start_transient(clean, simulate_trace(cfg, clean, default_simulate)) is None
