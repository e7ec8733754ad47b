"""The ``[drive]`` section of an axis config (owned and validated here).

Every key is optional::

    [drive]
    position_unit_m = 1e-6                 # one position unit of 0x607A/0x6064/... = 1 um at the table
    software_limit_reaction = "clamp"      # "clamp" (clamp + statusword bit 11) or "fault" (EMCY 0x8612)
    following_error_tolerance_m = 2e-3     # 0x6065 (else the EDS default)
    following_error_time_ms = 10           # 0x6066
    positioning_window_m = 10e-6           # 0x6067
    positioning_time_ms = 10               # 0x6068
    limit_switch_inset_m = 0.002           # limit switches act this far inside +-stroke/2
    home_switch_position_m = 0.0           # home switch active for x >= this (table position)
    index_pulse_offset_m = 0.0             # index pulse once per motor revolution, at offset + k * lead
    dc_link_overvoltage_v = 0              # 0: 1.25 x inverter.dc_link_v
    dc_link_undervoltage_v = 0             # 0: 0.70 x inverter.dc_link_v
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

from virtualaxis.config import AxisConfig, ConfigError


@dataclass(frozen=True)
class DriveSettings:
    position_unit_m: float = 1e-6
    software_limit_reaction: str = "clamp"
    following_error_tolerance_m: float | None = None
    following_error_time_ms: int | None = None
    positioning_window_m: float | None = None
    positioning_time_ms: int | None = None
    limit_switch_inset_m: float = 0.002
    home_switch_position_m: float = 0.0
    index_pulse_offset_m: float = 0.0
    dc_link_overvoltage_v: float = 0.0
    dc_link_undervoltage_v: float = 0.0


_INT_KEYS = {"following_error_time_ms", "positioning_time_ms"}
_POSITIVE = {"position_unit_m", "following_error_tolerance_m", "positioning_window_m"}


def drive_settings(cfg: AxisConfig) -> DriveSettings:
    """Validate ``[drive]`` of an axis config; ConfigError names file and ``drive.key``."""
    raw = cfg.extra.get("drive", {}) or {}
    if not isinstance(raw, dict):
        raise ConfigError(cfg.path, "drive", "must be a table")
    known = {f.name for f in fields(DriveSettings)}
    kwargs: dict = {}
    for key, value in raw.items():
        where = f"drive.{key}"
        if key not in known:
            raise ConfigError(cfg.path, where, f"unknown key (known: {', '.join(sorted(known))})")
        if isinstance(value, dict):
            if "value" not in value:
                raise ConfigError(cfg.path, where, "a table value needs 'value'")
            value = value["value"]
        if key == "software_limit_reaction":
            if value not in ("clamp", "fault"):
                raise ConfigError(cfg.path, where, f"must be 'clamp' or 'fault' (got {value!r})")
        elif key in _INT_KEYS:
            if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value <= 0xFFFF:
                raise ConfigError(cfg.path, where, f"must be an integer 0..65535 [ms] (got {value!r})")
        else:
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
                raise ConfigError(cfg.path, where, f"must be a finite number (got {value!r})")
            value = float(value)
            if key in _POSITIVE and not value > 0:
                raise ConfigError(cfg.path, where, f"must be > 0 (got {value})")
            if key not in _POSITIVE and key.endswith(("_m", "_v")) and key != "home_switch_position_m":
                if key != "index_pulse_offset_m" and value < 0:
                    raise ConfigError(cfg.path, where, f"must be >= 0 (got {value})")
        kwargs[key] = value
    settings = DriveSettings(**kwargs)
    lead = cfg.mechanics.lead_m or 0.0
    if lead > 0:
        feed = lead / settings.position_unit_m
        if not 1 <= round(feed) <= 0xFFFFFFFF:
            raise ConfigError(
                cfg.path,
                "drive.position_unit_m",
                f"gives a feed constant of {feed:g} units/rev (needs 1..2^32-1)",
            )
    return settings
