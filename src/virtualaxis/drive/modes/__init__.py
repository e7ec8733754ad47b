"""The CiA 402 modes of operation: one module per mode, each class registered by its number
(:class:`~virtualaxis.drive.opmodes.OperationMode`); the contract is
:class:`~virtualaxis.drive.modes.base.OperatingMode`."""

from virtualaxis.drive.modes.base import MODE_TYPES, OperatingMode, ProfileGenerator, make_modes, register
from virtualaxis.drive.modes.csp import CyclicPosition
from virtualaxis.drive.modes.cst import CyclicTorque
from virtualaxis.drive.modes.csv import CyclicVelocity
from virtualaxis.drive.modes.hm import HOMING_CRAWL_M, Homing
from virtualaxis.drive.modes.ip import InterpolatedPosition
from virtualaxis.drive.modes.pp import ProfilePosition
from virtualaxis.drive.modes.pt import ProfileTorque
from virtualaxis.drive.modes.pv import ProfileVelocity
from virtualaxis.drive.opmodes import OperationMode

__all__ = ["HOMING_CRAWL_M", "MODE_TYPES", "CyclicPosition", "CyclicTorque", "CyclicVelocity", "Homing",
           "InterpolatedPosition", "OperatingMode", "OperationMode", "ProfileGenerator", "ProfilePosition",
           "ProfileTorque", "ProfileVelocity", "make_modes", "register"]
