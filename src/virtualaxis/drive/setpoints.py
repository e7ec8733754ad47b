"""The set-point channel: the one way from the drive (its modes, stops and limiters) to the plant's set-point
API (:class:`~virtualaxis.sim.AxisSimulator` ``set_mode`` / ``set_position_setpoint`` /
``set_velocity_setpoint`` / ``set_torque_setpoint``).

It holds the demand in drive coordinates (``demand_m``: 0x6062, ``demand_v``: 0x606B, ``last_vff``: the last
speed feed-forward, whose change per cycle is the acceleration feed-forward) and the zero offset ``zero_m``
that homing sets (drive position = plant position - ``zero_m``), and the plant's control mode ``control``.

Its limiters (:meth:`position`, :meth:`velocity_limit`, :meth:`clamp_velocity`, :meth:`torque`,
:meth:`check_limit`) keep every set-point within the software limits 0x607D, the speed limits 0x607F /
0x6080, the torque limit 0x6072 and away from an active limit switch; ``internal_limit`` (statusword bit 11)
tells that one of them acted.

Polarity 0x607E (:meth:`set_polarity`): the drive computes in its own direction (that of the plant); the
signs ``position_sign`` (bit 7) and ``velocity_sign`` (bit 6) convert between it and the master's values: a
position object (0x607A, 0x60C1, 0x6062, 0x6064, 0x60F4, 0x607C, 0x607D, 0x60BA-0x60BD; the CSP velocity
offset 0x60B1) is ``position_sign`` times the drive's value, a velocity or torque object (0x60FF, 0x60B1 in
CSV, 0x606B, 0x606C, 0x6071, 0x60B2, 0x6074, 0x6077, 0x6078) ``velocity_sign`` times it.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import TYPE_CHECKING

from virtualaxis.drive.objects import clamp_to_dtype

if TYPE_CHECKING:
    from virtualaxis.drive.monitoring import LimitSwitchMonitor
    from virtualaxis.drive.parameters import DriveParameters
    from virtualaxis.sim import AxisSimulator, ControlMode

# torque modes: bit 11 while the torque pushes the axis at this share of 0x6080 or faster (the plant's speed
# limiter acts there; chosen: above the P limiter's droop at the bench axes' friction, ~1 %)
SPEED_LIMIT_SHARE = 0.97


class SetpointChannel:
    """Demand, zero offset, control mode and set-point limiters of one axis; the only caller of the plant's
    set-point API.

    Given by the drive: the plant ``sim``, the position-loop ``cycle_s``, the limit switch monitor
    ``switches`` and ``homing_owns_switches`` (a homing run searches the switches: they block nothing), the
    cached parameters ``params``, ``store`` (an object written without reaction: 0x6074) and
    ``target_outside`` (a target beyond 0x607D: counted; returns True when it is refused by a fault,
    0x2012 = 1). ``axis`` is the axis as last observed (the drive keeps it current)."""

    def __init__(self, sim: AxisSimulator, cycle_s: float, switches: LimitSwitchMonitor,
                 homing_owns_switches: Callable[[], bool], params: Callable[[], DriveParameters],
                 store: Callable[[tuple[int, int], int | float], None],
                 target_outside: Callable[[int], bool]) -> None:
        self._sim = sim
        self._cycle_s = cycle_s
        self._switches = switches
        self._homing_owns_switches = homing_owns_switches
        self._params = params
        self._store = store
        self._target_outside = target_outside
        self.axis = sim.state  # the axis as last observed
        self.demand_m = 0.0  # position demand, drive coordinate [m]
        self.zero_m = 0.0  # plant position of the drive's zero [m]
        self.demand_v = 0.0  # velocity demand [m/s]
        self.last_vff = 0.0  # speed feed-forward sent last [m/s]
        self.control: ControlMode = sim.mode
        self.internal_limit = False  # a limiter acted (statusword bit 11)
        self.position_sign = 1  # 0x607E bit 7: -1 (a position object is this times the drive's position)
        self.velocity_sign = 1  # 0x607E bit 6: -1 (a velocity / torque object is this times the drive's)

    def set_polarity(self, polarity: int) -> None:
        """Polarity 0x607E: bit 7 position, bit 6 velocity (and torque) values multiplied by -1."""
        self.position_sign = -1 if polarity & 0x80 else 1
        self.velocity_sign = -1 if polarity & 0x40 else 1

    # ------------------------------------------------------------------ plant
    def set_control(self, mode: ControlMode) -> None:
        """The plant's loop in command (position, velocity, torque)."""
        if mode != self.control:
            self._sim.set_mode(mode)
            self.control = mode

    def send_position(self, p_m: float, vff_m_s: float, acc_m_s2: float) -> None:
        """Position set-point ``p_m`` (drive coordinate) with speed / acceleration feed-forward, unlimited."""
        self._sim.set_position_setpoint(p_m + self.zero_m, vff_m_s, acc_m_s2)

    def send_velocity(self, v_m_s: float) -> None:
        """Speed set-point [m/s], unlimited."""
        self._sim.set_velocity_setpoint(v_m_s)

    def position_of(self, x_plant_m: float) -> float:
        """A plant position in drive coordinates [m]."""
        return x_plant_m - self.zero_m

    # ------------------------------------------------------------------ limiters
    def _blocked_direction(self) -> int:
        switches = self._switches
        return switches.blocked_direction(self._homing_owns_switches()) if switches.switches else 0

    def position(self, p_m: float, vff_m_s: float) -> None:
        """Position set-point ``p_m`` with speed feed-forward ``vff_m_s`` (the acceleration feed-forward from
        its change): no further toward an active limit switch (bit 11)."""
        blocked = self._blocked_direction()
        if blocked and (p_m - self.demand_m) * blocked > 0.0:
            p_m, vff_m_s = self.demand_m, 0.0
            self.internal_limit = True
        acc = (vff_m_s - self.last_vff) / self._cycle_s
        self.last_vff = vff_m_s
        self.demand_m, self.demand_v = p_m, vff_m_s
        self._sim.set_position_setpoint(p_m + self.zero_m, vff_m_s, acc)

    def velocity_limit(self, v_m_s: float, *, velocity_mode: bool = True) -> float:
        """A velocity: zero outward beyond a software limit or toward an active limit switch (bit 11); within
        them a velocity mode (``velocity_mode``) clears bit 11."""
        blocked = self._blocked_direction()
        if blocked and v_m_s * blocked > 0.0:
            self.internal_limit = True
            return 0.0
        lim = self._params().travel_limits_m
        if lim is None:
            return v_m_s
        x = self.axis.position_m - self.zero_m
        if (x >= lim[1] and v_m_s > 0) or (x <= lim[0] and v_m_s < 0):
            self.internal_limit = True
            return 0.0
        if velocity_mode:
            self.internal_limit = False
        return v_m_s

    def clamp_velocity(self, v_m_s: float) -> float:
        """A velocity target limited by 0x607F max profile velocity and 0x6080 max motor speed [m/s]."""
        vmax = self._params().max_velocity_m_s
        return max(-vmax, min(vmax, v_m_s))

    def torque(self, t_nm: float, rated_nm: float, t_max_nm: float, requested_nm: float | None = None) -> None:
        """Torque set-point: limited to +-``t_max_nm`` (0x6072), none pushing outward beyond a software limit;
        the plant's speed limiter (0x6080) caps it near the maximum speed; bit 11 while any limit acts;
        0x6074 = the torque demanded of the motor (per mille of ``rated_nm``)."""
        requested = t_nm if requested_nm is None else requested_nm
        limited = abs(requested) > t_max_nm
        t = max(-t_max_nm, min(t_max_nm, t_nm))
        if t != 0.0 and self.velocity_limit(math.copysign(1.0, t), velocity_mode=False) == 0.0:
            t, limited = 0.0, True
        v = self.axis.velocity_m_s
        if t * v > 0.0 and abs(v) >= SPEED_LIMIT_SHARE * self._params().max_speed_m_s:
            limited = True
        self.internal_limit = limited
        self._sim.set_torque_setpoint(t)
        self._store((0x6074, 0), clamp_to_dtype(self.velocity_sign * t / rated_nm * 1000 if rated_nm else 0, "i16"))

    def check_limit(self, target_m: float, raw_value: int) -> float | None:
        """A position target within the software limits 0x607D: clamped (bit 11), or None when the target is
        refused by a fault (0x2012 = 1)."""
        lim = self._params().travel_limits_m
        if lim is None or lim[0] <= target_m <= lim[1]:
            self.internal_limit = False
            return target_m
        if self._target_outside(raw_value):
            return None
        self.internal_limit = True
        return min(max(target_m, lim[0]), lim[1])
