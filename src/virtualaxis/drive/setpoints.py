"""The set-point channel: the one way from the drive (its modes, stops and limiters) to the plant's set-point
API (:class:`~virtualaxis.sim.AxisSimulator` ``set_mode`` / ``set_position_setpoint`` /
``set_velocity_setpoint`` / ``set_torque_setpoint``).

It holds the demand in drive coordinates (``demand_m``: 0x6062, ``demand_v``: 0x606B, ``last_vff``: the last
speed feed-forward, whose change per cycle is the acceleration feed-forward) and the zero offset ``zero_m``
that homing sets (drive position = plant position - ``zero_m``), and the plant's control mode ``control``.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from virtualaxis.sim import AxisSimulator, ControlMode


class SetpointChannel:
    """Demand, zero offset and control mode of one axis; the only caller of the plant's set-point API."""

    def __init__(self, sim: AxisSimulator) -> None:
        self._sim = sim
        self.demand_m = 0.0  # position demand, drive coordinate [m]
        self.zero_m = 0.0  # plant position of the drive's zero [m]
        self.demand_v = 0.0  # velocity demand [m/s]
        self.last_vff = 0.0  # speed feed-forward sent last [m/s]
        self.control: ControlMode = sim.mode

    def set_control(self, mode: ControlMode) -> None:
        """The plant's loop in command (position, velocity, torque)."""
        if mode != self.control:
            self._sim.set_mode(mode)
            self.control = mode

    def send_position(self, p_m: float, vff_m_s: float, acc_m_s2: float) -> None:
        """Position set-point ``p_m`` (drive coordinate) with speed / acceleration feed-forward."""
        self._sim.set_position_setpoint(p_m + self.zero_m, vff_m_s, acc_m_s2)

    def send_velocity(self, v_m_s: float) -> None:
        self._sim.set_velocity_setpoint(v_m_s)

    def send_torque(self, t_nm: float) -> None:
        self._sim.set_torque_setpoint(t_nm)

    def position_of(self, x_plant_m: float) -> float:
        """A plant position in drive coordinates [m]."""
        return x_plant_m - self.zero_m
