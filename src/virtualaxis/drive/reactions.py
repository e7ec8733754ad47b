"""Stop reactions of the drive, in one place, always FROM THE ACTUAL MOTION.

Every way the drive brings the axis to rest goes through :class:`StopRamp`: quick stop (0x605A), shutdown /
disable operation with a ramp (0x605B / 0x605C), the fault reaction (0x605E, or the fault's own class in
:data:`~virtualaxis.drive.faults.FAULT_TABLE`), abort connection (0x6007), a hardware limit switch and a mode
change while moving. A real drive (SINAMICS OFF1/OFF3, a CiA 402 servo) brakes the motor it measures, not a
set-point that may already be at rest (after a following-error fault the demand is far from the axis):

- ``slow`` (0x6084 profile deceleration) and ``quick`` (0x6085 quick-stop deceleration): as SINAMICS
  OFF1 / OFF3, a ramp on the speed set-point that starts at the ACTUAL speed and decelerates with the given
  rate (the speed controller's integrator carries over: no bump); at standstill the position loop takes
  over and holds. The stopping distance is v^2 / (2 a) whatever the position demand was.
- ``current``: speed set-point 0, the speed controller brakes at the current limit (0x6073 / 0x6072).
- ``coast``: pulses off at once (OFF2): encoder loss, over-current, option 0.

Once the ramp is at zero the drive waits for standstill (|v| below 0x606F), holds the position for
:data:`HOLD_S` (SINAMICS p1228 pulse suppression delay) and only then changes the state (switch on disabled,
fault, ...). If the axis is not at standstill within :func:`brake_bound_s` of the start, braking has failed:
fault 0x8400 (F07900) is raised and the pulses are switched off. :func:`run_stop` steps one cycle and returns
its :class:`StopOutcome`; the state change or the fault is the drive's to apply. A stop sees the drive
through the modes' :class:`~virtualaxis.drive.mode_context.ModeContext`.

Whatever 0x6084 / 0x6085 hold, a stop is bounded in time and distance (:func:`bounded_decel_m_s2`): the ramp
takes at most :data:`MAX_STOP_RAMP_S` and ends before the limit switch ahead (once past it, before the end
stop), steeper than configured where needed; the ramp is monitored (:func:`ramp_not_followed`), and an axis
that does not follow it falls back to the current-limit stop, which has :data:`CURRENT_STOP_BOUND_S` before
'braking failed'.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from virtualaxis.drive.profiles import VelocityRamp
from virtualaxis.drive.statemachine import Cia402State
from virtualaxis.sim import CONTROL_MODE

if TYPE_CHECKING:
    from virtualaxis.drive.mode_context import ModeContext

#: hold at standstill before the pulses are switched off [s] (SINAMICS p1228 default 0.01 s... chosen 20 ms,
#: two speed-controller settling times of the bench axes)
HOLD_S = 0.02
#: standstill detection: |v| below max(0x606F, this) [m/s]
MIN_STANDSTILL_M_S = 1e-4
#: braking may take this factor x the ideal ramp time plus :data:`BRAKE_MARGIN_S` before it counts as failed
BRAKE_FACTOR = 1.5
BRAKE_MARGIN_S = 0.5
#: a current-limit stop is given this long [s] (the achievable deceleration is not known in advance)
CURRENT_STOP_BOUND_S = 3.0
#: longest stop ramp [s]: a ramp 0x6084 / 0x6085 slower than this from the actual speed is steepened to it
#: (chosen: 10 s; SINAMICS allows OFF1 / OFF3 ramps up to 600 s, but a machine-tool axis whose stop takes
#: longer than seconds is not under control)
MAX_STOP_RAMP_S = 10.0
#: a ramp is planned to end within this share of the room ahead (to the limit switch, once past it to the end
#: stop): steeper than 0x6084 / 0x6085 where they would not (chosen: 0.8, room for the speed loop's lag)
STOP_ROOM_SHARE = 0.8
#: ramp monitoring: the actual speed may exceed the ramp by this share of the start speed (plus the standstill
#: threshold) for at most :data:`RAMP_MONITOR_S` before the stop falls back to the current limit (chosen:
#: 10 % and 20 ms, several speed-loop settling times of the bench axes)
RAMP_TOLERANCE_SHARE = 0.1
RAMP_MONITOR_S = 0.02

#: 0x605E fault reaction option -> stop kind (negative: manufacturer-specific; this drive: quick stop)
FAULT_OPTION_KIND = {0: "coast", 1: "slow", 2: "quick", 3: "current", 4: "current"}
#: 0x605A quick stop option -> stop kind (1..4: then switch on disabled; 5..8: stay in quick stop active)
QUICK_STOP_OPTION_KIND = {0: "coast", 1: "slow", 2: "quick", 3: "current", 4: "current", 5: "slow", 6: "quick",
                          7: "current", 8: "current"}


def fault_reaction_kind(reaction_class: str, option_605e: int) -> str:
    """The stop kind of a fault: its class ("coast", "quick") or, for "option", 0x605E."""
    if reaction_class == "coast":
        return "coast"
    if reaction_class == "quick":
        return "quick"
    return FAULT_OPTION_KIND.get(option_605e, "quick")


def brake_bound_s(v0_m_s: float, decel_m_s2: float, kind: str) -> float:
    """Time after which an axis not at standstill counts as 'braking failed' [s]."""
    if kind == "current":
        return CURRENT_STOP_BOUND_S
    return BRAKE_FACTOR * abs(v0_m_s) / max(decel_m_s2, 1e-9) + BRAKE_MARGIN_S


@dataclass
class StopRamp:
    """One running stop (the drive holds it while it runs)."""

    kind: str  # "slow" | "quick" | "current"
    then: Cia402State | str | None  # state once stopped; None: keep holding; "resume": re-enter the mode
    decel_m_s2: float
    v_m_s: float  # ramp velocity (drive coordinate)
    p_m: float  # ramp position (drive coordinate)
    velocity_control: bool  # the ramp runs on the speed set-point (until standstill; then position hold)
    bound_s: float
    t_s: float = 0.0
    stopped_s: float = -1.0  # time the ramp reached zero and the axis standstill (-1: not yet)
    v0_m_s: float = 0.0
    hold_s: float = HOLD_S  # hold at standstill before the state change [s]
    vramp: VelocityRamp = field(default_factory=lambda: VelocityRamp(1e-3))  # the OFF1/OFF3 speed ramp

    ramp_exceeded_s: float = 0.0  # how long the actual speed has been beyond the monitored ramp [s]
    room_to_switch_m: float = 0.0  # room to the limit switch ahead at the start (<= 0: on or past it) [m]

    @classmethod
    def start(cls, ctx: ModeContext, kind: str, then: Cia402State | str | None) -> StopRamp:
        ax = ctx.axis
        v0 = ax.velocity_m_s
        p0 = ax.position_m - ctx.setpoints.zero_m + ctx.lag_m(v0)  # bumpless: the speed set-point = actual speed
        decel_obj = 0x6084 if kind == "slow" else 0x6085
        decel = float(ctx.obj(decel_obj)) * ctx.u
        if kind in ("slow", "quick"):
            decel, kind = bounded_decel_m_s2(ctx, v0, decel, kind)
        decel = max(decel, 1e-6)
        velocity_control = True  # OFF1/OFF3 ramp on the speed set-point, from the actual speed
        ctx.setpoints.set_control(CONTROL_MODE.VELOCITY)
        ramp = cls(kind, then, decel, v0, p0, velocity_control, brake_bound_s(v0, decel, kind), v0_m_s=v0,
                   vramp=VelocityRamp(ctx.cycle_s))
        ramp.vramp.velocity_m_s = v0
        ramp.room_to_switch_m = ctx.travel_room_m(v0)[0]
        if at_standstill(ctx):  # nothing to brake: hold where it is, the state change in the next cycle
            ramp.v_m_s, ramp.stopped_s, ramp.hold_s, ramp.kind = 0.0, 0.0, 0.0, "hold"
            if velocity_control:
                ctx.setpoints.set_control(CONTROL_MODE.POSITION)
                ramp.velocity_control = False
        return ramp


def bounded_decel_m_s2(ctx: ModeContext, v0_m_s: float, decel_m_s2: float, kind: str) -> tuple[float, str]:
    """The deceleration of a ramp stop from ``v0_m_s`` [m/s^2] and its kind: the configured ``decel_m_s2``,
    steepened so that the ramp takes at most :data:`MAX_STOP_RAMP_S` and ends within :data:`STOP_ROOM_SHARE`
    of the room ahead (before the limit switch; once past it, before the end stop). No room left: the
    current-limit stop."""
    v = abs(v0_m_s)
    if v == 0.0:
        return decel_m_s2, kind
    to_switch_m, to_end_m = ctx.travel_room_m(v0_m_s)
    room_m = to_switch_m if to_switch_m > 0.0 else to_end_m
    if room_m <= 0.0:
        return decel_m_s2, "current"
    needed = max(v / MAX_STOP_RAMP_S, v * v / (2.0 * STOP_ROOM_SHARE * room_m))
    return max(decel_m_s2, needed), kind


def standstill_threshold_m_s(ctx: ModeContext) -> float:
    """|v| below this is standstill: 0x606F velocity threshold, at least :data:`MIN_STANDSTILL_M_S` [m/s]."""
    return max(float(ctx.obj(0x606F)) * ctx.u, MIN_STANDSTILL_M_S)


def at_standstill(ctx: ModeContext) -> bool:
    return abs(ctx.axis.velocity_m_s) < standstill_threshold_m_s(ctx)


class StopOutcome(enum.Enum):
    """What one cycle of a stop ramp came to (:func:`run_stop`); the drive applies it."""

    RUNNING = "running"  # ramping, or holding at standstill
    FALLBACK = "braking fallback"  # the ramp was not followed: braking at the current limit from now on
    DONE = "done"  # stopped and held: the state change the stop was for
    FAILED = "failed"  # not at standstill within the bound: fault 0x8400, pulses off


def run_stop(ctx: ModeContext, s: StopRamp) -> StopOutcome:
    """One cycle of the stop ``s``: ramp, standstill, hold; returns the outcome (the state change, or the
    braking-failed fault, is the drive's)."""
    s.t_s += ctx.cycle_s
    ax = ctx.axis
    threshold = standstill_threshold_m_s(ctx)
    outcome = StopOutcome.RUNNING
    if s.kind == "hold":
        ctx.setpoints.position(s.p_m, 0.0)
        ramp_done = True
    elif s.kind == "current":
        ctx.setpoints.send_velocity(0.0)
        ctx.setpoints.demand_v = 0.0
        ramp_done = True
    else:  # OFF1 / OFF3: the speed set-point ramps down from the actual speed
        v = s.vramp.step(0.0, s.decel_m_s2, s.decel_m_s2)
        ctx.setpoints.demand_v = v
        ctx.setpoints.send_velocity(v)
        ramp_done = v == 0.0
        if ramp_not_followed(ctx, s, v, threshold):  # monitored ramp: fall back to the current limit
            s.kind = "current"
            s.bound_s = s.t_s + CURRENT_STOP_BOUND_S
            ctx.setpoints.send_velocity(0.0)
            ctx.setpoints.demand_v = 0.0
            outcome = StopOutcome.FALLBACK
    if ramp_done and s.stopped_s < 0.0 and abs(ax.velocity_m_s) < threshold:
        s.stopped_s = s.t_s
        if s.velocity_control:  # hold the position where the axis came to rest
            ctx.setpoints.demand_m = ax.position_m - ctx.setpoints.zero_m
            ctx.setpoints.set_control(CONTROL_MODE.POSITION)
            ctx.setpoints.position(ctx.setpoints.demand_m, 0.0)
            s.velocity_control = False
            s.kind = "hold"
            s.v_m_s, s.p_m = 0.0, ctx.setpoints.demand_m
    if s.stopped_s < 0.0:
        return StopOutcome.FAILED if s.t_s > s.bound_s else outcome
    if s.t_s - s.stopped_s < s.hold_s - 1e-12:
        return outcome
    return StopOutcome.DONE


def ramp_not_followed(ctx: ModeContext, s: StopRamp, v_ramp_m_s: float, threshold_m_s: float) -> bool:
    """Ramp monitoring of a ramp stop: the actual speed above the ramp by more than the tolerance for
    :data:`RAMP_MONITOR_S`, or the axis still moving onto the limit switch ahead (the ramp was planned to
    end before it) or into the end stop."""
    v_act = ctx.axis.velocity_m_s
    if abs(v_act) > abs(v_ramp_m_s) + RAMP_TOLERANCE_SHARE * abs(s.v0_m_s) + threshold_m_s:
        s.ramp_exceeded_s += ctx.cycle_s
    else:
        s.ramp_exceeded_s = 0.0
    if s.ramp_exceeded_s >= RAMP_MONITOR_S - 1e-12:
        return True
    if abs(v_act) < threshold_m_s:
        return False
    to_switch_m, to_end_m = ctx.travel_room_m(v_act)
    started_before_switch = s.room_to_switch_m > 0.0
    return (to_switch_m <= 0.0 and started_before_switch) or to_end_m <= 0.0
