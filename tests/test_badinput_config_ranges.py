"""Config ranges: near-zero physical values, 0 without a documented meaning, hidden defaults and vague
messages. Each case writes a small config derived from configs/seed000-hust.toml into tmp_path and runs the CLI
in-process: exit 2, one ``error:`` line naming the key, nothing written.

- near-zero values that would crash ``simulate`` (ZeroDivisionError, LinAlgError)
- near-zero values of keys that must be positive (a table that never moves, a diverged run hidden by a
  saturated quantiser)
- 0 of current_limit_a / encoder counts: a documented meaning, values near it refused naming that meaning
- motor / drive keys without a default: required
- messages: Kv of 0, a missing lead, ``--config ''``
"""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np
import pytest

from virtualaxis.cli.main import main

ROOT = Path(__file__).resolve().parents[1]
SEED000 = ROOT / "configs" / "seed000-hust.toml"


def write_config(tmp_path: Path, changes: dict[str, object], name: str = "cfg.toml") -> Path:
    """seed000 with ``section.key`` set to a value (a TOML literal string) or removed (None)."""
    section = ""
    out = []
    done = set()
    for line in SEED000.read_text(encoding="utf-8").splitlines():
        m = re.match(r"^\[([A-Za-z_.]+)\]\s*$", line)
        if m:
            section = m.group(1)
        k = re.match(r"^([A-Za-z_0-9]+)\s*=", line)
        if k and f"{section}.{k.group(1)}" in changes:
            key = f"{section}.{k.group(1)}"
            done.add(key)
            if changes[key] is None:
                continue
            line = f"{k.group(1)} = {changes[key]}"
        out.append(line)
    assert done == set(changes), set(changes) - done
    p = tmp_path / name
    p.write_text("\n".join(out) + "\n", encoding="utf-8")
    return p


def run_cli(argv: list[str], capsys) -> tuple[int, str, str]:
    try:
        rc = main(argv)
    except SystemExit as exc:  # pragma: no cover - main returns its status
        rc = exc.code
    cap = capsys.readouterr()
    return rc, cap.out, cap.err


def assert_refused(tmp_path: Path, argv: list[str], capsys, *words: str) -> str:
    before = sorted(p.name for p in tmp_path.iterdir())
    rc, out, err = run_cli(argv, capsys)
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert rc == 2, (rc, out, err)
    assert len(lines) == 1 and lines[0].startswith("error: "), err
    assert "Traceback" not in err and "internal error" not in err
    for w in words:
        assert w in lines[0], (w, lines[0])
    assert sorted(p.name for p in tmp_path.iterdir()) == before  # nothing written
    return lines[0]


def simulate_argv(cfg: Path, tmp_path: Path) -> list[str]:
    return ["simulate", "--config", str(cfg), "--profile", "sine:stroke_mm=10,feed_mm_min=3000", "--duration", "0.05",
            "--out", str(tmp_path / "out.csv")]


# ---------------------------------------------------------------- near zero: simulate cannot run
@pytest.mark.parametrize("key", ["mechanics.lead_m", "mechanics.screw_root_diameter_m", "mechanics.nut_mass_kg"])
def test_g1_near_zero_values_refused_before_simulate(tmp_path, capsys, key):
    cfg = write_config(tmp_path, {key: "1e-300"})
    line = assert_refused(tmp_path, simulate_argv(cfg, tmp_path), capsys,
                          f"{key}: 1e-300 is outside the plausible range")
    assert "(or 0 = " in line  # the one meaning 0 has for these keys


# ---------------------------------------------------------------- near zero: a run that says nothing
@pytest.mark.parametrize("key", [
    "mechanics.lead_m",
    "mechanics.coupling_stiffness_nm_per_rad",
    "mechanics.motor_shaft_stiffness_nm_per_rad",
    "mechanics.bearing_axial_stiffness_n_per_m",
    "mechanics.support_axial_stiffness_n_per_m",
    "mechanics.nut_contact_stiffness_n_per_m",
    "mechanics.flange_stiffness_n_per_m",
    "mechanics.screw_root_diameter_m",
    "motor.torque_constant_nm_per_a",
    "control.current_kp_v_per_a",
    "control.current_ti_s",
    "control.speed_kp_nm_s_per_rad",
    "control.kv_per_s",
    "control.speed_limit_rpm",
])
def test_g5_near_zero_positive_keys_refused(tmp_path, capsys, key):
    cfg = write_config(tmp_path, {key: "1e-9"})
    assert_refused(tmp_path, ["modal", "--config", str(cfg)], capsys, f"{key}: 1e-09 is outside the plausible range")


def test_g5_scale_resolution_near_zero_refused(tmp_path, capsys):
    """1 nm is a real scale (1e-9 is fine); 1e-300 read every position as ~0."""
    cfg = write_config(tmp_path, {"sensors.linear_scale_resolution_m": "1e-300"})
    assert_refused(tmp_path, ["modal", "--config", str(cfg)], capsys,
                   "sensors.linear_scale_resolution_m: 1e-300 is outside the plausible range 1e-12 .. 0.01 m")


def test_g5_every_bounded_positive_key_has_a_positive_lower_bound_or_a_zero_meaning():
    from virtualaxis.config.bounds import BOUNDS, ZERO_MEANS, in_bounds

    for key in ZERO_MEANS:
        lo, hi = BOUNDS[key]
        assert 0 < lo < hi, key
        assert in_bounds(key, 0) and not in_bounds(key, lo * 1e-3), key
    for key in ("mechanics.lead_m", "control.kv_per_s", "mechanics.nut_contact_stiffness_n_per_m"):
        assert not in_bounds(key, 1e-9)


def test_g5_quantiser_passes_a_diverged_value_through():
    """A compiled ``math.floor`` returns an int64 that saturates: NaN read as -2^63 quanta (-9.2e10 m at 10 nm)."""
    from virtualaxis.control.loops import quantise

    assert math.isnan(quantise(float("nan"), 1e-8))
    assert quantise(1e300, 1e-8) == 1e300
    assert quantise(0.123456789, 1e-8) == pytest.approx(0.12345678, abs=1e-15)


def test_g5_simulate_reports_a_saturated_position_as_diverged(tmp_path, capsys, monkeypatch):
    """A finite but absurd position (what the saturated quantiser wrote) is a diverged run, not 'RMSE 8e16 um'."""
    import virtualaxis.sim.batch as batch

    real = batch.rows_to_columns

    def saturated(cfg, rows, extras=False):
        data = real(cfg, rows, extras=extras)
        data["pos_meas"] = np.full_like(data["pos_meas"], -9.223372036854776e10)
        return data

    monkeypatch.setattr(batch, "rows_to_columns", saturated)
    cfg = write_config(tmp_path, {})
    assert_refused(tmp_path, simulate_argv(cfg, tmp_path), capsys, "the simulation diverged", "beyond")


# ---------------------------------------------------------------- what 0 means
def test_g6_current_limit_near_zero_refused_and_zero_documented(tmp_path, capsys):
    from virtualaxis.config import load_axis_config

    cfg = write_config(tmp_path, {"control.current_limit_a": "1e-3"})
    assert_refused(tmp_path, ["modal", "--config", str(cfg)], capsys, "control.current_limit_a:",
                   "0 = 3 x motor.rated_current_a")
    zero = load_axis_config(write_config(tmp_path, {"control.current_limit_a": "0"}, "zero.toml"))
    assert zero.control.current_limit_a == 0.0


def test_g6_encoder_counts_near_zero_refused_and_zero_is_ideal(tmp_path, capsys):
    from virtualaxis.config import load_axis_config

    cfg = write_config(tmp_path, {"sensors.motor_encoder_counts_per_rev": "1"})
    assert_refused(tmp_path, ["modal", "--config", str(cfg)], capsys, "sensors.motor_encoder_counts_per_rev:",
                   "0 = ideal")
    load_axis_config(write_config(tmp_path, {"sensors.motor_encoder_counts_per_rev": "0"}, "zero.toml"))


# ---------------------------------------------------------------- no hidden default for the motor and drive
@pytest.mark.parametrize("key", ["motor.pole_pairs", "motor.rs_ohm", "motor.lq_h", "motor.rated_current_a",
                                 "control.position_cycle_s", "control.current_cycle_s", "control.speed_ti_s"])
def test_g7_motor_and_drive_keys_required(tmp_path, capsys, key):
    cfg = write_config(tmp_path, {key: None})
    assert_refused(tmp_path, ["modal", "--config", str(cfg)], capsys, f"{key}: missing (required")


def test_g7_documented_defaults_may_be_omitted(tmp_path):
    from virtualaxis.config import load_axis_config

    cfg = load_axis_config(write_config(tmp_path, {"mechanics.screw_mounting": None,
                                                   "mechanics.youngs_modulus_pa": None}))
    assert cfg.mechanics.screw_mounting == "fixed_fixed" and cfg.mechanics.youngs_modulus_pa == 2.06e11
    doc = (ROOT / "docs" / "plant.md").read_text(encoding="utf-8")
    for key in ("mechanics.screw_mounting", "youngs_modulus_pa", "control.current_limit_a", "motor.rated_torque_nm"):
        assert key in doc


# ---------------------------------------------------------------- messages
def test_g15_kv_zero_names_the_key_given(tmp_path, capsys):
    cfg = write_config(tmp_path, {"control.kv_per_s": "0"})
    line = assert_refused(tmp_path, ["modal", "--config", str(cfg)], capsys, "control.kv_per_s: must be > 0")
    assert "got []" not in line


def test_g15_kv_missing_says_missing(tmp_path, capsys):
    cfg = write_config(tmp_path, {"control.kv_per_s": None})
    assert_refused(tmp_path, ["modal", "--config", str(cfg)], capsys, "control.kv_per_s: missing")


def test_g15_missing_lead_says_missing(tmp_path, capsys):
    cfg = write_config(tmp_path, {"mechanics.lead_m": None})
    line = assert_refused(tmp_path, ["modal", "--config", str(cfg)], capsys,
                          "mechanics.lead_m: missing (required for a ball_screw axis)")
    assert "got 0" not in line


def test_g15_empty_config_path(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    line = assert_refused(tmp_path, ["modal", "--config", ""], capsys, "empty or blank path")
    assert "is a folder" not in line
