"""What a mode of operation (and a stop ramp, :mod:`virtualaxis.drive.reactions`) sees of its drive: the
:class:`ModeContext`. The drive builds one per power-on reset and keeps its state fields current; a mode
reads them, drives the axis through the set-point channel and returns its statusword bits as a value."""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

from virtualaxis.drive.profiles import WindowTimer

if TYPE_CHECKING:
    from virtualaxis.drive.parameters import DriveParameters
    from virtualaxis.drive.setpoints import SetpointChannel


class ModeContext:
    """The narrow view of one drive that its modes cycle on.

    Services (given by the drive): ``objects`` (the object values, read only: a mode never writes an object),
    ``setpoints`` (the set-point channel with its limiters), ``params()`` (the cached
    :class:`~virtualaxis.drive.parameters.DriveParameters`), ``switches(x_plant_m, method)`` (limit and home
    switch inputs), ``travel_room_m(direction)`` (room to the limit switch / end stop ahead),
    ``refuse_setpoint(reason)`` / ``accept_setpoint()`` (the warning of a set-point that cannot be planned) and
    :meth:`homed` (a homing run attained its home point).

    State (kept current by the drive): ``axis`` (the axis as last observed), ``prev_position_m`` (its plant
    position one cycle before), ``cw`` (controlword), ``powered`` (pulses on), ``enabled`` (OPERATION
    ENABLED), ``stopping`` (a stop ramp runs), ``u`` (metres per position unit), ``motor_rev_travel_m``; and
    the monitor flags a mode's status bits tell: ``fe_timer`` / ``fe_exceeded`` (following error 0x6065 /
    0x6066), ``speed_zero`` (0x606F / 0x6070), ``target_timer`` / ``target_reached`` (bit 10, restarted by
    :meth:`restart_target_window`)."""

    def __init__(self, *, objects: dict[tuple[int, int], int | float], setpoints: SetpointChannel, cycle_s: float,
                 params: Callable[[], DriveParameters],
                 switches: Callable[[float, int | None], tuple[bool, bool, bool]],
                 travel_room_m: Callable[[float], tuple[float, float]], refuse_setpoint: Callable[[str], None],
                 accept_setpoint: Callable[[], None], on_homed: Callable[[], None], stroke_m: float,
                 index_pulse_offset_m: float) -> None:
        self.objects = objects
        self.setpoints = setpoints
        self.cycle_s = cycle_s
        self.params = params
        self.switches = switches
        self.travel_room_m = travel_room_m
        self.refuse_setpoint = refuse_setpoint
        self.accept_setpoint = accept_setpoint
        self._on_homed = on_homed
        self.stroke_m = stroke_m
        self.index_pulse_offset_m = index_pulse_offset_m
        self.axis = setpoints.axis
        self.prev_position_m = 0.0
        self.cw = 0
        self.powered = False
        self.enabled = False
        self.stopping = False
        self.u = 1.0
        self.motor_rev_travel_m = 1.0
        self.fe_timer = WindowTimer()
        self.fe_exceeded = False
        self.speed_zero = False
        self.target_timer = WindowTimer()
        self.target_reached = False

    def obj(self, index: int, sub: int = 0) -> int | float:
        """An object's value."""
        return self.objects[(index, sub)]

    @property
    def halted(self) -> bool:
        """Controlword bit 8 (halt)."""
        return bool(self.cw & 0x100)

    def lag_m(self, v_m_s: float) -> float:
        """Steady following error of the position loop at velocity ``v`` [m]: v (1 - k_ff) / Kv. A position
        demand placed this far ahead of the actual position takes over a moving axis bumplessly (the speed
        set-point equals the actual speed)."""
        o = self.objects
        kv = float(o[(0x2000, 0)]) * 1000.0 / 60.0
        kff = float(o[(0x2001, 0)]) if int(o[(0x2002, 0)]) >= 1 else 0.0
        return v_m_s * (1.0 - kff) / kv if kv > 0 else 0.0

    def home_offset_m(self) -> float:
        """Home offset 0x607C [m, the drive's direction]: the position the home point reads as."""
        return int(self.objects[(0x607C, 0)]) * self.u * self.setpoints.position_sign

    def homed(self) -> None:
        """A homing run has attained its home point (the drive tells its observers)."""
        self._on_homed()

    def restart_target_window(self) -> None:
        """Target reached (bit 10) false and its 0x6068 window timer restarted (new set-point / mode)."""
        self.target_reached = False
        self.target_timer = WindowTimer()
