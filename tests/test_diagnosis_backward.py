"""The backward step after a joint refit: an accepted effect whose jointly refitted parameter sits at a bound of
its physical range is dropped by the rule every candidate is judged by (docs/diagnosis.md, "Plausible and
determined")."""

from __future__ import annotations

import math
from pathlib import Path

from virtualaxis.config import load_axis_config
from virtualaxis.diagnosis import effects as fx
from virtualaxis.diagnosis.selection import Step, backward_step

CONFIG = Path(__file__).resolve().parents[1] / "configs" / "examples" / "gap-bench-ballscrew.toml"


def _steps(cfg, items):
    steps, c = [], cfg
    for effect, values, stderr in items:
        c = fx.EFFECTS[effect].apply(c, values)
        steps.append(Step(effect, values, stderr, c, {}, {}))
    return steps


def test_an_effect_the_joint_refit_left_at_a_bound_is_dropped():
    """A docs-only tester's two-mass axis without screw torsion, table 75 kg heavier: mass_error 226 kg was
    accepted with axial_compliance 1.91 +- 0.04 as a pair; the joint refit moved the stiffness factor to
    1.96 +- 0.04 under its bound 2, and it stayed in the answer."""
    cfg = load_axis_config(CONFIG)
    accepted = _steps(cfg, [("mass_error", {"table_mass_kg": 226.4}, {"table_mass_kg": 0.45}),
                            ("axial_compliance", {"axial_stiffness_scale": 1.9636}, {"axial_stiffness_scale": 0.0407})])
    kept, dropped, n_sims = backward_step(cfg, accepted, [], [], [], {}, None, None,
                                          {"axial_compliance": ["axial_stiffness_scale"]})
    assert [s.effect for s in kept] == ["mass_error"] and n_sims == 0
    assert [d["effect"] for d in dropped] == ["axial_compliance"]
    assert "at the bound of its range" in dropped[0]["why"] and math.isnan(dropped[0]["heldout_energy_rise_without"])
    # the mass error stays as it was fitted
    assert kept[0].values == {"table_mass_kg": 226.4}
