"""Pacing (wall clock, SYNC lockstep), several axes on one bus, bus opening: see docs/drive.md."""

from virtualaxis.runtime.axes import AxisNode, AxisSpec, build_axes
from virtualaxis.runtime.bus import DEFAULT_BUS, BusOpenError, open_bus, parse_bus_spec
from virtualaxis.runtime.pacing import Runtime, RuntimeStats

__all__ = [
    "DEFAULT_BUS",
    "AxisNode",
    "AxisSpec",
    "BusOpenError",
    "Runtime",
    "RuntimeStats",
    "build_axes",
    "open_bus",
    "parse_bus_spec",
]
