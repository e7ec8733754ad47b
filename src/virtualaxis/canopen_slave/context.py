"""What each service of the slave (SDO server, PDO engine, SYNC consumer, heartbeat / guarding, EMCY producer,
COB-ID checks) may use of its node: one narrow protocol per service, which
:class:`~virtualaxis.canopen_slave.CanopenSlave` implements. A service is typed against its protocol, never
against the slave, so the services import nothing of slave.py and slave.py imports the services.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any, Protocol

from virtualaxis.canopen_slave.nmt import NmtState
from virtualaxis.canopen_slave.od import Entry, ObjectStore


class NodeContext(Protocol):
    """The node as every service sees it: its id, dictionary and counters, and a way to send a frame."""

    node_id: int
    od: ObjectStore
    counters: dict[str, int]

    def send(self, cob_id: int, data: bytes | bytearray) -> None: ...


class CommErrorNode(NodeContext, Protocol):
    """A service that detects communication errors (SYNC, heartbeat, guarding, RPDO deadlines)."""

    nmt_state: NmtState

    def rebuild_dispatch(self) -> None: ...
    def raise_comm_error(self, code: int, source: int = 0, data: bytes = b"") -> None: ...
    def clear_comm_error(self, code: int, source: int = 0) -> None: ...
    def comm_error_sources(self, code: int) -> frozenset[int]: ...
    def communication_error(self, kind: str, detail: int) -> None: ...
    def error_behaviour(self) -> None: ...


class PdoNode(CommErrorNode, Protocol):
    """The PDO engine's node: the application's RPDO brackets and set-point objects, the checked store."""

    setpoint_objects: frozenset[tuple[int, int]]
    hook_begin_pdo: Callable[[], None]
    hook_end_pdo: Callable[[], None]

    def store_all_from_pdo(self, entries: Sequence[Entry], values: Sequence[Any]) -> None: ...
    def emcy(self, code: int, register_bits: int = 0, data: bytes = b"", communication: bool = False) -> None: ...


class SdoNode(NodeContext, Protocol):
    """The SDO server's node: the checked object access of an SDO transfer."""

    def entry_size(self, index: int, sub: int) -> int | None: ...
    def sdo_check_writable(self, index: int, sub: int) -> Entry: ...
    def sdo_check_length(self, index: int, sub: int, size: int) -> None: ...
    def sdo_upload(self, index: int, sub: int) -> bytes: ...
    def sdo_download(self, index: int, sub: int, data: bytes) -> None: ...
