"""COB-ID objects (0x1005 SYNC, 0x1012 TIME, 0x1014 EMCY, 0x1400-0x1403:1 RPDO, 0x1800-0x1803:1 TPDO): a
write that would make the object use a restricted COB-ID (CiA 301 7.3.5 table 39) or one another object of
this node already uses is refused with abort 0x06090030 (invalid value), the message naming the conflict."""

from __future__ import annotations

from typing import TYPE_CHECKING

from virtualaxis.canopen_slave import errors as ab
from virtualaxis.canopen_slave.errors import SdoAbort

if TYPE_CHECKING:
    from virtualaxis.canopen_slave.context import NodeContext

#: COB-IDs no configurable object may use (CiA 301 table 39: NMT, reserved, SDO, NMT error control, LSS)
RESTRICTED: tuple[tuple[int, int], ...] = (
    (0x000, 0x000), (0x001, 0x07F), (0x101, 0x180), (0x581, 0x5FF), (0x601, 0x67F),
    (0x6E0, 0x6FF), (0x701, 0x77F), (0x780, 0x7FF),
)
SYNC, TIME, EMCY = 0x1005, 0x1012, 0x1014
RPDO_COMM, TPDO_COMM, N_PDO = 0x1400, 0x1800, 4


def restricted(cob: int) -> bool:
    """True if ``cob`` (11 bit) is in the CiA 301 restricted list."""
    return any(lo <= cob <= hi for lo, hi in RESTRICTED)


def is_cob_id_object(index: int, sub: int) -> bool:
    """True for the COB-ID entries this module checks."""
    if index in (SYNC, TIME, EMCY):
        return sub == 0
    return sub == 1 and (RPDO_COMM <= index < RPDO_COMM + N_PDO or TPDO_COMM <= index < TPDO_COMM + N_PDO)


def _active(index: int, value: int) -> bool:
    """Whether a COB-ID value puts the object on the bus (valid / consumed / produced)."""
    if index == TIME:
        return bool(value & 0xC0000000)          # bit 31 consume, bit 30 produce
    return not value & 0x80000000                # SYNC (as this stack uses it), EMCY, PDOs: bit 31 = invalid


def _label(index: int) -> str:
    if index == SYNC:
        return "SYNC (0x1005)"
    if index == TIME:
        return "TIME (0x1012)"
    if index == EMCY:
        return "EMCY (0x1014)"
    if index < TPDO_COMM:
        return f"RPDO{index - RPDO_COMM + 1} (0x{index:04X}:1)"
    return f"TPDO{index - TPDO_COMM + 1} (0x{index:04X}:1)"


def in_use(slave: NodeContext, except_index: int) -> dict[int, str]:
    """COB-ID -> user, for every active COB-ID object of this node other than ``except_index``, plus the
    node's fixed ones (default SDO server, NMT error control)."""
    od = slave.od
    users: dict[int, str] = {
        0x600 + slave.node_id: "the SDO server (client -> server)",
        0x580 + slave.node_id: "the SDO server (server -> client)",
        0x700 + slave.node_id: "NMT error control",
    }
    candidates = [SYNC, TIME, EMCY] + [RPDO_COMM + n for n in range(N_PDO)] + [TPDO_COMM + n for n in range(N_PDO)]
    for index in candidates:
        if index == except_index:
            continue
        sub = 0 if index in (SYNC, TIME, EMCY) else 1
        if (index, sub) not in od:
            continue
        value = od.value(index, sub)
        if _active(index, value):
            users.setdefault(value & 0x7FF, _label(index))
    return users


def check_write(slave: NodeContext, index: int, value: int) -> None:
    """Refuse (SdoAbort 0x06090030) a COB-ID the object may not use."""
    if not _active(index, value):
        return
    cob = value & 0x7FF
    if restricted(cob):
        raise SdoAbort(ab.INVALID_VALUE, f"{_label(index)}: COB-ID 0x{cob:03X} is restricted (CiA 301)")
    user = in_use(slave, index).get(cob)
    if user is not None:
        raise SdoAbort(ab.INVALID_VALUE, f"{_label(index)}: COB-ID 0x{cob:03X} is already used by {user}")
