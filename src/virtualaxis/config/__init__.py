"""Axis configuration: TOML files with SI units in key names and a source for every value."""

from virtualaxis.config.axis import (
    ActuatorParams,
    AxisConfig,
    AxisInfo,
    BacklashParams,
    ControlParams,
    EffectsParams,
    FrictionParams,
    InverterParams,
    LimitsParams,
    MechanicsParams,
    MotorParams,
    SensorParams,
    SimulationParams,
    axis_config_from_dict,
    load_axis_config,
)
from virtualaxis.config.errors import ConfigError

__all__ = [
    "ActuatorParams",
    "AxisConfig",
    "AxisInfo",
    "BacklashParams",
    "ConfigError",
    "ControlParams",
    "EffectsParams",
    "FrictionParams",
    "InverterParams",
    "LimitsParams",
    "MechanicsParams",
    "MotorParams",
    "SensorParams",
    "SimulationParams",
    "load_axis_config",
    "axis_config_from_dict",
]
