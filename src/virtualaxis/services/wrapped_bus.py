"""A python-can bus that passes everything through to the bus it wraps; a subclass adds what it does beside a
send (the cycle gate's PDO mark, the live page's frame log)."""

from __future__ import annotations

import can


class WrappedBus(can.BusABC):
    """``inner`` with every call passed through (``send`` included; subclasses extend it)."""

    def __init__(self, inner: can.BusABC):
        self.inner = inner
        self.channel_info = getattr(inner, "channel_info", "bus")
        super().__init__(channel=None)

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        self.inner.send(msg, timeout)

    def recv(self, timeout: float | None = None) -> can.Message | None:
        return self.inner.recv(timeout)

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        return self.inner.recv(timeout), False

    def fileno(self) -> int:
        return self.inner.fileno()

    def __getattr__(self, name: str):  # stats(), write() etc. of the wrapped bus
        if name == "inner":
            raise AttributeError(name)
        return getattr(self.inner, name)

    def shutdown(self) -> None:
        self.inner.shutdown()
        super().shutdown()
