"""The compiled axis simulator (control cascade + plant), its step and batch APIs, profiles and traces."""

from virtualaxis.sim.batch import simulate_command, simulate_profile
from virtualaxis.sim.simulator import CONTROL_MODE, AxisSimulator, AxisState, ControlMode

__all__ = ["CONTROL_MODE", "AxisSimulator", "AxisState", "ControlMode", "simulate_command", "simulate_profile"]
