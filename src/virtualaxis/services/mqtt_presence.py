"""Who publishes an axis on the broker, and how its connection goes: the identity of one ``serve`` process
(instance id, birth sequence), the detection of a second process publishing the same ``<machine>/<axis>``, and
one console line (stderr) per change of a connection's state, with the reason.

Every ``serve`` process draws a random **instance id**; its MQTT client identifiers
(``virtualaxis-<machine>-<axis>-<instance id>``) are therefore unique, so two processes never take each other's
session over. Each accepted connection of an axis increments its **birth sequence** (``birth_seq``, 1 for the
first); the birth message ``online`` and the last will ``offline`` of one connection carry the same
``instance_id`` and ``birth_seq`` (the idea of Sparkplug's ``bdSeq``): a consumer pairs a death with its birth
and counts the connections of a node.
"""

from __future__ import annotations

import json
import socket
import sys
import uuid
from typing import TextIO


def new_instance_id() -> str:
    """A random identifier of this process (12 hex digits)."""
    return uuid.uuid4().hex[:12]


def client_identifier(machine: str, axis: str, instance_id: str) -> str:
    """The MQTT client identifier of ``axis`` in the process ``instance_id``: unique per process."""
    return f"virtualaxis-{machine}-{axis}-{instance_id}"


def presence_fields(instance_id: str, birth_seq: int, pid: int) -> dict:
    """The fields of a status message (birth and will) that name the process (``pid``: serve's) and the
    connection."""
    return {"instance_id": instance_id, "birth_seq": birth_seq, "pid": pid, "host": socket.gethostname()}


def other_publisher(own_instance_id: str, payload: bytes | bytearray | str) -> dict | None:
    """The status message ``payload`` when it is an ``online`` birth of another process (a clash), else None."""
    try:
        d = json.loads(payload)
    except (ValueError, TypeError):
        return None
    if not isinstance(d, dict) or d.get("status") != "online":
        return None
    other = d.get("instance_id")
    if other == own_instance_id:
        return None
    return d


class ConnectionLog:
    """One line on ``stream`` per state change of an axis' broker connection: connected, refused/unreachable
    (the reason, once until it changes), lost (the reason), clash with another process."""

    def __init__(self, host: str, port: int, stream: TextIO | None = None):
        self.where = f"{host}:{port}"
        self.stream = stream
        self._last: dict[str, str] = {}  # axis -> the last state line's key
        self._clashes: dict[str, set] = {}

    def _say(self, line: str) -> None:
        print(line, file=self.stream or sys.stderr, flush=True)

    def connected(self, axis: str, birth_seq: int, protocol: str) -> None:
        self._last[axis] = "connected"
        self._say(f"mqtt: axis {axis}: connected to {self.where} ({protocol}, birth {birth_seq})")

    def failed(self, axis: str, reason: str, was_connected: bool, retry_s: float) -> None:
        """A connection attempt failed (``was_connected`` False) or a connection was lost (True)."""
        reason = reason.strip() or "no reason given"
        if "taken over" in reason.lower():
            reason += " (another client connected with this client identifier)"
        if "certificate" in reason.lower() and "verify" in reason.lower():
            reason += " (the broker's certificate is not trusted: check the CA file of the mqtts:// URL)"
        if was_connected:
            key = f"lost:{reason}"
            line = f"mqtt: axis {axis}: connection to {self.where} lost: {reason}; reconnecting in {retry_s:g} s"
        else:
            key = f"failed:{reason}"
            line = (f"mqtt: axis {axis}: cannot connect to {self.where}: {reason}; retrying with backoff "
                    f"(next in {retry_s:g} s)")
        if self._last.get(axis) == key:
            return  # the same failure again: said once
        self._last[axis] = key
        self._say(line)

    def clash(self, axis: str, topic: str, other: dict) -> None:
        """Another process publishes ``online`` on this axis' status topic: named once per other process."""
        ident = str(other.get("instance_id", "unknown"))
        seen = self._clashes.setdefault(axis, set())
        if ident in seen:
            return
        seen.add(ident)
        who = (f"instance {ident}, pid {other.get('pid', '?')} on host {other.get('host', '?')}"
               if "instance_id" in other else "a publisher without an instance id")
        self._say(f"warning: mqtt: axis {axis}: another process publishes {topic} ({who}): two serves with the "
                  f"same machine and axis names share the topics; give each its own --machine")

    def stopped(self, axis: str) -> None:
        self._last[axis] = "stopped"
        self._say(f"mqtt: axis {axis}: disconnected from {self.where} (stop)")
