"""Reference axis (virtualaxis.refaxis): independence from the diagnosed model, the case API, and physics
checked against closed-form results derived on paper (docs/refaxis.md, "Checks")."""

from __future__ import annotations

import ast
import json
from pathlib import Path

import numpy as np
import pytest

from virtualaxis.config import load_axis_config
from virtualaxis.refaxis import axes as A
from virtualaxis.refaxis import case_names, make_case

PKG = Path(A.__file__).resolve().parent
FORBIDDEN = ("virtualaxis.sim", "virtualaxis.plant", "virtualaxis.control", "virtualaxis.diagnosis")


def test_imports_nothing_from_the_diagnosed_model():
    """Every module of the package is parsed; its only virtualaxis imports are virtualaxis.refaxis itself."""
    files = sorted(PKG.glob("*.py"))
    assert len(files) >= 5
    for f in files:
        tree = ast.parse(f.read_text(encoding="utf-8"))
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                mods = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                assert node.level == 0, f"{f.name}: relative import"
                mods = [node.module or ""]
            else:
                continue
            for m in mods:
                assert not m.startswith(FORBIDDEN), f"{f.name} imports {m}"
                if m.startswith("virtualaxis"):
                    assert m.startswith("virtualaxis.refaxis"), f"{f.name} imports {m}"


def test_case_names_cover_every_effect_and_the_pairs():
    names = case_names()
    assert len(names) == len(set(names)) >= 30
    tm = case_names("two_mass")
    effects = ["backlash", "coulomb_friction", "stribeck_friction", "viscous_friction", "friction_asymmetry",
               "mass_error", "axial_compliance", "resonance", "lead_error", "torque_ripple", "time_delay",
               "thermal_drift"]
    for e in effects + ["clean", "coulomb_friction+viscous_friction", "backlash+coulomb_friction",
                        "mass_error+time_delay"]:
        assert f"two_mass/{e}" in tm
    assert "rigid_pp/clean" in case_names("rigid_pp")
    with pytest.raises(ValueError, match="unknown structure"):
        case_names("three_mass")
    with pytest.raises(KeyError, match="unknown reference case"):
        make_case("two_mass/nothing", Path("/nonexistent"))


@pytest.mark.parametrize("name", ["two_mass/backlash", "rigid_pp/channel_shift"])
def test_make_case_writes_a_loadable_config_traces_and_truth(tmp_path, name):
    cf = make_case(name, tmp_path, seed=3, quick=True)
    cfg = load_axis_config(cf.config_path)  # our schema, validated on load
    assert cfg.mechanics.model == ("two_mass" if name.startswith("two") else "rigid")
    assert not cfg.backlash.enabled  # the withheld effect is not in the config
    for key, src in cfg.sources.items():
        assert src.strip(), key
    assert len(cf.fit) == 4 and len(cf.holdout) == 3
    truth = json.loads((tmp_path / "truth.json").read_text())
    assert truth == json.loads(json.dumps(cf.truth))
    assert set(cf.truth) >= {"effects", "params", "main_param", "notes"}
    for eff, key in cf.truth["main_param"].items():
        assert eff in cf.truth["effects"] and key in cf.truth["params"]
    header = cf.fit[0].read_text().splitlines()[0].split(",")
    expect = ["t", "pos_cmd", "pos_meas", "force_drive"]
    if name.startswith("two"):
        expect += ["pos_fb", "motor_pos", "current_q"]
    assert set(expect) <= set(header)
    d = np.genfromtxt(cf.fit[0], delimiter=",", names=True)
    assert np.allclose(np.diff(d["t"]), 1e-3)
    assert np.all(np.isfinite(d.view(float).reshape(len(d), -1)))
