"""The CiA 402 modes of operation by number (0x6060 / 0x6061, the bits of 0x6502): the one definition."""

from __future__ import annotations

import enum


class OperationMode(enum.IntEnum):
    """0x6060 values of the modes this drive offers (0: no mode, the position is held)."""

    NO_MODE = 0
    PP = 1  # profile position
    PV = 3  # profile velocity
    PT = 4  # profile torque
    HM = 6  # homing
    IP = 7  # interpolated position
    CSP = 8  # cyclic synchronous position
    CSV = 9  # cyclic synchronous velocity
    CST = 10  # cyclic synchronous torque


#: the mode's bit in 0x6502 supported drive modes (bit = number - 1)
SUPPORTED_MODE_BITS = {m: 1 << (m - 1) for m in OperationMode if m != OperationMode.NO_MODE}
#: the position profile modes and those that hold a position
TORQUE_MODES = (OperationMode.PT, OperationMode.CST)
POSITION_MODES = (OperationMode.PP, OperationMode.HM, OperationMode.IP, OperationMode.CSP)
VELOCITY_MODES = (OperationMode.PV, OperationMode.CSV)
