"""Pacing (wall clock, SYNC lockstep), several axes on one bus, bus opening: see docs/drive.md."""

from typing import TYPE_CHECKING

from virtualaxis.lazy import lazy_exports

if TYPE_CHECKING:
    from virtualaxis.runtime.axes import AxisNode, AxisSpec, build_axes
    from virtualaxis.runtime.bus import DEFAULT_BUS, BusOpenError, open_bus, parse_bus_spec
    from virtualaxis.runtime.pacing import Runtime, RuntimeStats

# imported on first use (virtualaxis.lazy): a submodule such as runtime.bus loads without the drive
__getattr__, __dir__ = lazy_exports(__name__, {
    **{n: "virtualaxis.runtime.axes" for n in ("AxisNode", "AxisSpec", "build_axes")},
    **{n: "virtualaxis.runtime.bus" for n in ("DEFAULT_BUS", "BusOpenError", "open_bus", "parse_bus_spec")},
    **{n: "virtualaxis.runtime.pacing" for n in ("Runtime", "RuntimeStats")},
}, globals())

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
