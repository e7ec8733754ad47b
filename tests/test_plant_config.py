"""Bad configuration input: one clear error naming the file and the key, never a traceback."""

import subprocess
import sys

import pytest
from plant_helpers import SEED000, config_with, seed_dict

from virtualaxis.config import ConfigError, load_axis_config


def test_seed_configs_load_with_a_source_for_every_value():
    for name in ("seed000-hust.toml", "seed004-siemens.toml", "seed002-usst.toml"):
        path = SEED000.parent / name
        cfg = load_axis_config(path)
        raw = seed_dict(path)
        for section, values in raw.items():
            if section in cfg.extra:
                continue
            for key, value in values.items():
                if isinstance(value, (int, float)) and not isinstance(value, bool):
                    pytest.fail(f"{name}: {section}.{key} has no source")
                if isinstance(value, dict):
                    assert value.get("source"), f"{name}: {section}.{key} has an empty source"


@pytest.mark.parametrize(
    "changes, key, words",
    [
        ({"mechanics": {"table_mass_kg": None}}, "mechanics.table_mass_kg", "missing"),
        ({"mechanics": {"tabel_mass_kg": 3.0}}, "mechanics.tabel_mass_kg", "unknown key"),
        ({"mechanics": {"table_mass_kg": "heavy"}}, "mechanics.table_mass_kg", "must be a number"),
        ({"mechanics": {"table_mass_kg": -5.0}}, "mechanics.table_mass_kg", "> 0"),
        ({"mechanics": {"lead_m": 0.0}}, "mechanics.lead_m", "> 0"),
        ({"control": {"speed_cycle_s": 100e-6}}, "control.speed_cycle_s", "integer multiple"),
        ({"control": {"position_cycle_s": 1.1e-3}}, "control.position_cycle_s", "integer multiple"),
        ({"backlash": {"enabled": "yes"}}, "backlash.enabled", "true or false"),
        ({"mechanics": {"model": "triple"}}, "mechanics.model", "one of"),
        ({"control": {"kv_1000_per_min": 2.0}}, "control.kv_1000_per_min", "exactly one"),
        ({"mechanics": {"modal_damping_ratio": 1.5}}, "mechanics.modal_damping_ratio", "between 0 and 1"),
    ],
)
def test_bad_values_name_the_key(changes, key, words):
    with pytest.raises(ConfigError) as exc:
        config_with(changes)
    assert exc.value.key == key
    assert words in str(exc.value)
    assert "seed000-hust.toml" in str(exc.value)


def test_unknown_section_and_bad_toml(tmp_path):
    p = tmp_path / "bad.toml"
    p.write_text(SEED000.read_text() + "\n[mechanicks]\nx = 1\n")
    with pytest.raises(ConfigError, match="bad.toml: mechanicks: unknown section"):
        load_axis_config(p)
    p.write_text("[axis\nname = 1")
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_axis_config(p)


def test_cli_reports_one_line_and_exit_2(tmp_path):
    bad = tmp_path / "neg.toml"
    bad.write_text(SEED000.read_text().replace('table_mass_kg = { value = 150.0', 'table_mass_kg = { value = -150.0'))
    r = subprocess.run([sys.executable, "-m", "virtualaxis.cli.main", "simulate", "--config", str(bad), "--profile",
                        "sine:stroke_mm=100,feed_mm_min=1000", "--out", str(tmp_path / "t.csv")],
                       capture_output=True, text=True)
    assert r.returncode == 2
    assert r.stderr.strip().count("\n") == 0
    assert "neg.toml: mechanics.table_mass_kg: must be > 0" in r.stderr
    assert "Traceback" not in r.stderr


def test_profile_beyond_limits_is_rejected(tmp_path):
    r = subprocess.run([sys.executable, "-m", "virtualaxis.cli.main", "simulate", "--config", str(SEED000),
                        "--profile", "sine:stroke_mm=100,feed_mm_min=60000", "--out", str(tmp_path / "t.csv")],
                       capture_output=True, text=True)
    assert r.returncode == 2
    assert "exceeds limits.max_velocity_m_s" in r.stderr
    r = subprocess.run([sys.executable, "-m", "virtualaxis.cli.main", "simulate", "--config", str(SEED000),
                        "--profile", "sine:stroke=100", "--out", str(tmp_path / "t.csv")],
                       capture_output=True, text=True)
    assert r.returncode == 2 and "unknown parameter 'stroke'" in r.stderr


def test_round_trip_to_toml(tmp_path):
    cfg = load_axis_config(SEED000)
    p = tmp_path / "rt.toml"
    p.write_text(cfg.to_toml("round trip"))
    again = load_axis_config(p)
    assert again == cfg
    assert again.sources["mechanics.lead_m"] == cfg.sources["mechanics.lead_m"]


def test_every_numeric_parameter_has_a_bound_and_a_unit_table():
    """Plausibility bounds for every physical parameter; a key's unit table comes from its name."""
    import dataclasses

    from virtualaxis.config.axis import _SECTIONS
    from virtualaxis.config.bounds import BOUNDS, DIMENSIONLESS, convert_unit, units_for_key

    for sec, cls in _SECTIONS.items():
        for f in dataclasses.fields(cls):
            typ = f.type if isinstance(f.type, str) else f.type.__name__
            if typ in ("float", "int"):
                assert f"{sec}.{f.name}" in BOUNDS, f"{sec}.{f.name}"
    assert set(BOUNDS) <= {f"{s}.{f.name}" for s, c in _SECTIONS.items() for f in dataclasses.fields(c)}
    assert convert_unit("mechanics.lead_m", 16, "mm") == pytest.approx(0.016)
    assert convert_unit("motor.rated_speed_rpm", 50, "1/s") == pytest.approx(3000)
    assert convert_unit("control.kv_per_s", 120, "1/min") == pytest.approx(2)
    assert convert_unit("mechanics.motor_inertia_kg_m2", 16, "kg cm^2") == pytest.approx(1.6e-3)
    assert convert_unit("mechanics.nut_contact_stiffness_n_per_m", 400, "N/um") == pytest.approx(4e8)
    assert units_for_key("motor.pole_pairs") is DIMENSIONLESS
    with pytest.raises(ValueError, match="accepted"):
        convert_unit("mechanics.lead_m", 16, "rpm")


def test_every_shipped_config_loads():
    from plant_helpers import ROOT

    paths = sorted((ROOT / "configs").rglob("*.toml"))
    assert len(paths) >= 5
    for p in paths:
        load_axis_config(p)
