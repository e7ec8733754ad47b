"""CiA 301 CANopen slave stack: EDS-loaded object dictionary, NMT, SDO server (expedited, segmented,
block), PDO engine, SYNC, EMCY, heartbeat, node guarding, store/restore. See docs/canopen-slave-api.md."""

from pathlib import Path

from virtualaxis.canopen_slave.errors import SdoAbort
from virtualaxis.canopen_slave.nmt import NmtState
from virtualaxis.canopen_slave.slave import CanopenSlave, DeviceApplication

#: eds/virtualaxis.eds of the source tree (the package is installed editable from the repository)
DEFAULT_EDS_PATH = Path(__file__).resolve().parents[3] / "eds" / "virtualaxis.eds"

__all__ = ["CanopenSlave", "DeviceApplication", "NmtState", "SdoAbort", "DEFAULT_EDS_PATH"]
