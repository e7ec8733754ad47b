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


def connect(spec: str = DEFAULT_BUS, *, bitrate: int = 0) -> canopen.Network:
    """A connected ``canopen.Network`` on the bus ``spec`` names (``INTERFACE:CHANNEL[,key=value...]``).

    ``bitrate`` (bit/s, 0 = off): the master's frames go out with the timing of a CAN bus at that rate
    (:class:`virtualaxis.runtime.bitrate.BitRateBus`: frame times, arbitration, transmit queue), so that a
    master that would overload a real bus sees the delays (``net.bus.stats()``) and, when its transmit queue is
    full, ``can.CanOperationError`` from ``send``."""
    bus = open_bus(spec)
    if bitrate:
        from virtualaxis.runtime.bitrate import BitRateBus

        bus = BitRateBus(bus, bitrate)
    net = canopen.Network(bus)
    net.connect()
    return net
