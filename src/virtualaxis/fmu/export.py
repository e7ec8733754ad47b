"""Export the configured axis as an FMI 2.0 co-simulation FMU with pythonfmu (the ``fmu`` extra)."""

from __future__ import annotations

import json
import math
import shutil
import tempfile
from pathlib import Path

from virtualaxis.config import AxisConfig, load_axis_config
from virtualaxis.config.errors import InputError
from virtualaxis.fmu.settings import CONFIG_FILE, SETTINGS_FILE, STEP_TOLERANCE_CYCLES, model_identifier

#: the FMU's inputs: what the importing tool drives (docs/fmu.md)
INTERFACES = ("torque", "speed", "position")
SLAVE_SCRIPT = Path(__file__).with_name("virtualaxis_slave.py")


class FmuExportError(InputError):
    """An export option the FMU cannot honour (interface, step)."""

    def __init__(self, option: str, message: str):
        ValueError.__init__(self, f"{option}: {message}")
        self.file, self.row, self.column = None, None, option


def check_step(cfg: AxisConfig, step_s: float | None) -> float:
    """The communication step [s]: the position-loop cycle by default, else a whole number of current-loop
    cycles (the kernel's unit of time)."""
    if step_s is None:
        return cfg.control.position_cycle_s
    if not (math.isfinite(step_s) and step_s > 0):
        raise FmuExportError("--step", f"must be a finite number > 0 s (got {step_s:g})")
    hc = cfg.control.current_cycle_s
    n = round(step_s / hc)
    if n < 1 or abs(step_s / hc - n) > STEP_TOLERANCE_CYCLES:
        raise FmuExportError("--step", f"{step_s:g} s is not a whole number of current-loop cycles "
                                       f"({hc:g} s, control.current_cycle_s of {cfg.path})")
    return float(step_s)


def build_fmu(config: str | Path, out: str | Path, interface: str = "position", step_s: float | None = None) -> Path:
    """Write the FMU of the axis config ``config`` to ``out`` (a ``.fmu`` file) and return its path.

    The FMU embeds the config file and this package's slave script; it needs a Python with ``virtualaxis``
    importable at run time (docs/fmu.md). Raises :class:`FmuExportError` / ``ConfigError`` on bad input and
    ``ModuleNotFoundError`` without pythonfmu.
    """
    if interface not in INTERFACES:
        raise FmuExportError("--interface", f"unknown interface {interface!r} (expected {', '.join(INTERFACES)})")
    cfg = load_axis_config(config)
    step = check_step(cfg, step_s)
    from pythonfmu import FmuBuilder

    out = Path(out)
    with tempfile.TemporaryDirectory(prefix="virtualaxis-fmu-") as tmp:
        stage = Path(tmp) / "resources"
        stage.mkdir()
        shutil.copyfile(config, stage / CONFIG_FILE)
        settings = {"interface": interface, "step_s": step, "config": Path(config).name}
        (stage / SETTINGS_FILE).write_text(json.dumps(settings, indent=2), encoding="utf-8")
        built_dir = Path(tmp) / "built"
        built = FmuBuilder.build_FMU(SLAVE_SCRIPT, dest=built_dir,
                                     project_files=[stage / CONFIG_FILE, stage / SETTINGS_FILE])
        expected = built_dir / f"{model_identifier(cfg.axis.name, interface)}.fmu"
        if Path(built) != expected:  # (the model name decides the binary's name inside the FMU)
            raise RuntimeError(f"pythonfmu wrote {built}, expected {expected}")
        out.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(built, out)
    return out
