"""The compiled axis simulator (control cascade + plant), its step and batch APIs, profiles and traces."""

from typing import TYPE_CHECKING

from virtualaxis.lazy import lazy_exports

if TYPE_CHECKING:
    from virtualaxis.sim.batch import simulate_command, simulate_profile
    from virtualaxis.sim.simulator import CONTROL_MODE, AxisSimulator, AxisState, ControlMode

# imported on first use (virtualaxis.lazy): a submodule such as sim.trace_io loads without the others
__getattr__, __dir__ = lazy_exports(__name__, {
    "simulate_command": "virtualaxis.sim.batch", "simulate_profile": "virtualaxis.sim.batch",
    **{n: "virtualaxis.sim.simulator" for n in ("CONTROL_MODE", "AxisSimulator", "AxisState", "ControlMode")},
}, globals())

__all__ = ["CONTROL_MODE", "AxisSimulator", "AxisState", "ControlMode", "simulate_command", "simulate_profile"]
