"""The fast subset of the gap bench (withheld-effect cases with a known answer), the CLI and the report
schema. The whole bench runs from benchmarks/bench_gap.py."""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import background
import pytest

from virtualaxis.cli.main import main
from virtualaxis.diagnosis import NO_EFFECT
from virtualaxis.diagnosis.bench import QUICK_CASES, all_cases, generate_case
from virtualaxis.diagnosis.report import REQUIRED_KEYS


@pytest.fixture(scope="module")
def quick_bench(request):
    """``run_bench(out, seed=3, quick=True, jobs=2)``, computed in the background (tests/background.py)."""
    return background.result(request.config, "quick_bench")


def _case(bench: dict, name: str) -> dict:
    return next(c for c in bench["cases"] if c["case"] == name)


@pytest.mark.slow
@pytest.mark.background("quick_bench")
@pytest.mark.parametrize("name", [n for n in QUICK_CASES if n != "clean"])
def test_withheld_effect_is_identified(quick_bench, name):
    ev = _case(quick_bench, name)
    assert ev["accepted"][:1] == ev["truth"], ev
    for key, rec in ev["param_recovery"].items():
        assert rec["rel_error"] < 0.15, (key, rec)
    assert ev["param_recovery"], "the withheld parameter must be reported"
    # the goal: held-out RMSE shrinks by >= 60 % where an effect was withheld
    assert max(ev["heldout_rmse_shrink"].values()) >= 0.6, ev["heldout_rmse_shrink"]


@pytest.mark.slow
@pytest.mark.background("quick_bench")
def test_clean_case_says_no_significant_effect(quick_bench, tmp_path):
    ev = _case(quick_bench, "clean")
    assert ev["accepted"] == [] and not ev["false_positive"]
    assert quick_bench["summary"]["false_positive_rate"] == 0.0


@pytest.mark.background("rigid_force_diagnosis")
def test_cli_diagnose_on_a_rigid_force_axis(request):
    """A rigid single-mass axis with a force-output controller, only scale position + force recorded.
    (``virtualaxis diagnose --jobs 1`` on the rigid-coulomb case, run in the background.)"""
    job = background.result(request.config, "rigid_force_diagnosis")
    rc, text, out = job["rc"], job["stdout"], job["out"]
    assert rc == 0, job["stderr"]
    assert "conclusion: coulomb_friction" in text
    rep = json.loads((out / "report.json").read_text())
    for key in REQUIRED_KEYS:
        assert key in rep
    # report schema of the issue
    for ch, m in rep["baseline"].items():
        assert set(m) >= {"rmse", "mae", "max"} and ch in ("pos_meas", "force_drive")
    assert {"dimension", "bin", "share"} <= set(rep["where"][0])
    phase = [w["share"] for w in rep["where"] if w["channel"] == "force_drive" and w["dimension"] == "phase"]
    assert math.isclose(sum(phase), 1.0, rel_tol=1e-6)
    e0 = rep["effects"][0]
    assert {"name", "params", "accepted", "fit", "heldout"} <= set(e0)
    assert {"rmse_before", "rmse_after"} <= set(e0["heldout"])
    assert e0["accepted"] and e0["name"] == "coulomb_friction"
    assert abs(e0["params"]["coulomb_n"]["value"] - 90.0) / 90.0 < 0.15
    assert e0["params"]["coulomb_n"]["stderr"] > 0 and e0["params"]["coulomb_n"]["determined"]
    # the true value lies within 3 reported standard errors
    assert abs(e0["params"]["coulomb_n"]["value"] - 90.0) <= 3 * e0["params"]["coulomb_n"]["stderr"]
    assert set(rep["not_applicable"]) >= {"backlash", "axial_compliance", "torque_ripple", "lead_error"}
    assert {"model", "heldout_rmse_after"} <= set(rep["hybrid"])
    assert {m["model"] for m in rep["hybrid"]["models"]} >= {"bp_2_10_1", "gbr_lagged"}
    html = (out / "report.html").read_text()
    assert "data:image/png;base64," in html
    cal = (out / "calibrated.toml").read_text()
    assert "gap diagnosis" in cal
    from virtualaxis.config import load_axis_config

    calibrated = load_axis_config(out / "calibrated.toml")
    assert abs(calibrated.friction.coulomb_n - 90.0) / 90.0 < 0.15


def test_cli_bad_inputs_exit_2(tmp_path, capsys):
    cfg = Path(__file__).resolve().parents[1] / "configs" / "seed000-hust.toml"
    bad = tmp_path / "bad.csv"
    bad.write_text("t,pos_cmd,pos_meas\n0,0,0\n0.001,0,0\n0.001,0,0\n" + "".join(
        f"{0.001 * i:.3f},0,0\n" for i in range(3, 40)))
    rc = main(["diagnose", "--config", str(cfg), str(bad), "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err
    assert rc == 2 and err.startswith("error: ") and "row 4: column t: time is not increasing" in err
    assert "Traceback" not in err
    rc = main(["diagnose", "--config", str(cfg), str(tmp_path / "none.csv"), "--out", str(tmp_path / "o")])
    assert rc == 2 and "file not found" in capsys.readouterr().err
    rc = main(["diagnose", "--config", str(cfg), str(bad), "--out", str(tmp_path / "o"), "--effects", "nonsense"])
    assert rc == 2


def test_cli_scheduler_without_dask_is_a_clear_error(tmp_path, capsys, monkeypatch):
    """Where dask[distributed] is not installed (it is an optional extra): a None entry in sys.modules
    makes ``import dask.distributed`` fail exactly as a missing package does."""
    monkeypatch.setitem(sys.modules, "dask.distributed", None)
    case = next(c for c in all_cases() if c.name == "rigid-clean")
    meta = generate_case(case, tmp_path / "case", seed=1, quick=True)
    rc = main(["diagnose", "--config", str(tmp_path / "case" / "nominal.toml"), *meta["files"]["fit"],
               "--out", str(tmp_path / "o"), "--scheduler", "tcp://127.0.0.1:8786", "--no-hybrid"])
    assert rc == 2
    assert "dask[distributed]" in capsys.readouterr().err


def test_no_effect_constant():
    assert NO_EFFECT == "no significant effect"


@pytest.mark.slow
@pytest.mark.background("withheld_pair")
def test_a_withheld_pair_is_found_and_refitted_jointly(request):
    """Backlash + Coulomb friction withheld together (quick traces): both are found; the joint refit
    is reported with its costs and, where kept, its values are the ones the report gives. Coulomb friction
    fitted alone takes part of the backlash (about 123 N for 110), and backlash on top of it makes the held-out
    torque worse: the joint refit with the earlier effect decides. (Bench run in the background through the
    CLI: ``run_bench(out, seed=3, case_names=["backlash+coulomb"], quick=True, jobs=2)``.)"""
    job = background.result(request.config, "withheld_pair")
    bench, out = job["bench"], job["out"]
    ev = bench["cases"][0]
    assert set(ev["accepted"]) == {"backlash", "coulomb_friction"}, ev
    rep = json.loads((out / "backlash+coulomb" / "diagnosis" / "report.json").read_text())
    jr = rep["joint_refit"]
    assert jr["effects"] == rep["accepted"]
    assert jr["accepted"] == (jr["fit_cost_joint"] < jr["fit_cost_sequential"]
                              and jr["heldout_cost_joint"] <= jr["heldout_cost_sequential"])
    kept = jr["joint_values"] if jr["accepted"] else jr["sequential_values"]
    for e in rep["effects"]:
        if e["accepted"]:
            assert {k: v["value"] for k, v in e["params"].items()} == pytest.approx(kept[e["name"]])
    for key, rec in ev["param_recovery"].items():
        assert rec["rel_error"] < 0.2, (key, rec)
