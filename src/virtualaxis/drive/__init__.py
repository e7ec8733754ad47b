"""The CiA 402 drive: state machine, modes, monitoring, faults around the axis simulator, and the one
drive API (``Drive``) that CANopen, Modbus, MQTT, conformance tests and fault injection use.
See docs/drive-api.md and docs/drive.md."""

from virtualaxis.drive.core import DEFAULT_EDS, Drive, ObjectAccessError
from virtualaxis.drive.faults import FAULT_TABLE, FaultRecord
from virtualaxis.drive.snapshot import PARAMETERS, DriveState
from virtualaxis.drive.statemachine import Cia402State

__all__ = [
    "DEFAULT_EDS",
    "FAULT_TABLE",
    "PARAMETERS",
    "Cia402State",
    "Drive",
    "DriveState",
    "FaultRecord",
    "ObjectAccessError",
]
