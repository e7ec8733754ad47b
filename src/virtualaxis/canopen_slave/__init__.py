"""CiA 301 CANopen slave stack: EDS-loaded object dictionary, NMT, SDO server (expedited, segmented,
block), PDO engine, SYNC, EMCY, heartbeat, node guarding, store/restore. See docs/canopen-slave-api.md."""

from virtualaxis.canopen_slave.errors import SdoAbort
from virtualaxis.canopen_slave.nmt import NmtState
from virtualaxis.canopen_slave.slave import CanopenSlave, DeviceApplication
from virtualaxis.resources import project_file

#: eds/virtualaxis.eds of the repository, or of the installed data files
DEFAULT_EDS_PATH = project_file("eds/virtualaxis.eds")

__all__ = ["CanopenSlave", "DeviceApplication", "NmtState", "SdoAbort", "DEFAULT_EDS_PATH"]
