"""Helpers for a CANopen master (the `canopen` package) talking to served drives.

    import canopen
    from virtualaxis.master import DEFAULT_EDS, connect

    net = connect("udp_multicast:239.74.163.2")       # the same bus string as `virtualaxis serve --can`
    node = canopen.BaseNode402(1, DEFAULT_EDS)
    net.add_node(node)

:func:`connect` opens the bus with :func:`virtualaxis.runtime.open_bus` (``hop_limit=0`` for udp_multicast and
the master's own frames filtered out, as a CAN controller does: without that, ``canopen`` takes the master's
own RPDOs for periodic PDOs sent by the drive and ``BaseNode402`` waits for them in vain).
"""

from __future__ import annotations

import canopen

from virtualaxis.resources import project_file
from virtualaxis.runtime.bus import DEFAULT_BUS, open_bus

#: the drive's EDS (``eds/virtualaxis.eds``), as a string for ``canopen`` nodes
DEFAULT_EDS = str(project_file("eds/virtualaxis.eds"))


def connect(spec: str = DEFAULT_BUS) -> canopen.Network:
    """A connected ``canopen.Network`` on the bus ``spec`` names (``INTERFACE:CHANNEL[,key=value...]``)."""
    net = canopen.Network(open_bus(spec))
    net.connect()
    return net
