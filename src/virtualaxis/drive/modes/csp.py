"""CSP (8): cyclic synchronous position."""

from __future__ import annotations

from typing import TYPE_CHECKING

from virtualaxis.drive import reactions as rx
from virtualaxis.drive.modes.base import OperatingMode, ProfileGenerator, register
from virtualaxis.drive.opmodes import OperationMode
from virtualaxis.drive.profiles import LinearInterpolator
from virtualaxis.sim import CONTROL_MODE

if TYPE_CHECKING:
    from virtualaxis.drive.core import Drive


@register
class CyclicPosition(OperatingMode):
    """CSP (8): 0x607A every cycle, interpolated over 0x60C2 (``interp``), velocity offset 0x60B1 as
    feed-forward."""

    number = OperationMode.CSP

    def __init__(self, gen: ProfileGenerator):
        super().__init__(gen)
        self.interp = LinearInterpolator()
        self.interp.reset(gen.target_m)

    def reset(self, d: Drive, p_m: float) -> None:
        self.interp.reset(p_m)

    def enter(self, d: Drive) -> None:
        # the master's next target takes over; until then the demand is the actual position (+ lag)
        moving = d._power and not rx.at_standstill(d)
        v_act = d._axis.velocity_m_s if moving else 0.0
        if moving and d.setpoints.control != CONTROL_MODE.POSITION:
            d.setpoints.demand_m += d._lag_m(v_act)
            self.interp.reset(d.setpoints.demand_m)
        d.setpoints.set_control(CONTROL_MODE.POSITION)
        d.setpoints.send_position(d.setpoints.demand_m, v_act, 0.0)

    def on_target_position(self, d: Drive, value: int) -> None:
        if d._state_enabled() and d._stop is None:
            target = d._check_limit(value * d._u, value)
            if target is not None:
                self.interp.new_target(target, d._interp_cycles())

    def cycle(self, d: Drive) -> None:
        p, slope = self.interp.step()
        d._set_position(p, slope / d.cycle_s + int(d.objects[(0x60B1, 0)]) * d._u)

    def stop(self, d: Drive, decel_m_s2: float) -> None:
        self.interp.reset(d.setpoints.demand_m)  # no further targets: hold (a CS mode follows the master)

    def target_reached(self, d: Drive, ax, dt: float) -> bool:
        pc = d._pc
        x = ax.position_m - d.setpoints.zero_m
        it = self.interp
        cond = abs(it.end - x) <= pc.position_window_m and it.i >= it.n
        return d._tr_timer.update(cond, dt, pc.position_time_s)

    def status_bits(self, d: Drive) -> int:
        # bit 12: the drive follows the command value (not while a shutdown / disable-operation ramp runs)
        return (0x1000 if d._stop is None else 0) | (0x2000 if d._fe_exceeded else 0)
