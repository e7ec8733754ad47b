"""NMT slave: states, the NMT commands on COB-ID 0x000 and the boot-up message."""

from __future__ import annotations

import enum
import types

NMT_COB = 0x000
START, STOP, ENTER_PRE_OPERATIONAL, RESET_NODE, RESET_COMMUNICATION = 0x01, 0x02, 0x80, 0x81, 0x82


class NmtState(enum.IntEnum):
    """NMT states; the values are the state byte of heartbeat and node-guarding frames."""

    INITIALISING = 0
    STOPPED = 4
    OPERATIONAL = 5
    PRE_OPERATIONAL = 127


#: the members as plain attributes (``NMT_STATE.OPERATIONAL is NmtState.OPERATIONAL``): CPython 3.11 looks an Enum
#: member up through the class's descriptors, ~10x a plain attribute, and every frame and cycle tests the state
NMT_STATE = types.SimpleNamespace(**NmtState.__members__)


#: command specifier -> target state (the two reset commands are handled by the slave)
COMMAND_STATES: dict[int, NmtState] = {
    START: NmtState.OPERATIONAL,
    STOP: NmtState.STOPPED,
    ENTER_PRE_OPERATIONAL: NmtState.PRE_OPERATIONAL,
}


def parse_command(data: bytes, node_id: int) -> tuple[str, int]:
    """Classify an NMT frame: ("malformed" | "other_node" | "command", command specifier)."""
    if len(data) != 2:
        return "malformed", 0
    if data[1] not in (0, node_id):
        return "other_node", data[0]
    return "command", data[0]
