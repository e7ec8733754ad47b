"""The CiA 402 drive: state machine, modes, monitoring, faults around the axis simulator, and the one
drive API (``Drive``) that CANopen, Modbus, MQTT, conformance tests and fault injection use.
See docs/drive-api.md and docs/drive.md."""

from typing import TYPE_CHECKING

from virtualaxis.lazy import lazy_exports

if TYPE_CHECKING:
    from virtualaxis.drive.core import DEFAULT_EDS, Drive, ObjectAccessError
    from virtualaxis.drive.faults import FAULT_TABLE, FaultRecord
    from virtualaxis.drive.snapshot import PARAMETERS, DriveState
    from virtualaxis.drive.statemachine import Cia402State

# imported on first use (virtualaxis.lazy): a submodule such as drive.injection loads without the kernel
__getattr__, __dir__ = lazy_exports(__name__, {
    "DEFAULT_EDS": "virtualaxis.drive.core", "Drive": "virtualaxis.drive.core",
    "ObjectAccessError": "virtualaxis.drive.core", "FAULT_TABLE": "virtualaxis.drive.faults",
    "FaultRecord": "virtualaxis.drive.faults", "PARAMETERS": "virtualaxis.drive.snapshot",
    "DriveState": "virtualaxis.drive.snapshot", "Cia402State": "virtualaxis.drive.statemachine",
}, globals())

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
