"""NMT reset of a `canopen` node and the wait for its boot-up message, listening from before the command.

canopen's ``NmtMaster.wait_for_bootup`` starts listening when it is called, i.e. after the command was sent: a
node that answers a reset at once (a boot-up on the bus before the call) is then reported as silent."""

from __future__ import annotations

import threading
import weakref
from collections.abc import Callable

_BOOTED: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()  # NmtMaster -> Event set by its next boot-up


def reset_and_wait_for_bootup(node, timeout_s: float = 5.0, send: Callable[[], None] | None = None) -> None:
    """Send NMT reset node (or call ``send``) and wait up to ``timeout_s`` for the node's boot-up message."""
    nmt = node.nmt
    booted = _BOOTED.get(nmt)
    if booted is None:
        booted = _BOOTED[nmt] = threading.Event()
        nmt.add_heartbeat_callback(lambda state, ev=booted: ev.set() if state == 0 else None)
    booted.clear()
    if send is None:
        nmt.state = "RESET"
    else:
        send()
    if not booted.wait(timeout_s):
        raise AssertionError(f"node {node.id}: no boot-up message within {timeout_s:g} s of the NMT reset")
