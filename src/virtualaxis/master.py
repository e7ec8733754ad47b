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

import queue
import struct
import time

import canopen
import canopen.sdo

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


#: SDO abort code the master sends when it ends a transfer that does not end (CiA 301: SDO protocol timed out)
ABORT_SDO_TIMED_OUT = 0x05040000
#: an SDO transfer (initiate to last frame) may last this many response timeouts at most (at least 1 s)
TRANSFER_TIMEOUTS = 10
#: ... and this many server frames at most (70 kB of segments: far more than any object of a drive's EDS)
MAX_TRANSFER_FRAMES = 10_000


class SdoTransferOverrun(Exception):  # noqa: N818 - the name says what happened
    """An SDO transfer that did not end: more frames or more time than any object needs (a server sending
    segments for ever, or answering each segment request without finishing). Not an ``SdoCommunicationError``:
    the node's SDO server is broken, which is no answer about the object asked for."""


class BoundedSdoClient(canopen.sdo.SdoClient):
    """``canopen``'s SDO client with the guards a master talking to an unknown node needs:

    - every server frame must be 8 bytes (CiA 301 SDO frames always are); a shorter one is an
      ``SdoCommunicationError`` naming it (``canopen`` itself would raise ``struct.error``);
    - a transfer ends within ``transfer_timeout_s`` (default :data:`TRANSFER_TIMEOUTS` response timeouts, at
      least 1 s) and :data:`MAX_TRANSFER_FRAMES` frames; else it is aborted (0x05040000) and
      :class:`SdoTransferOverrun` raised, then and for every later request of this client (:attr:`overrun`);
    - :attr:`unanswered` counts the exchanges that ended without a valid answer (timeouts, malformed frames),
      :attr:`unanswered_in_row` those since the last valid answer, :attr:`stalled` those in the middle of a
      transfer the node had begun (segments stopped coming).
    """

    def __init__(self, rx_cobid: int, tx_cobid: int, od, *, transfer_timeout_s: float | None = None):
        super().__init__(rx_cobid, tx_cobid, od)
        self.transfer_timeout_s = transfer_timeout_s
        self.overrun: str | None = None
        self.unanswered = 0
        self.unanswered_in_row = 0
        self.stalled = 0
        self.last_failure = ""
        self._t0 = time.monotonic()
        self._frames = 0
        self._received = 0
        self._what = ""

    def _limit_s(self) -> float:
        if self.transfer_timeout_s is not None:
            return self.transfer_timeout_s
        return max(1.0, TRANSFER_TIMEOUTS * float(self.RESPONSE_TIMEOUT))

    def send_request(self, request) -> None:
        if self.overrun:
            raise SdoTransferOverrun(self.overrun)
        b = bytes(request)
        ccs = b[0] >> 5 if b else 0
        if ccs in (1, 2) or (ccs == 5 and b[0] & 0x03 == 0) or (ccs == 6 and b[0] & 0x01 == 0) or ccs == 4:
            self._t0 = time.monotonic()  # an initiate (or an abort) starts a new transfer
            self._frames = 0
            self._received = 0
            self._what = f"0x{b[2] << 8 | b[1]:04X}:{b[3]}" if len(b) >= 4 and ccs != 4 else self._what
        super().send_request(request)

    def read_response(self) -> bytes:
        if self.overrun:
            raise SdoTransferOverrun(self.overrun)
        self._frames += 1
        elapsed = time.monotonic() - self._t0
        if self._frames > MAX_TRANSFER_FRAMES or elapsed > self._limit_s():
            self.overrun = (f"the SDO transfer of {self._what or 'an object'} did not end ({self._frames - 1} frames "
                            f"in {elapsed:.1f} s; at most {MAX_TRANSFER_FRAMES} frames and {self._limit_s():g} s): "
                            "the node's SDO server does not finish its transfers")
            try:
                super().send_request(_abort_frame(ABORT_SDO_TIMED_OUT))
            except Exception:  # noqa: BLE001 - the abort is a courtesy; the overrun is what is reported
                pass
            raise SdoTransferOverrun(self.overrun)
        try:
            response = self.responses.get(block=True, timeout=self.RESPONSE_TIMEOUT)
        except queue.Empty:
            self._fail("No SDO response received")
        if len(response) != 8:
            self._fail(f"malformed SDO response: {len(response)} byte(s) [{response.hex(' ')}]; an SDO frame has 8")
        if response[0] == 0x80:  # abort transfer
            raise canopen.SdoAbortedError(struct.unpack_from("<L", response, 4)[0])
        self._received += 1
        self.unanswered_in_row = 0
        return response

    def _fail(self, text: str):
        self.unanswered += 1
        self.unanswered_in_row += 1
        if self._received:  # the node began this transfer and stopped answering in its middle
            self.stalled += 1
            text = f"{text} after {self._received} frame(s) of the transfer"
        self.last_failure = f"{text} ({self._what})" if self._what else text
        raise canopen.SdoCommunicationError(text)


def _abort_frame(code: int) -> bytes:
    return bytes((0x80, 0, 0, 0)) + struct.pack("<L", code)


def install_bounded_sdo(node, *, transfer_timeout_s: float | None = None) -> BoundedSdoClient:
    """Replace ``node``'s default SDO client (before ``network.add_node(node)``) by a :class:`BoundedSdoClient`
    on the same COB-IDs; returns it."""
    old = node.sdo
    client = BoundedSdoClient(old.rx_cobid, old.tx_cobid, node.object_dictionary,
                              transfer_timeout_s=transfer_timeout_s)
    client.RESPONSE_TIMEOUT = old.RESPONSE_TIMEOUT
    node.sdo_channels[:] = [client if c is old else c for c in node.sdo_channels]
    node.sdo = client
    return client
