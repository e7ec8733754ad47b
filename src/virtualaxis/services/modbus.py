"""Modbus TCP server of the served axes (pymodbus), in its own thread and asyncio loop.

The register map is :mod:`virtualaxis.services.modbus_map`; this module only binds it to pymodbus:

- a server context (:class:`DriveServerContext`) whose ``async_getValues`` / ``async_setValues`` read and
  write the drive and return the Modbus exception code of a refused access;
- request classes for FC03/04/23 that decode any count (pymodbus' own raise on a count > 125 while decoding,
  which it answers with exception 01; the map answers 03) and one class per other function code that
  answers exception 01;
- :class:`ModbusService`: ``start()`` / ``stop()`` of the server thread.

The drive cycle never waits for Modbus: a request takes the drive's lock only for the short read or write
of the drive API, like any other API user.
"""

from __future__ import annotations

import asyncio
import logging
import struct
import threading
import time
from collections.abc import Sequence

from pymodbus.constants import ExcCodes
from pymodbus.datastore import ModbusServerContext
from pymodbus.pdu import ExceptionResponse, ModbusPDU
from pymodbus.pdu.register_message import (
    ReadHoldingRegistersRequest,
    ReadInputRegistersRequest,
    ReadWriteMultipleRegistersRequest,
)
from pymodbus.server import ModbusTcpServer

from virtualaxis.services.modbus_map import (
    REASON_BAD_COUNT,
    REASON_UNSUPPORTED_FUNCTION,
    REASON_WRITES_DISABLED,
    AxisLink,
    RegisterError,
    read_block,
    write_block,
)

SUPPORTED_FUNCTIONS = (3, 4, 6, 16, 23)
DEFAULT_ADDRESS = ("127.0.0.1", 5020)


def parse_host_port(text: str | None) -> tuple[str, int]:
    """``HOST:PORT`` (or ``[v6]:PORT``, ``HOST``, ``:PORT``) for --modbus; default 127.0.0.1:5020."""
    if not text:
        return DEFAULT_ADDRESS
    host, port = text, str(DEFAULT_ADDRESS[1])
    if text.startswith("["):
        host, _, rest = text[1:].partition("]")
        if rest.startswith(":"):
            port = rest[1:]
    elif text.count(":") == 1:
        host, port = text.split(":")
    if not host:
        host = DEFAULT_ADDRESS[0]
    try:
        p = int(port)
    except ValueError:
        raise ValueError(f"--modbus {text!r}: port {port!r} is not a number") from None
    if not 0 <= p <= 65535:
        raise ValueError(f"--modbus {text!r}: port must be 0..65535")
    return host, p


class DriveServerContext(ModbusServerContext):
    """The pymodbus server context of the axes: unit id -> :class:`AxisLink`.

    It takes pymodbus' path for a custom (``old_simulator``) context: the server calls only
    ``async_getValues`` / ``async_setValues``, whose return value may be an exception code.
    """

    def __init__(self, links: dict[int, AxisLink], *, writable: bool):  # noqa: D107 (no base init: no datablocks)
        self.links = links
        self.writable = writable
        self.old_simulator = True  # the server then uses this object as is
        self.simdevices = []
        self._devices = links

    def device_ids(self) -> list[int]:
        return list(self.links)

    def _link(self, unit: int) -> AxisLink | None:
        return self.links.get(unit)

    async def async_getValues(self, device_id: int, func_code: int, address: int, count: int = 1):
        link = self._link(device_id)
        if link is None:
            return ExcCodes.GATEWAY_NO_RESPONSE
        link.requests += 1
        try:
            if func_code not in (3, 4, 6, 16, 23):
                raise RegisterError(REASON_UNSUPPORTED_FUNCTION, f"function {func_code} not supported")
            if not 1 <= count <= 125:
                raise RegisterError(REASON_BAD_COUNT, f"count {count} out of 1..125", address=address)
            return read_block(link, address, count)
        except RegisterError as exc:
            link.record_error(exc)
            return ExcCodes(exc.exception_code)

    async def async_setValues(self, device_id: int, func_code: int, address: int, values: Sequence[int]):
        link = self._link(device_id)
        if link is None:
            return ExcCodes.GATEWAY_NO_RESPONSE
        link.requests += 1
        try:
            if func_code not in (6, 16, 23):
                raise RegisterError(REASON_UNSUPPORTED_FUNCTION, f"function {func_code} not supported")
            if not self.writable:
                raise RegisterError(REASON_WRITES_DISABLED, "writes are disabled", address=address)
            write_block(link, address, [int(v) for v in values])
            return None
        except RegisterError as exc:
            link.record_error(exc)
            return ExcCodes(exc.exception_code)


def _count_exception(pdu: ModbusPDU, context: DriveServerContext, device_id: int) -> ModbusPDU:
    link = context.links.get(device_id)
    if link is None:
        return ExceptionResponse(pdu.function_code, ExcCodes.GATEWAY_NO_RESPONSE)
    link.requests += 1
    link.record_error(RegisterError(REASON_BAD_COUNT, "bad count", address=pdu.address))
    return ExceptionResponse(pdu.function_code, ExcCodes.ILLEGAL_VALUE)


class ReadHoldingAnyCount(ReadHoldingRegistersRequest):
    """FC03 that decodes any count (the count is checked when answering: exception 03)."""

    def decode(self, data: bytes) -> None:
        self.address, self.count = struct.unpack(">HH", data[:4])

    async def datastore_update(self, context, device_id):
        if not 1 <= self.count <= 125:
            return _count_exception(self, context, device_id)
        return await super().datastore_update(context, device_id)


class ReadInputAnyCount(ReadHoldingAnyCount):
    """FC04 (the same map as FC03)."""

    function_code = ReadInputRegistersRequest.function_code


class ReadWriteAnyCount(ReadWriteMultipleRegistersRequest):
    """FC23 that decodes any count; the base class answers bad counts with exception 03."""

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
            struct.unpack(">H", data[i : i + 2])[0] for i in range(9, min(len(data), self.write_byte_count + 9) - 1, 2)
        ]

    async def datastore_update(self, context, device_id):
        if not (1 <= self.read_count <= 125 and 1 <= self.write_count <= 121):
            self.address = self.write_address
            return _count_exception(self, context, device_id)
        return await super().datastore_update(context, device_id)


class _Unsupported(ModbusPDU):
    """Any function code the map does not serve: exception 01 (the request body is ignored)."""

    function_code = 0

    def decode(self, data: bytes) -> None:
        self._raw = data

    async def datastore_update(self, context, device_id):
        link = context.links.get(device_id) if isinstance(context, DriveServerContext) else None
        if link is not None:
            link.requests += 1
            link.record_error(RegisterError(REASON_UNSUPPORTED_FUNCTION, "unsupported function"))
        return ExceptionResponse(self.function_code, ExcCodes.ILLEGAL_FUNCTION)


_UNSUPPORTED = [
    type(f"UnsupportedFunction{fc:02d}", (_Unsupported,), {"function_code": fc})
    for fc in range(1, 128)
    if fc not in SUPPORTED_FUNCTIONS
]
CUSTOM_PDUS: list[type[ModbusPDU]] = [ReadHoldingAnyCount, ReadInputAnyCount, ReadWriteAnyCount, *_UNSUPPORTED]


class ModbusService:
    """The Modbus TCP server of the axes ``links`` (unit id -> link) in a background thread."""

    def __init__(self, links: list[AxisLink], *, host: str = "127.0.0.1", port: int = 5020, writable: bool = False):
        ids = [link.unit_id for link in links]
        if len(set(ids)) != len(ids):
            raise ValueError(f"Modbus unit ids must be unique (got {ids})")
        self.links = {link.unit_id: link for link in links}
        self.host = host
        self.port = port
        self.writable = writable
        self.context = DriveServerContext(self.links, writable=writable)
        self._thread: threading.Thread | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._server: ModbusTcpServer | None = None
        self._ready = threading.Event()
        self._error: BaseException | None = None
        self.bound_port: int | None = None

    def start(self, timeout_s: float = 10.0) -> ModbusService:
        """Start listening; returns when the socket is bound (raises OSError if it cannot be)."""
        logging.getLogger("pymodbus").setLevel(logging.CRITICAL)  # its per-request warnings are not ours
        self._thread = threading.Thread(target=self._run, name="virtualaxis-modbus", daemon=True)
        self._thread.start()
        if not self._ready.wait(timeout_s):
            raise TimeoutError("Modbus server did not start")
        if self._error is not None:
            raise OSError(f"Modbus server on {self.host}:{self.port}: {self._error}")
        return self

    def _run(self) -> None:
        loop = asyncio.new_event_loop()
        self._loop = loop
        asyncio.set_event_loop(loop)
        try:
            loop.run_until_complete(self._serve())
        except BaseException as exc:  # noqa: BLE001 - reported to start()
            self._error = exc
            self._ready.set()
        finally:
            loop.close()

    async def _serve(self) -> None:
        self._server = ModbusTcpServer(self.context, address=(self.host, self.port), custom_pdu=CUSTOM_PDUS)
        try:
            await self._server.serve_forever(background=True)
        except RuntimeError as exc:
            raise OSError(f"cannot listen ({exc})") from None
        listener = self._server.transport  # an asyncio Server for a TCP listener
        sockets = getattr(listener, "sockets", None) or []
        self.bound_port = sockets[0].getsockname()[1] if sockets else self.port
        self._ready.set()
        await self._server.serving

    def stop(self) -> None:
        if self._loop is not None and self._server is not None and self._loop.is_running():
            fut = asyncio.run_coroutine_threadsafe(self._server.shutdown(), self._loop)
            try:
                fut.result(timeout=5.0)
            except Exception:  # noqa: BLE001 - best effort at shutdown
                pass
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            self._thread = None

    def stats(self) -> dict:
        return {
            "address": f"{self.host}:{self.bound_port or self.port}",
            "writable": self.writable,
            "units": {
                uid: {"requests": link.requests, "exceptions": link.exceptions, "last_error": link.last_error_reason}
                for uid, link in self.links.items()
            },
        }


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
