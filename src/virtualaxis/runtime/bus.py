"""Opening a python-can bus from an ``INTERFACE:CHANNEL[,key=value...]`` string.

- ``socketcan:vcan0`` (the default): kernel SocketCAN; a missing interface gives an error that says how
  to create a virtual one and how to use ``udp_multicast`` instead.
- ``virtual:NAME``: python-can's in-process bus (tests, ``virtualaxis demo``).
- ``udp_multicast:GROUP``: python-can's host-local bus across processes; always opened with
  ``hop_limit=0`` (frames never leave the host) unless the string says otherwise
  (``udp_multicast:239.74.163.2,hop_limit=1,port=43113``). Needs the ``msgpack`` package. Opened as
  :class:`OwnFrameFilteringUdpBus`: multicast loops every frame back to its sender, which a CAN controller
  never does (a ``canopen`` master would take its own RPDOs for periodic PDOs from the drive); each frame is
  tagged with the bus's own id in the ``channel`` field and dropped when it comes back.
- any other python-can interface name is passed through (``pcan:PCAN_USBBUS1,bitrate=1000000``).
"""

from __future__ import annotations

import itertools
import os
import socket
import struct
from collections.abc import Callable
from typing import Any

import can
from can.interfaces.udp_multicast import UdpMulticastBus

from virtualaxis.runtime.frames import MalformedFrame, decode_datagram

try:
    import msgpack
except ImportError:  # (python-can's udp_multicast refuses to open without it)
    msgpack = None

DEFAULT_BUS = "socketcan:vcan0"
DEFAULT_UDP_GROUP = "239.74.163.2"

VCAN_HELP = (
    "create it with 'sudo ip link add dev {ch} type vcan; sudo ip link set up {ch}' "
    "(modprobe vcan first if needed), or use a host-local bus without kernel CAN: "
    "--can udp_multicast:" + DEFAULT_UDP_GROUP
)


class BusOpenError(Exception):
    """The bus could not be opened; the message says why and what to do."""


_bus_ids = itertools.count(1)
#: receive buffer asked for on the multicast socket [bytes] (the kernel caps it at net.core.rmem_max; the
#: default ~208 KiB holds only ~200 small datagrams: ~15 ms of a 7-axis 1 ms bus with its looped-back frames)
RECEIVE_BUFFER_BYTES = 4 << 20


class OwnFrameFilteringUdpBus(UdpMulticastBus):
    """python-can's ``udp_multicast`` bus that, like a CAN controller, does not receive its own frames.

    ``send`` writes a tag unique to this bus object (process id + counter) into the frame's ``channel`` field
    (which python-can's udp_multicast carries across); received frames with that tag are dropped (counted in
    :attr:`own_frames_dropped`). Frames of other buses, also of other buses in the same process, are received.
    """

    def __init__(self, channel: str = DEFAULT_UDP_GROUP, port: int = 43113, hop_limit: int = 0, **kwargs: Any):
        try:
            super().__init__(channel=channel, port=port, hop_limit=hop_limit, **kwargs)
        except BaseException:
            # a bus that never opened has nothing to shut down: without this, python-can's __del__ logs
            # "OwnFrameFilteringUdpBus was not properly shut down" after the one error line
            self._is_shutdown = True
            raise
        self.own_tag = f"va-{os.getpid()}-{next(_bus_ids)}"
        self.own_frames_dropped = 0
        self.malformed_dropped = 0
        #: every frame this bus delivers is a checked classical CAN frame (runtime.frames)
        self.checks_frames = True
        sock = getattr(getattr(self, "_multicast", None), "_socket", None)
        if sock is not None:
            try:
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, RECEIVE_BUFFER_BYTES)
            except OSError:  # (kept at the system's default)
                pass
        self._drain_setup()

    def _drain_setup(self) -> None:
        """What :meth:`drain` needs of python-can's multicast socket (its kernel receive timestamps); without
        it :meth:`drain` is not offered (``drain`` = None) and a reader uses ``recv``."""
        mc = getattr(self, "_multicast", None)
        sock = getattr(mc, "_socket", None)
        if msgpack is None or sock is None or not getattr(mc, "timestamp_nanosecond", False):
            self.drain = None  # type: ignore[assignment]
            return
        self._sock = sock
        #: the bytes of this bus's tag as python-can packs the ``channel`` field: key, then value (see drain)
        self._own_marker = msgpack.packb("channel") + msgpack.packb(self.own_tag)
        self._max_buffer = mc.max_buffer
        self._anc_size = mc.received_ancillary_buffer_size
        self._ts_struct = struct.Struct(mc.received_timestamp_struct)

    def drain(self, limit: int, on_error: Callable[[Exception], None] | None = None) -> list[can.Message]:
        """Every frame waiting in the socket (at most ``limit``), without blocking: one non-blocking
        ``recvmsg`` per datagram and no ``select`` (python-can's ``recv`` does one of each per frame), own
        frames dropped before a Message is built. Decoded as python-can's udp_multicast does (msgpack, the
        kernel's receive timestamp); a datagram that is not a classical CAN frame
        (:func:`~virtualaxis.runtime.frames.decode_datagram`: undecodable, a CAN FD frame, a non-integer or
        out-of-range identifier, a DLC that does not match the data, ...) is counted in :attr:`malformed_dropped`
        and reported to ``on_error`` as :class:`~virtualaxis.runtime.frames.MalformedFrame` (as a receive
        thread's listener would be told), the rest still read.

        An own frame is recognised in the raw datagram, before decoding, by the packed ``"channel"`` key
        followed by this bus's packed tag (a msgpack decode costs more than the whole rest of a frame's
        reception). Those 18+ bytes cannot come from a classic frame's data (at most 8 bytes, between fixed
        keys); only a CAN FD payload could hold them, and CAN FD frames are malformed here anyway."""
        out: list[can.Message] = []
        sock, tag, marker = self._sock, self.own_tag, self._own_marker
        flags = socket.MSG_DONTWAIT
        for _ in range(limit):
            try:
                data, anc, _flags, _addr = sock.recvmsg(self._max_buffer, self._anc_size, flags)
            except (BlockingIOError, InterruptedError):
                break
            if marker in data:
                self.own_frames_dropped += 1
                continue
            try:
                stamp = None
                if anc:
                    sec, nsec = self._ts_struct.unpack(anc[0][2])
                    stamp = sec + nsec * 1e-9
                msg, channel = decode_datagram(data, stamp)
            except MalformedFrame as exc:  # a foreign datagram: counted, reported, not fatal
                self.malformed_dropped += 1
                if on_error is not None:
                    on_error(exc)
                continue
            if channel == tag:  # (a packing that differs from python-can's: still dropped)
                self.own_frames_dropped += 1
                continue
            out.append(msg)
        return out

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        msg.channel = self.own_tag
        super().send(msg, timeout)

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        """python-can's reception (socket, kernel timestamp), decoded and checked as :meth:`drain` does: a
        malformed datagram raises :class:`~virtualaxis.runtime.frames.MalformedFrame` (counted in
        :attr:`malformed_dropped`; a ``can.Notifier`` hands it to its listeners' ``on_error``)."""
        result = self._multicast.recv(timeout)
        if not result:
            return None, False
        data, _addr, stamp = result
        try:
            msg, channel = decode_datagram(data, stamp)
        except MalformedFrame:
            self.malformed_dropped += 1
            raise
        if channel == self.own_tag:
            self.own_frames_dropped += 1
            return None, False
        return msg, False


#: options whose value python-can needs as an integer (name -> accepted range); any interface
INT_OPTIONS: dict[str, tuple[int, int]] = {
    "port": (1, 65535), "hop_limit": (0, 255), "bitrate": (1, 10_000_000), "data_bitrate": (1, 100_000_000),
    "rx_queue_size": (0, 10_000_000),
}
#: boolean options (true / false / 1 / 0)
BOOL_OPTIONS = frozenset({"fd", "preserve_timestamps"})
#: the options each of the host-local buses takes; python-can's virtual and udp_multicast buses would silently
#: ignore any other (other interfaces get theirs passed through: python-can checks them)
BUS_OPTIONS: dict[str, tuple[str, ...]] = {
    "virtual": ("rx_queue_size", "preserve_timestamps"),
    "udp_multicast": ("port", "hop_limit", "fd"),
}


def parse_bus_spec(spec: str) -> tuple[str, str, dict]:
    """``"iface:channel,k=v"`` -> (iface, channel, options); values are int where they look like ints. The
    options of :data:`INT_OPTIONS` and :data:`BOOL_OPTIONS` must have such a value, and the virtual and
    udp_multicast buses take only theirs (:data:`BUS_OPTIONS`): else :class:`BusOpenError` naming the option."""
    if not spec or ":" not in spec:
        raise BusOpenError(
            f"bus {spec!r}: expected INTERFACE:CHANNEL, e.g. socketcan:vcan0, virtual:demo, "
            f"udp_multicast:{DEFAULT_UDP_GROUP}"
        )
    interface, rest = spec.split(":", 1)
    interface = interface.strip()
    parts = rest.split(",")
    channel = parts[0]
    options: dict = {}
    for part in parts[1:]:
        if "=" not in part:
            raise BusOpenError(f"bus {spec!r}: option {part!r} is not key=value")
        key, value = part.split("=", 1)
        key, value = key.strip(), value.strip()
        if key in options:
            raise BusOpenError(f"bus {spec!r}: option {key!r} given twice")
        accepted = BUS_OPTIONS.get(interface)
        if accepted is not None and key not in accepted:
            raise BusOpenError(f"bus {spec!r}: option {key!r} is not one the {interface} bus takes (accepted: "
                               f"{', '.join(accepted)})")
        if key in BOOL_OPTIONS:
            if value.lower() not in ("true", "false", "1", "0"):
                raise BusOpenError(f"bus {spec!r}: option {key}={value!r}: expected true, false, 1 or 0")
            options[key] = value.lower() in ("true", "1")
            continue
        try:
            options[key] = int(value, 0)
        except ValueError:
            if key in INT_OPTIONS:
                lo, hi = INT_OPTIONS[key]
                raise BusOpenError(f"bus {spec!r}: option {key}={value!r}: expected an integer {lo}..{hi}") from None
            options[key] = value
            continue
        if key in INT_OPTIONS and not INT_OPTIONS[key][0] <= options[key] <= INT_OPTIONS[key][1]:
            lo, hi = INT_OPTIONS[key]
            raise BusOpenError(f"bus {spec!r}: option {key}={value}: expected an integer {lo}..{hi}")
    return interface, channel.strip(), options


def open_bus(spec: str = DEFAULT_BUS, *, receive_own_messages: bool = False) -> can.BusABC:
    """Open the bus a spec names (see module doc)."""
    interface, channel, options = parse_bus_spec(spec)
    if interface == "udp_multicast":
        options.setdefault("hop_limit", 0)
        channel = channel or DEFAULT_UDP_GROUP
    if interface == "virtual" and not channel:
        channel = "virtualaxis"
    if interface == "udp_multicast":
        import ipaddress

        try:
            group = ipaddress.ip_address(channel)
        except ValueError:
            raise BusOpenError(f"bus {spec!r}: {channel!r} is not an IP address; udp_multicast needs a multicast "
                               f"group, e.g. {DEFAULT_UDP_GROUP}") from None
        if not group.is_multicast:
            raise BusOpenError(f"bus {spec!r}: {channel} is not a multicast address (224.0.0.0/4 or ff00::/8), "
                               f"e.g. {DEFAULT_UDP_GROUP}")
    try:
        if interface == "udp_multicast" and not receive_own_messages:
            return OwnFrameFilteringUdpBus(channel=channel, **options)
        return can.Bus(interface=interface, channel=channel, receive_own_messages=receive_own_messages, **options)
    except can.CanInterfaceNotImplementedError as exc:
        if interface == "socketcan":
            raise BusOpenError(
                f"bus {spec!r}: SocketCAN is not available here ({exc}); " + VCAN_HELP.format(ch=channel or "vcan0")
            ) from None
        raise BusOpenError(f"bus {spec!r}: interface not available ({exc})") from None
    except (OSError, can.CanError, ValueError, TypeError) as exc:
        if interface == "socketcan":
            raise BusOpenError(
                f"bus {spec!r}: cannot open {channel!r} ({exc}); " + VCAN_HELP.format(ch=channel or "vcan0")
            ) from None
        raise BusOpenError(f"bus {spec!r}: cannot open ({exc})") from None
