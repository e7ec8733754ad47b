"""The seam between the CiA 301 stack (:class:`~virtualaxis.canopen_slave.CanopenSlave`) and the device
application it serves (the CiA 402 drive, :class:`virtualaxis.drive.canopen_app.Cia402Application`).

:class:`CanopenApplication` declares every hook the slave calls; :class:`BaseApplication` implements each as
"nothing to do", so an application subclasses it and overrides only the hooks it needs. The slave binds the
hooks once when it is built (RPDOs are a hot path) and never probes for them.
"""

from __future__ import annotations

from typing import Any, Protocol, runtime_checkable

from virtualaxis.canopen_slave.nmt import NmtState


@runtime_checkable
class CanopenApplication(Protocol):
    """What the slave calls on its application (see docs/canopen-slave-api.md for when each is called)."""

    #: objects whose write only sets a value that the next write replaces (set-points such as CiA 402
    #: targets): a SYNC's RPDO that changes nothing else may be left out when the next SYNC's replaces it
    setpoint_objects: frozenset[tuple[int, int]]

    def validate_write(self, index: int, sub: int, value: Any) -> None:
        """Raise :class:`~virtualaxis.canopen_slave.SdoAbort` to refuse a write (SDO or RPDO)."""

    def after_write(self, index: int, sub: int, value: Any) -> None:
        """The value is stored: react to it (a write inside an RPDO comes between ``begin_pdo`` / ``end_pdo``)."""

    def before_read(self, index: int, sub: int) -> None:
        """Refresh a value before an SDO upload."""

    def begin_pdo(self) -> None:
        """An RPDO's entries are about to be stored (one ``after_write`` each)."""

    def end_pdo(self) -> None:
        """Every entry of the RPDO is stored: react to them together."""

    def on_nmt_state(self, state: NmtState) -> None:
        """The NMT state changed."""

    def on_communication_error(self, kind: str, detail: int) -> None:
        """A communication error (heartbeat lost, life guarding, RPDO timeout / length, SYNC timeout)."""

    def on_reset(self, application: bool) -> None:
        """NMT reset node (``application``) or reset communication."""

    def has_error(self) -> bool:
        """The application has an error or warning (the stack keeps 0x1001 set while it does)."""


class BaseApplication:
    """Every hook of :class:`CanopenApplication` doing nothing: the application of a bare node, and the base
    class of applications that need only some hooks."""

    setpoint_objects: frozenset[tuple[int, int]] = frozenset()

    def validate_write(self, index: int, sub: int, value: Any) -> None:
        return None

    def after_write(self, index: int, sub: int, value: Any) -> None:
        return None

    def before_read(self, index: int, sub: int) -> None:
        return None

    def begin_pdo(self) -> None:
        return None

    def end_pdo(self) -> None:
        return None

    def on_nmt_state(self, state: NmtState) -> None:
        return None

    def on_communication_error(self, kind: str, detail: int) -> None:
        return None

    def on_reset(self, application: bool) -> None:
        return None

    def has_error(self) -> bool:
        return False


#: the members every application has (:class:`CanopenApplication`)
APPLICATION_MEMBERS = ("setpoint_objects", "validate_write", "after_write", "before_read", "begin_pdo", "end_pdo",
                       "on_nmt_state", "on_communication_error", "on_reset", "has_error")


def check_application(app: Any) -> CanopenApplication:
    """``app`` if it has every member of :class:`CanopenApplication`; a ``TypeError`` naming the missing ones
    otherwise (subclass :class:`BaseApplication` to get the hooks an application does not need)."""
    missing = [name for name in APPLICATION_MEMBERS if not hasattr(app, name)]
    if missing:
        raise TypeError(f"{type(app).__name__} is no CanopenApplication: it lacks {', '.join(missing)} "
                        "(subclass virtualaxis.canopen_slave.BaseApplication for hooks it does not need)")
    return app
