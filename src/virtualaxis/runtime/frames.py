"""What a frame from the bus must be to be served: a classical CAN 2.0A/B data, remote or error frame.

A host-local bus carries whatever a sender packs: python-can's ``udp_multicast`` sends a msgpack map of the
``can.Message`` fields, and any program on the host can send a datagram to the group. Every frame the
runtime takes from the bus is therefore checked here before anything (bit-rate emulation, routing to the
axes) looks at it; a frame that no CAN controller could have received is *malformed*: counted and dropped.

- :func:`frame_problem`: why a ``can.Message`` is not a classical CAN frame (None when it is one): an
  identifier that is not an integer in range (11 bits, or 29 bits with the extended-id flag), flags that are
  not booleans, a DLC that is not an integer 0..8, data that are not bytes or do not match the DLC, a remote
  frame that is also an error frame, a CAN FD frame (the served bus is classical CAN), FD flags without FD,
  a timestamp that is not a finite time.
- :func:`decode_datagram`: a ``udp_multicast`` datagram to a checked ``can.Message``, or
  :class:`MalformedFrame` naming what is wrong (not msgpack, not a map, an unknown field, a field of the
  wrong type, or any :func:`frame_problem`). Nothing in a datagram can make the decoder allocate more than
  the datagram's own size.
"""

from __future__ import annotations

import math
from typing import Any

import can

try:
    import msgpack
except ImportError:  # (python-can's udp_multicast refuses to open without it)
    msgpack = None

#: the fields python-can's udp_multicast packs (``can.interfaces.udp_multicast.utils.pack_message``)
DATAGRAM_FIELDS = frozenset({
    "timestamp", "arbitration_id", "is_extended_id", "is_remote_frame", "is_error_frame", "channel", "dlc",
    "data", "is_fd", "bitrate_switch", "error_state_indicator",
})
_FLAGS = ("is_extended_id", "is_remote_frame", "is_error_frame", "is_fd", "bitrate_switch", "error_state_indicator")
#: largest classical CAN data length code
MAX_DLC = 8


class MalformedFrame(can.CanOperationError):
    """A frame (or datagram) from the bus that is not a classical CAN frame; the message says why."""


def frame_problem(msg: can.Message) -> str | None:
    """Why ``msg`` cannot be a classical CAN frame received from the bus, None when it is one."""
    ident, dlc, stamp = msg.arbitration_id, msg.dlc, msg.timestamp
    if (msg.is_extended_id is False and msg.is_remote_frame is False and msg.is_error_frame is False
            and msg.is_fd is False and msg.bitrate_switch is False and msg.error_state_indicator is False
            and type(ident) is int and 0 <= ident < 0x800 and type(dlc) is int and 0 <= dlc <= MAX_DLC
            and type(msg.data) is bytearray and len(msg.data) == dlc and type(stamp) is float
            and 0.0 <= stamp < math.inf):
        return None  # (the common case, a standard data frame, in one test)
    return _problem(msg)


def _problem(msg: can.Message) -> str | None:
    ident = msg.arbitration_id
    if type(ident) is not int:
        return f"identifier {ident!r} is not an integer"
    for flag in _FLAGS:
        if type(getattr(msg, flag)) is not bool:
            return f"{flag} {getattr(msg, flag)!r} is not true or false"
    if msg.is_extended_id:
        if not 0 <= ident < 1 << 29:
            return f"29-bit identifier 0x{ident:X} out of range 0..0x1FFFFFFF" if ident >= 0 else \
                f"identifier {ident} is negative"
    elif not 0 <= ident < 1 << 11:
        return f"11-bit identifier 0x{ident:X} out of range 0..0x7FF" if ident >= 0 else \
            f"identifier {ident} is negative"
    if msg.is_fd:
        return "CAN FD frame on a classical CAN bus"
    if msg.bitrate_switch or msg.error_state_indicator:
        return "bit rate switch / error state indicator set on a classical frame"
    dlc = msg.dlc
    if type(dlc) is not int or not 0 <= dlc <= MAX_DLC:
        return f"DLC {dlc!r} is not an integer 0..{MAX_DLC}"
    data = msg.data
    if not isinstance(data, (bytes, bytearray)):
        return f"data of type {type(data).__name__}, not bytes"
    if msg.is_remote_frame:
        if msg.is_error_frame:
            return "remote frame and error frame at once"
        if data:
            return "remote frame with data"
    elif len(data) != dlc and not msg.is_error_frame:
        return f"DLC {dlc} but {len(data)} data bytes"
    stamp = msg.timestamp
    if type(stamp) not in (int, float) or not math.isfinite(stamp) or stamp < 0:
        return f"timestamp {stamp!r} is not a time"
    return None


def decode_datagram(datagram: bytes, timestamp_s: float | None = None) -> tuple[can.Message, Any]:
    """One ``udp_multicast`` datagram -> (checked frame, its ``channel`` field); :class:`MalformedFrame` when
    it is not a classical CAN frame packed as python-can packs one. ``timestamp_s``: the kernel's receive time
    (replaces the sender's field)."""
    try:
        fields = msgpack.unpackb(datagram, raw=False, strict_map_key=True)
    except Exception as exc:  # noqa: BLE001 - msgpack's errors have no common base class
        raise MalformedFrame(f"datagram is not msgpack ({type(exc).__name__})") from None
    if not isinstance(fields, dict):
        raise MalformedFrame(f"datagram holds a {type(fields).__name__}, not a map of frame fields")
    if not fields.keys() <= DATAGRAM_FIELDS:
        unknown = next(k for k in fields if k not in DATAGRAM_FIELDS)
        raise MalformedFrame(f"unknown frame field {str(unknown)[:40]!r}")
    data = fields.get("data")
    if data is not None and not isinstance(data, (bytes, bytearray)):
        raise MalformedFrame(f"data of type {type(data).__name__}, not bytes")
    channel = fields.pop("channel", None)
    if timestamp_s is not None:
        fields["timestamp"] = timestamp_s
    msg = can.Message(**fields)
    msg.channel = channel if isinstance(channel, str) else None
    problem = frame_problem(msg)
    if problem is not None:
        raise MalformedFrame(problem)
    return msg, channel
