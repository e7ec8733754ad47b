"""Holding brake control and safe torque off (STO) of the drive (SINAMICS / AX5000 / AKD-style).

Brake control (objects 0x2040, 0x2041, 0x60FE; the brake's physics is
:class:`~virtualaxis.sim.brake.HoldingBrake`):

- enable (switched on -> operation enabled): the power stage is switched on and holds the actual position, the
  brake is opened, and the drive stays in SWITCHED ON for the brake opening delay 0x2040 [ms]; then it enters
  OPERATION ENABLED and accepts motion;
- a stop that ends in a state without torque (disable operation / shutdown with a ramp, quick stop 1..4, a
  fault reaction with a ramp): at standstill the brake is closed and the position held with torque for the
  brake closing delay 0x2041 [ms]; then the power stage is switched off and the state changes;
- every switch-off without a ramp (disable voltage, coast, STO, a coast fault): torque off at once and the brake
  closed at once (it holds after its own closing time);
- 0x60FE:1 bit 0 (set brake): the brake output (1 = brake applied). With 0x60FE:2 bit 0 set the master drives
  it: 1 applies the brake, 0 releases it; a release while the power stage is off is refused (SDO abort
  0x08000022) when the axis carries a standing load (``effects.force_offset_n``, e.g. a vertical axis), and a
  brake released this way closes when the power stage switches off: 0x60FE:1 bit 0 then reads 1 (applied) and
  the master releases it again once the power stage is on. 0x60FE:1 bit 0 always shows the brake output.

Without a brake in the axis config the delays are 0 and the drive enables and disables as without this module.

Safe torque off: the STO input (0x2042 = 1, the simulated safety terminal; or the fault injection kind
``safe_torque_off``) switches the power stage off at once (torque off from the next position cycle on), closes
the brake, takes the drive to SWITCH ON DISABLED (FAULT REACTION ACTIVE to FAULT), shows 0x60FD bit 18 and
statusword bit 14, and raises the warning :data:`STO_EMCY` (statusword bit 7, EMCY). While it is active the
drive refuses to switch on (shutdown is ignored); once it is gone the drive stays where it is (restart
interlock): shutdown -> switch on -> enable operation (and a fault reset in FAULT) start it again.
"""

from __future__ import annotations

import enum

#: brake opening delay [ms] (SINAMICS p1216, AKD MOTOR.TBRAKERELEASE), brake closing delay [ms] (p1217,
#: MOTOR.TBRAKEAPPLY), the STO input (1 = torque off demanded)
OBJ_OPENING_DELAY = (0x2040, 0)
OBJ_CLOSING_DELAY = (0x2041, 0)
OBJ_STO_INPUT = (0x2042, 0)
OBJ_OUTPUTS = (0x60FE, 1)  # physical outputs: bit 0 set brake
OBJ_OUTPUT_MASK = (0x60FE, 2)  # bit mask: bit 0 = the master drives the brake output
SET_BRAKE = 0x1
#: EMCY code of safe torque off active (CiA 301 0x5400: device hardware, power section; the gate drive of the
#: power section is off)
STO_EMCY = 0x5400
STO_INPUT_BIT = 1 << 18  # 0x60FD: manufacturer-specific bit 18 (16 / 17 are the touch probe inputs)
STO_STATUS_BIT = 0x4000  # statusword bit 14 (manufacturer-specific)
ABORT_DEVICE_STATE = 0x08000022


class BrakePhase(enum.Enum):
    IDLE = 0
    OPENING = 1  # power on, holding, brake opening: the drive waits 0x2040 before OPERATION ENABLED
    CLOSING = 2  # at standstill, brake closing, torque held for 0x2041 before the power stage switches off


class BrakeControl:
    """The drive's brake sequence: its phase, the time spent in it and the state to take after closing."""

    def __init__(self, has_brake: bool, standing_load: bool):
        self.has_brake = has_brake
        self.standing_load = standing_load
        self.phase = BrakePhase.IDLE
        self.elapsed_s = 0.0
        self.then: object = None  # the state to take once closed (CLOSING)

    def busy(self) -> bool:
        return self.phase is not BrakePhase.IDLE

    def start(self, phase: BrakePhase, delay_ms: int, then: object = None) -> bool:
        """Enter ``phase`` for ``delay_ms``; False (nothing to wait for) without a brake or with a zero delay."""
        if not self.has_brake or delay_ms <= 0:
            self.phase = BrakePhase.IDLE
            return False
        if self.phase is not phase:
            self.phase, self.elapsed_s = phase, 0.0
        self.then = then
        return True

    def tick(self, dt_s: float, delay_ms: int) -> bool:
        """One cycle of the phase; True when its delay has elapsed (the phase is then over)."""
        self.elapsed_s += dt_s
        if self.elapsed_s * 1000.0 >= delay_ms - 1e-9:
            self.phase = BrakePhase.IDLE
            return True
        return False

    def stop(self) -> None:
        self.phase = BrakePhase.IDLE
        self.elapsed_s = 0.0
        self.then = None

    def released(self, powered: bool, outputs: int, mask: int) -> bool:
        """Whether the brake output releases the brake: the drive's sequence (released while the power stage is
        on and not closing), or the master's 0x60FE:1 bit 0 where 0x60FE:2 bit 0 gives it the output (a release
        without torque only for an axis without a standing load)."""
        if mask & SET_BRAKE:
            release = not outputs & SET_BRAKE
            return release and (powered or not self.standing_load)
        return powered and self.phase is not BrakePhase.CLOSING

    def check_output_write(self, key: tuple[int, int], value: int, outputs: int, mask: int, powered: bool) -> str:
        """Why writing 0x60FE:1 / :2 = ``value`` is refused ('' if allowed): a master release of the brake while
        the power stage is off on an axis with a standing load."""
        if key == OBJ_OUTPUTS:
            outputs = value
        elif key == OBJ_OUTPUT_MASK:
            mask = value
        else:
            return ""
        if mask & SET_BRAKE and not outputs & SET_BRAKE and not powered and self.standing_load:
            return ("brake release refused: the power stage is off and the axis carries a standing load "
                    "(effects.force_offset_n)")
        return ""


class SafeTorqueOff:
    """The STO input: active while any source (``terminal`` 0x2042, ``injected``) demands it."""

    def __init__(self) -> None:
        self.sources: set[str] = set()

    @property
    def active(self) -> bool:
        return bool(self.sources)

    def set(self, source: str, active: bool) -> tuple[bool, bool]:
        """Set one source; returns (was active, is active)."""
        was = self.active
        if active:
            self.sources.add(source)
        else:
            self.sources.discard(source)
        return was, self.active


def brake_objects(opening_time_s: float, closing_time_s: float) -> dict[tuple[int, int], int]:
    """The delays commissioned for a brake with these data-sheet times: each rounded up to whole ms (no brake:
    0, 0)."""
    import math

    return {OBJ_OPENING_DELAY: int(math.ceil(opening_time_s * 1000.0 - 1e-9)),
            OBJ_CLOSING_DELAY: int(math.ceil(closing_time_s * 1000.0 - 1e-9))}
