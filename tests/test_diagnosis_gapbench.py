"""The gap bench on the independent reference axis (``virtualaxis.refaxis``, written apart from the diagnosed
model): a case is made, diagnosed with the nominal config it provides and scored against its truth, through the
CLI. And the rule that keeps the reference independent: neither package imports the other."""

from __future__ import annotations

import ast
import json
from pathlib import Path

import background
import pytest

SRC = Path(__file__).resolve().parents[1] / "src" / "virtualaxis"


def _imports(pkg: str) -> set[str]:
    out: set[str] = set()
    for f in (SRC / pkg).rglob("*.py"):
        for node in ast.walk(ast.parse(f.read_text(encoding="utf-8"))):
            if isinstance(node, ast.ImportFrom) and node.module:
                out.add(node.module)
            elif isinstance(node, ast.Import):
                out.update(a.name for a in node.names)
    return out


def test_the_diagnosis_and_the_reference_do_not_import_each_other():
    assert not any(m.startswith("virtualaxis.refaxis") for m in _imports("diagnosis"))
    if (SRC / "refaxis").exists():
        assert not any(m.startswith("virtualaxis.diagnosis") for m in _imports("refaxis"))


@pytest.mark.background("reference_case_cli")
def test_a_reference_case_is_diagnosed_and_scored_through_the_cli(request):
    """(computed in the background: tests/background.py)"""
    job = background.result(request.config, "reference_case_cli")
    tmp_path = job["out"]
    assert job["rc"] == 0, job["stderr"]
    out = json.loads((tmp_path / "reference.json").read_text())
    case = out["cases"][0]
    assert case["truth"] == ["coulomb_friction"]
    assert case["accepted"] == ["coulomb_friction"] and case["top1"] and case["none_outside"]
    rec = case["param_recovery"]["coulomb_friction.coulomb_n"]
    assert rec["rel_error"] < 0.15, rec
    assert case["shrink_on_effect_channel"] > 0.6
    assert out["summary"]["right_effect_first"] == 1.0
    assert (tmp_path / "rigid_pp__coulomb_friction" / "diagnosis" / "report.json").exists()
    assert "right effect first 100 %" in job["stdout"]
    # the case went through `virtualaxis diagnose` in a subprocess, as a user runs it (no terminal: a line per
    # stage in its log)
    assert case["door"]["door"] == "cli" and case["door"]["exit_code"] == 0
    log = (tmp_path / "rigid_pp__coulomb_friction" / "diagnosis.log").read_text()
    assert " diagnose --config " in log and "exit status 0" in log
    assert "diagnose: round 1: screening" in log and "conclusion: coulomb_friction" in log
