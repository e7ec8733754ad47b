"""Which served unit a Modbus TCP request addresses.

A request's unit id is an axis' node id. Unit ids 0 and 255 are the conventions of Modbus TCP gateways and
SCADA drivers for "the device at this IP address" (255 recommended by the Modbus TCP implementation guide for a
directly connected device, 0 the default of many clients): when ``serve`` serves a single axis, both address
it, reads and writes alike, and every request is answered (Modbus TCP has no broadcast: unit 0 is not treated
as a serial-line broadcast). With several axes they name no axis (exception 0B, like any unknown unit id).
"""

from __future__ import annotations

from collections.abc import Sequence

THIS_DEVICE_UNIT_IDS = (0, 255)


def resolve_unit(unit: int, served: Sequence[int]) -> int:
    """The served unit id that ``unit`` addresses: itself, or the single served unit for 0 / 255."""
    if unit in THIS_DEVICE_UNIT_IDS and unit not in served and len(served) == 1:
        return served[0]
    return unit
