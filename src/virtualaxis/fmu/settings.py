"""What the FMU exporter and the FMU's slave share (no pythonfmu needed to import this)."""

from __future__ import annotations

import re

#: the export settings written next to the config in the FMU's resources
SETTINGS_FILE = "fmu.json"
#: the axis config embedded in the FMU's resources
CONFIG_FILE = "axis.toml"
#: a communication step is a whole number of current-loop cycles to within this fraction of a cycle
STEP_TOLERANCE_CYCLES = 1e-6


def model_identifier(axis_name: str, interface: str) -> str:
    """A C identifier naming the FMU's model and binary: ``virtualaxis_<axis name>_<interface>``."""
    return re.sub(r"[^A-Za-z0-9_]", "_", f"virtualaxis_{axis_name}_{interface}")
