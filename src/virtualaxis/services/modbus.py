"""Modbus TCP server of the served axes: pymodbus in a process of its own, reads from a published image.

Why: pymodbus costs ~100-150 us of Python per request (framing, transaction handling, asyncio), and even the
map's own evaluation (~40-100 us per request) is taken from the interpreter lock the drive's runtime thread
needs each millisecond; ten clients polling at 100 Hz moved the SYNC -> TPDO p99 by milliseconds. So:

- ``serve`` publishes every unit's complete **register image** (all registers, scaled and saturated as the
  map defines) into shared memory every ``image_period_s`` (default 10 ms; one image costs ~45 us), see
  :mod:`virtualaxis.services.register_image`;
- the **server process** (:func:`_server_main`, a child interpreter joined by socket pairs; it imports neither
  the drive nor numba) runs ``pymodbus.server.ModbusTcpServer`` with a server context
  (:class:`ForwardingContext`) that answers valid **reads from the image** without talking to ``serve``. A
  read therefore shows the drive's state of at most one publication period (plus one image build) ago,
  like the cyclically updated map of a real drive;
- everything else (writes, and the refused accesses whose reason goes to the last-error registers) is
  forwarded over a pipe to a **bridge thread** in ``serve`` (:class:`ModbusService`), which validates and
  applies it with the register map of :mod:`virtualaxis.services.modbus_map` on the live drive, then
  republishes that unit's image before it answers: a read after a write (FC23's read too) sees the write.

pymodbus specifics handled here: request classes for FC03/04/23 that decode any count (pymodbus raises
while decoding a count > 125, which it answers with exception 01; the map answers 03), one class per other
function code that answers exception 01, and a custom server context (pymodbus' "old simulator" path: the
server calls only ``async_getValues`` / ``async_setValues``, whose return value may be an exception code).
"""

from __future__ import annotations

import os
import socket
import struct
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Sequence
from multiprocessing.connection import Connection
from pathlib import Path

from virtualaxis.services import listen
from virtualaxis.services.register_image import DEFAULT_PERIOD_S
from virtualaxis.services.threads import CHILD_PROLOGUE, short_gil_slices

SUPPORTED_FUNCTIONS = (3, 4, 6, 16, 23)
DEFAULT_ADDRESS = ("127.0.0.1", 5020)
GATEWAY_NO_RESPONSE = 0x0B

# pipe protocol (server process -> serve): ">IBBBHH" request id, op (0 read, 1 write, 2 count error,
# 3 unsupported function, 4 request of a wrong length), unit, function code, address, count, then the write
# values (">H" each).
# Reply: ">I" request id, then b"\x00" + words (">H" each) or b"\x01" + exception code. Several requests may be
# in flight (one per client connection); serve answers them in arrival order.
_REQ = struct.Struct(">IBBBHH")


def parse_host_port(text: str | None) -> tuple[str, int]:
    """``HOST:PORT`` (or ``[v6]:PORT``, ``HOST``, ``:PORT``) for --modbus; default 127.0.0.1:5020."""
    return listen.parse_host_port(text, option="--modbus", default=DEFAULT_ADDRESS)


def check_listen(host: str, port: int) -> None:
    """Raise ValueError naming ``--modbus`` and the cause if a server could not listen on ``host:port``:
    pymodbus' own message hides it ("please check address")."""
    listen.check_listen(host, port, option="--modbus")


# ============================================================================================ serve side
class RegisterAccess:
    """The register map of the axes (unit id -> ``AxisLink``) answering forwarded accesses."""

    def __init__(self, links: dict, *, writable: bool):
        self.links = links
        self.writable = writable

    def handle(
        self, op: int, unit: int, fc: int, address: int, count: int, values: Sequence[int]
    ) -> bytes:
        """One access. Each read sees one drive instant (the drive's lock held while it reads its registers)."""
        from virtualaxis.services.modbus_map import (
            REASON_BAD_COUNT,
            REASON_BAD_LENGTH,
            REASON_UNSUPPORTED_FUNCTION,
            REASON_WRITES_DISABLED,
            RegisterError,
            View,
            check_mapped,
            read_block,
            write_block,
        )

        link = self.links.get(unit)
        if link is None:
            return bytes((1, GATEWAY_NO_RESPONSE))
        link.requests += 1
        try:
            if op == 3 or fc not in SUPPORTED_FUNCTIONS:
                raise RegisterError(REASON_UNSUPPORTED_FUNCTION, f"function {fc} not supported", address=address)
            if op == 2:
                raise RegisterError(REASON_BAD_COUNT, f"count {count} out of range", address=address)
            if op == 4:
                raise RegisterError(REASON_BAD_LENGTH, f"function {fc}: request of a wrong length", address=address)
            if op == 0:
                if not 1 <= count <= 125:
                    raise RegisterError(REASON_BAD_COUNT, f"count {count} out of 1..125", address=address)
                with link.drive.lock:  # one read, one drive instant (state and objects)
                    words = read_block(link, address, count, View(link))
                return b"\x00" + struct.pack(f">{len(words)}H", *words)
            if not self.writable:
                check_mapped(address, len(values))  # (02 for an address outside the map, as with writes on)
                raise RegisterError(REASON_WRITES_DISABLED, "writes are disabled", address=address)
            write_block(link, address, list(values))
            return b"\x00"
        except RegisterError as exc:
            link.record_error(exc)
            return bytes((1, exc.exception_code))


class ModbusService:
    """The Modbus TCP server of ``links`` (``AxisLink``, unit id = node id): :meth:`start` / :meth:`stop`."""

    def __init__(
        self,
        links: list,
        *,
        host: str = "127.0.0.1",
        port: int = 5020,
        writable: bool = False,
        image_period_s: float = DEFAULT_PERIOD_S,
        gate=None,
    ):
        ids = [link.unit_id for link in links]
        if len(set(ids)) != len(ids):
            raise ValueError(f"Modbus unit ids must be unique (got {ids})")
        self.links = {link.unit_id: link for link in links}
        self.host = host
        self.port = port
        self.writable = writable
        self.access = RegisterAccess(self.links, writable=writable)
        if image_period_s <= 0:
            raise ValueError(f"Modbus register image period must be > 0 s (got {image_period_s})")
        self.image_period_s = image_period_s
        self.gate = gate  # CycleGate or None: image builds in the gap after a SYNC's PDOs
        self.image = None  # ImagePublisher while running
        self._image_reads: dict[int, int] = {}  # reads answered from the image, as of stop()
        self._image_build_us: float | None = None  # mean image build time, as of stop()
        self.bound_port: int | None = None
        self._proc = None
        self._conn = None
        self._ctl = None
        self._bridge: threading.Thread | None = None

    def start(self, timeout_s: float = 30.0) -> ModbusService:
        """Start the server process and the bridge; returns once the socket is bound (OSError if it cannot be)."""
        from virtualaxis.services.register_image import ImagePublisher

        short_gil_slices()  # the bridge thread must not hold the drive's runtime thread for a 5 ms slice
        self.image = ImagePublisher(self.links, self.image_period_s, gate=self.gate).start()
        units = ",".join(str(u) for u in self.links)
        # a plain child interpreter (not multiprocessing's spawn, which would re-run the caller's __main__),
        # joined by two socket pairs: access RPC and a stop signal (EOF when serve dies)
        rpc_ours, rpc_theirs = socket.socketpair()
        ctl_ours, ctl_theirs = socket.socketpair()
        src = str(Path(__file__).resolve().parents[2])  # the virtualaxis package this process runs
        env = dict(os.environ, PYTHONPATH=os.pathsep.join([src, *filter(None, [os.environ.get("PYTHONPATH")])]))
        code = (
            f"import sys; {CHILD_PROLOGUE}from virtualaxis.services.modbus import _server_child; "
            "_server_child(int(sys.argv[1]), int(sys.argv[2]), sys.argv[3], int(sys.argv[4]), sys.argv[5], sys.argv[6])"
        )
        self._proc = subprocess.Popen(
            [sys.executable, "-c", code, str(rpc_theirs.fileno()), str(ctl_theirs.fileno()), self.host, str(self.port),
             self.image.name, units],
            pass_fds=(rpc_theirs.fileno(), ctl_theirs.fileno()),
            env=env,
        )
        rpc_theirs.close()
        ctl_theirs.close()
        ours = Connection(rpc_ours.detach())
        self._ctl = Connection(ctl_ours.detach())
        self._conn = ours
        if not ours.poll(timeout_s):
            self.stop()
            raise OSError(f"Modbus server on {self.host}:{self.port}: did not start in {timeout_s:g} s")
        try:
            kind, value = ours.recv()
        except EOFError:
            self.stop()
            raise OSError(f"Modbus server on {self.host}:{self.port}: the server process ended") from None
        if kind != "ready":
            self.stop()
            raise OSError(f"Modbus server on {self.host}:{self.port}: {value}")
        self.bound_port = int(value)
        self._bridge = threading.Thread(target=self._serve_bridge, name="virtualaxis-modbus-bridge", daemon=True)
        self._bridge.start()
        return self

    def _serve_bridge(self) -> None:
        """Answer forwarded accesses; the ones waiting together are answered in one go (each read one drive
        instant), so a burst of clients costs the drive's process one wake-up, not one each."""
        conn, handle = self._conn, self.access.handle
        unpack = _REQ.unpack_from
        size = _REQ.size
        while True:
            try:
                batch = [conn.recv_bytes()]
                while len(batch) < 64 and conn.poll():
                    batch.append(conn.recv_bytes())
            except (EOFError, OSError):
                return
            replies = []
            touched: set[int] = set()
            for msg in batch:
                rid, op, unit, fc, address, count = unpack(msg)
                values = struct.unpack_from(f">{(len(msg) - size) // 2}H", msg, size) if len(msg) > size else ()
                try:
                    reply = handle(op, unit, fc, address, count, values)
                except Exception:  # noqa: BLE001 - never a dead bridge: device failure, as pymodbus does
                    reply = bytes((1, 0x04))
                replies.append(struct.pack(">I", rid) + reply)
                if unit in self.links:
                    touched.add(unit)
            for unit in touched:  # a write / a new last error is in the image before the reply leaves
                try:
                    self.image.publish(unit)
                except Exception:  # noqa: BLE001 - the periodic publication retries
                    pass
            try:
                for r in replies:
                    conn.send_bytes(r)
            except (EOFError, OSError):
                return

    def stop(self) -> None:
        if self._ctl is not None:
            try:
                self._ctl.send_bytes(b"stop")
            except (EOFError, OSError):
                pass
            self._ctl.close()
            self._ctl = None
        if self._proc is not None:
            try:
                self._proc.wait(timeout=5.0)
            except subprocess.TimeoutExpired:
                self._proc.terminate()
                self._proc.wait(timeout=5.0)
            self._proc = None
        if self._conn is not None:
            self._conn.close()
            self._conn = None
        if self._bridge is not None:
            self._bridge.join(timeout=5.0)
            self._bridge = None
        if self.image is not None:
            self._image_reads = {uid: self.image.reads(uid) for uid in self.links}  # kept for stats()
            self._image_build_us = (
                round(self.image.build_s_total / self.image.builds * 1e6, 1) if self.image.builds else None
            )
            self.image.close()
            self.image = None

    def sync(self, timeout_s: float = 5.0) -> None:
        """Wait until the published image shows the drives' state at least as new as at this call (one
        publication that started after it)."""
        if self.image is not None:
            self.image.sync(timeout_s)

    def _reads_from_image(self, uid: int) -> int:
        if self.image is not None:
            return self.image.reads(uid)
        return self._image_reads.get(uid, 0)

    def stats(self) -> dict:
        return {
            "address": f"{self.host}:{self.bound_port or self.port}",
            "writable": self.writable,
            "image_period_s": self.image_period_s,
            "image_build_us_mean": (
                round(self.image.build_s_total / self.image.builds * 1e6, 1)
                if self.image is not None and self.image.builds
                else self._image_build_us
            ),
            "units": {
                uid: {
                    "requests": link.requests + self._reads_from_image(uid),
                    "exceptions": link.exceptions,
                    "last_error": link.last_error_reason,
                }
                for uid, link in self.links.items()
            },
        }


# ============================================================================================ server process
def _server_child(rpc_fd: int, ctl_fd: int, host: str, port: int, image_name: str, units: str) -> None:
    """Entry of the server process (``python -c``): the two inherited socket fds as connections, the shared
    memory block of the register image and the published unit ids (comma-separated)."""
    _server_main(Connection(rpc_fd), Connection(ctl_fd), host, port, image_name, [int(u) for u in units.split(",")])


def _server_main(conn, ctl, host: str, port: int, image_name: str, units: list[int]) -> None:
    """Entry of the server process: pymodbus on ``host:port``; valid reads answered from the register image
    ``image_name``, every other access forwarded over ``conn``; a message on ``ctl`` (or its EOF: serve is
    gone) stops it."""
    import asyncio
    import logging

    logging.getLogger("pymodbus").setLevel(logging.CRITICAL)
    from pymodbus.server import ModbusTcpServer

    from virtualaxis.services.modbus_units import resolve_unit
    from virtualaxis.services.register_image import ImageReader

    image = ImageReader(image_name, units)

    pending: dict[int, asyncio.Future] = {}
    ids = iter(range(1, 1 << 62))
    loop_box: list = []

    async def call(op: int, unit: int, fc: int, address: int, count: int, values: Sequence[int] = ()) -> bytes:
        rid = next(ids) & 0xFFFFFFFF
        unit = resolve_unit(unit, units)  # 0 / 255: the single served axis (modbus_units)
        msg = _REQ.pack(rid, op, unit & 0xFF, fc & 0xFF, address & 0xFFFF, count & 0xFFFF)
        if values:
            msg += struct.pack(f">{len(values)}H", *values)
        fut = loop_box[0].create_future()
        pending[rid] = fut
        conn.send_bytes(msg)  # only the event loop's thread sends
        return await fut

    def read_replies() -> None:
        loop = loop_box[0]

        def resolve(rid: int, body: bytes) -> None:
            fut = pending.pop(rid, None)
            if fut is not None and not fut.done():
                fut.set_result(body)

        try:
            while True:
                msg = conn.recv_bytes()
                loop.call_soon_threadsafe(resolve, struct.unpack_from(">I", msg)[0], msg[4:])
        except (EOFError, OSError):
            return

    async def serve() -> None:
        loop_box.append(asyncio.get_running_loop())
        threading.Thread(target=read_replies, daemon=True).start()
        server = pipelining_server_class(ModbusTcpServer)(
            ForwardingContext(call, image), address=(host, port), custom_pdu=custom_pdus(call)
        )
        try:
            await server.serve_forever(background=True)
        except RuntimeError as exc:
            conn.send(("error", f"cannot listen ({exc})"))
            return
        sockets = getattr(server.transport, "sockets", None) or []
        conn.send(("ready", sockets[0].getsockname()[1] if sockets else port))
        stop = asyncio.Event()
        loop = asyncio.get_running_loop()

        def watch_parent() -> None:  # the parent's "stop" (or its death) ends the server
            try:
                ctl.recv_bytes()
            except (EOFError, OSError):
                pass
            loop.call_soon_threadsafe(stop.set)

        threading.Thread(target=watch_parent, daemon=True).start()
        await stop.wait()
        await server.shutdown()

    try:
        asyncio.run(serve())
    except Exception as exc:  # noqa: BLE001 - reported to the parent
        try:
            conn.send(("error", str(exc)))
        except (EOFError, OSError):
            pass


#: PDU length of the requests that have a fixed one (function code, address, count / value) [bytes]
FIXED_PDU_BYTES = {3: 5, 4: 5, 6: 5}
#: requests of one connection decoded and not yet answered beyond which the connection is not read (TCP flow
#: control holds the client back), and below which it is read again
PIPELINE_PAUSE, PIPELINE_RESUME = 1024, 256


def pipelining_server_class(server_class):
    """``server_class`` (pymodbus' ModbusTcpServer) whose connections answer every request a client sends
    without waiting for the answers (pipelining, which the Modbus TCP implementation guide allows), in order,
    however many arrive at once.

    pymodbus' own request handler decodes one frame per arrival of bytes, keeps one pending request per
    connection (``last_pdu``, which the next request overwrites while the first one's asynchronous datastore
    access runs) and drops a receive buffer longer than one frame (264 bytes: 23 requests of 12 bytes in one
    TCP segment would all go unanswered). Here the connection frames the byte stream itself (MBAP
    header: transaction id, protocol id, length, unit id): every complete request is queued in order and
    answered one after the other; a request pymodbus cannot decode or that has no function code of the map is
    answered in its place: exception 01 for a function code the map does not serve (0x00, 0x80..0xFF and every
    other code), 03 for a request of a served function whose PDU is too short or too long. A frame of another
    protocol (protocol id not 0) is skipped, and so is a frame whose length field is below 2 (no function code:
    nothing to answer; the frame still ends where its length says, and the requests after it are answered). A
    request longer than Modbus allows (a PDU of more than 253 bytes)
    is still framed by its length and answered (exception 03 from its count or length). If pymodbus' handler is
    not the one this was written for (3.16), its own is used."""
    import asyncio
    import logging
    from collections import deque

    try:
        from pymodbus.exceptions import NoSuchIdException
        from pymodbus.pdu import ExceptionResponse, ModbusPDU
        from pymodbus.server.requesthandler import ServerRequestHandler
    except ImportError:  # another pymodbus: its own handler
        return server_class
    if not all(hasattr(ServerRequestHandler, name) for name in ("callback_data", "handle_request", "server_send",
                                                                "handle_later")):
        return server_class

    class Refusal(ModbusPDU):
        """A request answered with an exception without decoding it: recorded in the unit's last-error
        registers (forwarded as ``op``: 3 an unsupported function, 4 a request of a wrong length) and answered
        with the code the map gives."""

        def __init__(self, function_code: int, op: int, dev_id: int, transaction_id: int):
            super().__init__(dev_id=dev_id, transaction_id=transaction_id)
            self.function_code = function_code
            self.op = op

        async def datastore_update(self, context, device_id):
            reply = await context.call(self.op, device_id, self.function_code, 0, 0)
            return ExceptionResponse(self.function_code, _exc(reply[1] if reply[0] else 0x04))

    class OrderedRequestHandler(ServerRequestHandler):
        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            self._requests: deque = deque()  # (pdu, addr) decoded, not yet answered
            self._one_at_a_time = asyncio.Lock()
            self._paused = False
            self._partial = b""  # the start of a frame whose rest has not arrived
            # the transport drops a receive buffer longer than this: one socket read of pipelined requests
            # (asyncio reads up to 256 KiB at a time) must stay whole
            self.max_buffer_size = 1 << 20

        def callback_data(self, data: bytes, addr: tuple | None = None) -> int:
            # every byte is taken: the transport empties its receive buffer whenever an answer is sent (it
            # expects one request, then the answer) and would lose the start of a request that has arrived in
            # part; the incomplete frame at the end is kept here instead (at most one: < 64 KiB, the length
            # field's range)
            used = len(data)
            if self._partial:
                data, self._partial = self._partial + data, b""
            total, n = 0, len(data)
            decode = self.framer.decoder.decode
            while n - total >= 6:
                tid, pid, length = struct.unpack_from(">HHH", data, total)
                end = total + 6 + length
                if end > n:
                    break  # the rest of this frame has not arrived yet
                if length < 2 or pid != 0:
                    total = end  # no function code (nothing to answer), or not a Modbus frame: skipped
                    continue
                unit = data[total + 6]
                pdu_bytes = data[total + 7 : end]
                total = end
                fc = pdu_bytes[0]
                if fc not in SUPPORTED_FUNCTIONS:
                    request = Refusal(fc, 3, unit, tid)
                else:
                    fixed = FIXED_PDU_BYTES.get(fc)
                    request = decode(pdu_bytes) if fixed is None or len(pdu_bytes) == fixed else None
                    if request is None:
                        request = Refusal(fc, 4, unit, tid)
                    else:
                        request.dev_id, request.transaction_id = unit, tid
                self._requests.append((request, addr))
                self.loop.call_soon(self.handle_later)
            self._partial = data[total:]
            if len(self._requests) > PIPELINE_PAUSE and not self._paused and self.transport is not None:
                self._paused = True
                self.transport.pause_reading()
            return used

        async def handle_request(self) -> None:
            async with self._one_at_a_time:
                if not self._requests:
                    return
                pdu, addr = self._requests.popleft()
                if self._paused and len(self._requests) < PIPELINE_RESUME and self.transport is not None:
                    self._paused = False
                    self.transport.resume_reading()
                try:
                    response = await pdu.datastore_update(self.server.context, pdu.dev_id)
                except NoSuchIdException:
                    response = ExceptionResponse(pdu.function_code, _exc(0x0B))
                except Exception:  # noqa: BLE001 - as pymodbus: the device could not serve it
                    logging.getLogger(__name__).exception("Modbus request failed")
                    response = ExceptionResponse(pdu.function_code, _exc(0x04))
                response.transaction_id = pdu.transaction_id
                response.dev_id = pdu.dev_id
                self.server_send(response, addr)

    class PipeliningServer(server_class):
        def callback_new_connection(self):
            return OrderedRequestHandler(self, self.trace_packet, self.trace_pdu, self.trace_connect)

    return PipeliningServer


def _exc(code: int):
    from pymodbus.constants import ExcCodes

    return ExcCodes(code)


def _decode_reply(reply: bytes):
    if reply[0] == 0:
        n = (len(reply) - 1) // 2
        return list(struct.unpack_from(f">{n}H", reply, 1))
    return _exc(reply[1])


def _make_context_class():
    from pymodbus.datastore import ModbusServerContext

    class _ForwardingContext(ModbusServerContext):
        """pymodbus server context: valid reads from the register ``image`` (an ``ImageReader``), every other access
        forwarded to ``call`` (no data blocks of its own)."""

        def __init__(self, call: Callable, image=None):  # no base init: it would require data blocks
            self.call = call
            self.image = image
            self.old_simulator = True  # the server then uses this object as is
            self.simdevices = []
            self._devices = {}

        def device_ids(self) -> list[int]:
            return []

        async def async_getValues(self, device_id: int, func_code: int, address: int, count: int = 1):
            image = self.image
            if image is not None and image.covers(address, count):
                words = image.read(device_id, address, count)
                if words is not None:
                    return words
            return _decode_reply(await self.call(0, device_id, func_code, address, count))

        async def async_setValues(self, device_id: int, func_code: int, address: int, values: Sequence[int]):
            values = [int(v) & 0xFFFF for v in values]
            reply = await self.call(1, device_id, func_code, address, len(values), values)
            return None if reply[0] == 0 else _exc(reply[1])

    return _ForwardingContext


def ForwardingContext(call: Callable, image=None):  # noqa: N802 - a class built on first use (lazy pymodbus)
    return _make_context_class()(call, image)


def custom_pdus(call: Callable) -> list:
    """Request classes: FC03/04/23 with any count (exception 03 when answering), FC06 answered with the echo,
    01 for every other code."""
    from pymodbus.pdu import ExceptionResponse, ModbusPDU
    from pymodbus.pdu.register_message import (
        ReadHoldingRegistersRequest,
        ReadInputRegistersRequest,
        ReadWriteMultipleRegistersRequest,
        WriteMultipleRegistersRequest,
        WriteSingleRegisterRequest,
        WriteSingleRegisterResponse,
    )

    def byte_count_fits(count: int, byte_count: int, payload_bytes: int) -> bool:
        """FC16 / FC23: the byte count is 2 x the register count and the number of data bytes sent (else the
        request's length does not fit its counts: reason 10)."""
        return byte_count == 2 * count and payload_bytes == byte_count

    async def refused(pdu, device_id: int, op: int, address: int):
        reply = await call(op, device_id, pdu.function_code, address, 0)
        return ExceptionResponse(pdu.function_code, _exc(reply[1]))

    class ReadHoldingAnyCount(ReadHoldingRegistersRequest):
        def decode(self, data: bytes) -> None:
            self.address, self.count = struct.unpack(">HH", data[:4])

        async def datastore_update(self, context, device_id):
            if not 1 <= self.count <= 125:
                return await refused(self, device_id, 2, self.address)
            return await super().datastore_update(context, device_id)

    class ReadInputAnyCount(ReadHoldingAnyCount):
        function_code = ReadInputRegistersRequest.function_code

    class ReadWriteAnyCount(ReadWriteMultipleRegistersRequest):
        def decode(self, data: bytes) -> None:
            (
                self.read_address,
                self.read_count,
                self.write_address,
                self.write_count,
                self.write_byte_count,
            ) = struct.unpack(">HHHHB", data[:9])
            self._payload_byte_count = len(data) - 9
            self.write_registers = [
                struct.unpack(">H", data[i : i + 2])[0]
                for i in range(9, min(len(data), self.write_byte_count + 9) - 1, 2)
            ]

        async def datastore_update(self, context, device_id):
            """Checked completely before the write is applied: the counts (the refused one's address in the
            last-error registers), then the read range (an unknown register or a hole: exception 02 and
            nothing written), then write, then read (the read sees the write)."""
            if not 1 <= self.read_count <= 125:
                return await refused(self, device_id, 2, self.read_address)
            if not 1 <= self.write_count <= 121:
                return await refused(self, device_id, 2, self.write_address)
            if not byte_count_fits(self.write_count, self.write_byte_count, self._payload_byte_count):
                return await refused(self, device_id, 4, self.write_address)
            checked = await context.async_getValues(device_id, self.function_code, self.read_address,
                                                    self.read_count)
            if not isinstance(checked, list):
                return ExceptionResponse(self.function_code, checked)
            return await super().datastore_update(context, device_id)

    class WriteMultipleCounted(WriteMultipleRegistersRequest):
        """FC16: a count out of 1..123 (reason 8) or a byte count that does not fit the count or the data sent
        (reason 10: the request's length does not fit its function) is recorded in the last-error registers
        too (exception 03)."""

        async def datastore_update(self, context, device_id):
            if not 1 <= self.count <= 123:
                return await refused(self, device_id, 2, self.address)
            if self.byte_count is not None and not byte_count_fits(self.count, self.byte_count,
                                                                     self._payload_byte_count):
                return await refused(self, device_id, 4, self.address)
            return await super().datastore_update(context, device_id)

    class WriteSingleEcho(WriteSingleRegisterRequest):
        """FC06: the normal response echoes the request (Modbus application protocol 6.6; pymodbus answers
        the register read back, which for a command word such as STW1 or a set-point is not what was
        written)."""

        async def datastore_update(self, context, device_id):
            value = self.registers[0]
            if not 0 <= value <= 0xFFFF:
                return ExceptionResponse(self.function_code, _exc(3))
            rc = await context.async_setValues(device_id, self.function_code, self.address, self.registers)
            if rc:
                return ExceptionResponse(self.function_code, rc)
            return WriteSingleRegisterResponse(address=self.address, registers=[value])

    class Unsupported(ModbusPDU):
        function_code = 0

        def decode(self, data: bytes) -> None:
            self._raw = data

        async def datastore_update(self, context, device_id):
            return await refused(self, device_id, 3, 0)

    others = [
        type(f"UnsupportedFunction{fc:02d}", (Unsupported,), {"function_code": fc})
        for fc in range(1, 128)
        if fc not in SUPPORTED_FUNCTIONS
    ]
    return [ReadHoldingAnyCount, ReadInputAnyCount, ReadWriteAnyCount, WriteMultipleCounted, WriteSingleEcho,
            *others]


def wait_port(host: str, port: int, timeout_s: float = 5.0) -> None:
    """Wait until ``host:port`` accepts a TCP connection."""
    import socket

    end = time.monotonic() + timeout_s
    while True:
        try:
            with socket.create_connection((host, port), timeout=0.2):
                return
        except OSError:
            if time.monotonic() > end:
                raise
            time.sleep(0.02)
