"""Helpers for plant tests: configs derived from the seed files as plain dicts."""

from __future__ import annotations

import copy
import sys
from pathlib import Path

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

from virtualaxis.config import axis_config_from_dict

ROOT = Path(__file__).resolve().parents[1]
SEED000 = ROOT / "configs" / "seed000-hust.toml"
SEED004 = ROOT / "configs" / "seed004-siemens.toml"


def seed_dict(path: Path = SEED000) -> dict:
    return tomllib.loads(path.read_text())


def config_with(changes: dict, path: Path = SEED000):
    d = copy.deepcopy(seed_dict(path))
    for sec, vals in changes.items():
        d.setdefault(sec, {})
        for k, v in vals.items():
            if v is None:
                d[sec].pop(k, None)
            else:
                d[sec][k] = v
    return axis_config_from_dict(d, f"{path.name}+changes")


def rigid_force_axis(**friction):
    """A rigid single-mass axis driven by a force command from a P/PI controller (not our motor)."""
    d = {
        "axis": {"name": "rigid", "stroke_m": 0.5, "nut_offset_m": 0.25},
        "mechanics": {"model": "rigid", "table_mass_kg": 50.0},
        "actuator": {"kind": "force", "force_limit_n": 2000.0, "force_lag_s": 0.0005},
        "control": {"current_cycle_s": 125e-6, "speed_cycle_s": 125e-6, "position_cycle_s": 1e-3,
                    "velocity_kp_n_s_per_m": 4000.0, "speed_ti_s": 0.02, "kv_per_s": 40.0,
                    "position_feedback": "linear_scale"},
        "friction": {"enabled": bool(friction), **friction},
        "sensors": {"motor_encoder_counts_per_rev": 0, "linear_scale_resolution_m": 1e-7},
        "limits": {"max_velocity_m_s": 1.0, "max_acceleration_m_s2": 20.0},
    }
    return axis_config_from_dict(d, "rigid-force")
