"""The CiA 402 power drive state machine: controlword decoding, transitions, statusword state bits.

Only the logic lives here (pure functions); the drive applies the reactions (ramps, power stage).
"""

from __future__ import annotations

import enum
import types


class Cia402State(enum.Enum):
    NOT_READY_TO_SWITCH_ON = "NOT READY TO SWITCH ON"
    SWITCH_ON_DISABLED = "SWITCH ON DISABLED"
    READY_TO_SWITCH_ON = "READY TO SWITCH ON"
    SWITCHED_ON = "SWITCHED ON"
    OPERATION_ENABLED = "OPERATION ENABLED"
    QUICK_STOP_ACTIVE = "QUICK STOP ACTIVE"
    FAULT_REACTION_ACTIVE = "FAULT REACTION ACTIVE"
    FAULT = "FAULT"


S = Cia402State

# statusword bits 0..3, 5, 6 per state (bit 4 "voltage enabled" is added by the drive)
STATE_BITS: dict[Cia402State, int] = {
    S.NOT_READY_TO_SWITCH_ON: 0x0000,
    S.SWITCH_ON_DISABLED: 0x0040,
    S.READY_TO_SWITCH_ON: 0x0021,
    S.SWITCHED_ON: 0x0023,
    S.OPERATION_ENABLED: 0x0027,
    S.QUICK_STOP_ACTIVE: 0x0007,
    S.FAULT_REACTION_ACTIVE: 0x002F,
    S.FAULT: 0x0028,
}


class Command(enum.Enum):
    DISABLE_VOLTAGE = "disable voltage"
    QUICK_STOP = "quick stop"
    SHUTDOWN = "shutdown"
    SWITCH_ON = "switch on"
    ENABLE_OPERATION = "enable operation"


def decode(controlword: int) -> Command:
    """The device control command in controlword bits 0..3 (bit 7, fault reset, is an edge: see drive)."""
    if not controlword & 0x2:
        return Command.DISABLE_VOLTAGE
    if not controlword & 0x4:
        return Command.QUICK_STOP
    if not controlword & 0x1:
        return Command.SHUTDOWN
    if not controlword & 0x8:
        return Command.SWITCH_ON
    return Command.ENABLE_OPERATION


class Transition(enum.IntEnum):
    """CiA 402 transition numbers; HOLD = the command keeps the present state; ILLEGAL = not a transition."""

    HOLD = 0
    T2 = 2  # switch on disabled -> ready to switch on
    T3 = 3  # ready -> switched on
    T4 = 4  # switched on -> operation enabled
    T5 = 5  # operation enabled -> switched on (0x605C)
    T6 = 6  # switched on -> ready
    T7 = 7  # ready -> switch on disabled
    T8 = 8  # operation enabled -> ready (0x605B)
    T9 = 9  # operation enabled -> switch on disabled (coast)
    T10 = 10  # switched on -> switch on disabled
    T11 = 11  # operation enabled -> quick stop active (0x605A)
    T12 = 12  # quick stop active -> switch on disabled
    T16 = 16  # quick stop active -> operation enabled (0x605A = 5..8)
    T3_4 = 34  # ready -> switched on -> operation enabled in one command
    ILLEGAL = -1
    IGNORED = -2  # commands have no meaning in this state (fault reaction active, fault)


#: the members as plain attributes (``STATE.FAULT is Cia402State.FAULT``, ``TRANSITION.T4 is Transition.T4``):
#: CPython 3.11 looks an Enum member up through the class's descriptors, ~10x a plain attribute, and the drive
#: cycle reads states and transitions several times per cycle
STATE = types.SimpleNamespace(**Cia402State.__members__)
TRANSITION = types.SimpleNamespace(**Transition.__members__)


_TABLE: dict[Cia402State, dict[Command, Transition]] = {
    S.SWITCH_ON_DISABLED: {
        Command.DISABLE_VOLTAGE: Transition.HOLD,
        Command.QUICK_STOP: Transition.HOLD,
        Command.SHUTDOWN: Transition.T2,
        Command.SWITCH_ON: Transition.ILLEGAL,
        Command.ENABLE_OPERATION: Transition.ILLEGAL,
    },
    S.READY_TO_SWITCH_ON: {
        Command.DISABLE_VOLTAGE: Transition.T7,
        Command.QUICK_STOP: Transition.T7,
        Command.SHUTDOWN: Transition.HOLD,
        Command.SWITCH_ON: Transition.T3,
        Command.ENABLE_OPERATION: Transition.T3_4,
    },
    S.SWITCHED_ON: {
        Command.DISABLE_VOLTAGE: Transition.T10,
        Command.QUICK_STOP: Transition.T10,
        Command.SHUTDOWN: Transition.T6,
        Command.SWITCH_ON: Transition.HOLD,
        Command.ENABLE_OPERATION: Transition.T4,
    },
    S.OPERATION_ENABLED: {
        Command.DISABLE_VOLTAGE: Transition.T9,
        Command.QUICK_STOP: Transition.T11,
        Command.SHUTDOWN: Transition.T8,
        Command.SWITCH_ON: Transition.T5,
        Command.ENABLE_OPERATION: Transition.HOLD,
    },
    S.QUICK_STOP_ACTIVE: {
        Command.DISABLE_VOLTAGE: Transition.T12,
        Command.QUICK_STOP: Transition.HOLD,
        Command.SHUTDOWN: Transition.ILLEGAL,
        Command.SWITCH_ON: Transition.ILLEGAL,
        Command.ENABLE_OPERATION: Transition.T16,  # only with 0x605A = 5..8, checked by the drive
    },
}


def transition_for(state: Cia402State, command: Command) -> Transition:
    """The transition a command requests in a state (before option-code checks)."""
    table = _TABLE.get(state)
    if table is None:  # not ready, fault reaction active, fault: commands are not evaluated
        return Transition.IGNORED
    return table[command]


TARGET_STATE: dict[Transition, Cia402State] = {
    Transition.T2: S.READY_TO_SWITCH_ON,
    Transition.T3: S.SWITCHED_ON,
    Transition.T4: S.OPERATION_ENABLED,
    Transition.T5: S.SWITCHED_ON,
    Transition.T6: S.READY_TO_SWITCH_ON,
    Transition.T7: S.SWITCH_ON_DISABLED,
    Transition.T8: S.READY_TO_SWITCH_ON,
    Transition.T9: S.SWITCH_ON_DISABLED,
    Transition.T10: S.SWITCH_ON_DISABLED,
    Transition.T11: S.QUICK_STOP_ACTIVE,
    Transition.T12: S.SWITCH_ON_DISABLED,
    Transition.T16: S.OPERATION_ENABLED,
    Transition.T3_4: S.OPERATION_ENABLED,
}
