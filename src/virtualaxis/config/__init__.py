"""Axis configuration: TOML files with SI units in key names and a source for every value."""

from virtualaxis.config.errors import ConfigError
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
    load_axis_config,
    axis_config_from_dict,
)

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
