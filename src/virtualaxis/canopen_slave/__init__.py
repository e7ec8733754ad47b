"""CiA 301 CANopen slave stack: EDS-loaded object dictionary, NMT, SDO server (expedited, segmented,
block), PDO engine, SYNC, EMCY, heartbeat, node guarding, store/restore. See docs/canopen-slave-api.md."""

from virtualaxis.canopen_slave.app import BaseApplication, CanopenApplication
from virtualaxis.canopen_slave.errors import SdoAbort
from virtualaxis.canopen_slave.nmt import NmtState
from virtualaxis.canopen_slave.slave import CanopenSlave
from virtualaxis.resources import project_file

#: eds/virtualaxis.eds of the repository, or of the installed data files
DEFAULT_EDS_PATH = project_file("eds/virtualaxis.eds")

#: another name of :class:`CanopenApplication`
DeviceApplication = CanopenApplication

__all__ = ["BaseApplication", "CanopenApplication", "CanopenSlave", "DeviceApplication", "NmtState", "SdoAbort",
           "DEFAULT_EDS_PATH"]
