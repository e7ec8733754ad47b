"""MQTT telemetry of the served axes (aiomqtt), published by a process of its own.

Topics per axis under ``virtualaxis/<machine>/<axis>/`` (payloads JSON, units in the field names, schemas in
``docs/schemas/``):

- ``status``: ``online`` birth message (retained, QoS 1) and the retained last will ``offline`` (also sent on a
  clean stop);
- ``state``: NMT and CiA 402 state, mode, active faults, telemetry counters (retained, QoS 1; on connect, on
  every drive event and every ``state_interval_s``);
- ``telemetry``: batches of samples (QoS 0, not retained; default 100 Hz in batches of 10);
- ``faults``: fault raised / cleared events (QoS 1, not retained);
- ``fault/set`` (subscribed, QoS 1): fault-injection commands, JSON ``{"action": "inject"|"clear", "kind": name or
  number, "duty", "period_s", "magnitude", "id"}``; each gets one ``fault/result`` (QoS 1, not retained). The
  publisher process checks a command's form (:func:`parse_fault_command`) and forwards the valid ones to
  ``serve``, whose command thread applies them with ``FaultInjector.command`` (refused unless ``serve
  --allow-fault-injection``; :func:`apply_fault_command`).

Where the work runs (the drive's process keeps only what must touch the drive):

- in ``serve``, a **sampler thread** (:class:`MqttService`) takes one ``drive.state`` per axis at the sample
  rate and writes its raw values into a **shared-memory ring** (:class:`TelemetryRing`, no lock: a sequence
  counter per slot); it forwards drive events (state transitions, faults, recorded by a drive observer) and
  the current state (10 per second) as small JSON messages over a socket pair;
- the **publisher process** (:func:`virtualaxis.services.mqtt_child.publisher_child`, a plain child interpreter
  below the drive that imports neither the drive nor numba) drains the ring every 10 ms into a bounded buffer per axis
  (:class:`SampleBuffer`), encodes the JSON and runs the asyncio / aiomqtt clients (one connection per axis).
  Its counters are published back into the shared memory (a sequence lock), so ``serve`` shows them
  (``MqttService.channels``, ``stats()``).

The drive never waits for the broker: with the broker absent, restarted or lost, samples stay in the buffer;
when it is full the oldest are dropped and counted (``samples_dropped``), and the connection is retried with
exponential backoff. Invariant, exact at any time: ``samples_taken = samples_published + samples_dropped +
samples_buffered``. When ``serve`` dies the publisher notices the closed socket pair and drops its
connections without a DISCONNECT, so the broker publishes the last will.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import re
import select
import ssl
import struct
import subprocess
import sys
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING
from urllib.parse import urlsplit

from virtualaxis.services.mqtt_presence import (
    ConnectionLog,
    client_identifier,
    new_instance_id,
    other_publisher,
    presence_fields,
)
from virtualaxis.services.threads import CHILD_PROLOGUE, short_gil_slices

if TYPE_CHECKING:  # the publisher process must not import the drive (numba)
    from virtualaxis.drive.core import Drive

TOPIC_ROOT = "virtualaxis"
SCHEMA_VERSION = 1
ENV_USERNAME = "VIRTUALAXIS_MQTT_USERNAME"
ENV_PASSWORD = "VIRTUALAXIS_MQTT_PASSWORD"
ENV_PASSWORD_FILE = "VIRTUALAXIS_MQTT_PASSWORD_FILE"
ENV_CA_FILE = "VIRTUALAXIS_MQTT_CA_FILE"
STATE_FORWARD_PERIOD_S = 0.1  # serve -> publisher: the current state this often (the retained state's freshness)
#: serve -> publisher: messages (events, transitions, command results) that wait, at most, for a publisher process
#: far behind before the oldest are dropped (chosen: a burst of ~1 000 faults; ~0.5 MB)
BACKLOG_MESSAGES = 2048


class MqttSettingsError(ValueError):
    """A bad --mqtt URL, credentials file or environment (the message names which)."""


@dataclass
class MqttSettings:
    """Broker, identity and rates of the MQTT telemetry."""

    host: str
    port: int
    machine: str
    tls: bool = False
    username: str | None = None
    password: str | None = None
    ca_file: str | None = None
    cert_file: str | None = None
    key_file: str | None = None
    rate_hz: float = 100.0  # telemetry sample rate
    batch_size: int = 10  # samples per telemetry message
    buffer_samples: int = 1000  # ring buffer per axis (10 s at 100 Hz)
    event_buffer: int = 256  # fault events kept while the broker is away
    state_interval_s: float = 1.0  # state republished at least this often (counters)
    backoff_min_s: float = 0.2  # reconnect backoff: doubles from min to max
    backoff_max_s: float = 5.0
    keepalive_s: int = 10
    publish_timeout_s: float = 2.0
    sparkplug_group: str | None = None  # Sparkplug B instead of the JSON topics (services/sparkplug.py)

    def validate(self) -> None:
        if not self.rate_hz > 0 or self.rate_hz > 1000:
            raise MqttSettingsError(f"--telemetry-rate: must be > 0 and at most 1000 Hz (got {self.rate_hz:g})")
        if self.batch_size < 1:
            raise MqttSettingsError(f"--telemetry-batch: must be >= 1 (got {self.batch_size})")
        if self.buffer_samples < self.batch_size:
            raise MqttSettingsError(
                f"--telemetry-buffer: {self.buffer_samples} samples must hold at least one batch "
                f"(--telemetry-batch {self.batch_size})"
            )
        if not TOPIC_NAME.fullmatch(self.machine):
            raise MqttSettingsError(f"--machine {self.machine!r}: use letters, digits, '_', '-', '.'")
        if self.sparkplug_group is not None and not TOPIC_NAME.fullmatch(self.sparkplug_group):
            raise MqttSettingsError(f"--sparkplug {self.sparkplug_group!r}: a group id takes letters, digits, '_', "
                                    "'-', '.'")


def parse_mqtt_url(url: str, machine: str) -> MqttSettings:
    """``mqtt://HOST[:PORT]`` or ``mqtts://HOST[:PORT]`` (TLS). Credentials in the URL are refused: they belong
    in a file or the environment, never on the command line."""
    parts = urlsplit(url)
    if parts.scheme not in ("mqtt", "mqtts"):
        raise MqttSettingsError(f"--mqtt {url!r}: expected mqtt://HOST:PORT or mqtts://HOST:PORT")
    if parts.username or parts.password:
        raise MqttSettingsError(
            f"--mqtt: credentials are not accepted on the command line; put them in --mqtt-credentials FILE "
            f"or {ENV_USERNAME} / {ENV_PASSWORD}"
        )
    if not parts.hostname:
        raise MqttSettingsError(f"--mqtt {url!r}: no host")
    extra = [name for name, value in (("path", parts.path not in ("", "/")), ("query", parts.query),
                                      ("fragment", parts.fragment)) if value]
    if extra:
        raise MqttSettingsError(f"--mqtt {url!r}: a broker URL has no {' / '.join(extra)} (mqtt://HOST:PORT)")
    tls = parts.scheme == "mqtts"
    try:
        port = parts.port or (8883 if tls else 1883)
    except ValueError:
        raise MqttSettingsError(f"--mqtt {url!r}: bad port") from None
    return MqttSettings(host=parts.hostname, port=port, machine=machine, tls=tls)


def load_credentials(settings: MqttSettings, path: str | None, env: dict | None = None) -> None:
    """Username / password / TLS files from a TOML file (keys ``username``, ``password``, ``ca_file``,
    ``cert_file``, ``key_file``) or the environment (``VIRTUALAXIS_MQTT_USERNAME``, ``..._PASSWORD``,
    ``..._PASSWORD_FILE``, ``..._CA_FILE``); the file wins."""
    env = os.environ if env is None else env
    settings.username = env.get(ENV_USERNAME) or settings.username
    settings.password = env.get(ENV_PASSWORD) or settings.password
    if env.get(ENV_PASSWORD_FILE):
        pw_path = Path(env[ENV_PASSWORD_FILE])
        try:
            settings.password = pw_path.read_text().strip()
        except OSError as exc:
            raise MqttSettingsError(f"{ENV_PASSWORD_FILE} {pw_path}: {exc.strerror}") from None
    settings.ca_file = env.get(ENV_CA_FILE) or settings.ca_file
    if path is not None:
        _credentials_file(settings, Path(path))
    if settings.password and not settings.username:  # (MQTT 3.1.1 has no password without a user name)
        raise MqttSettingsError(f"a password is given ({ENV_PASSWORD}, {ENV_PASSWORD_FILE} or --mqtt-credentials) "
                                f"but no user name ({ENV_USERNAME} or username in --mqtt-credentials)")


def _credentials_file(settings: MqttSettings, p: Path) -> None:
    """The keys of a --mqtt-credentials TOML file into ``settings``."""
    from virtualaxis.config.axis import read_text_file
    from virtualaxis.config.errors import ConfigError
    from virtualaxis.config.tomlfile import TomlError, parse_toml

    try:  # (size-capped, UTF-8 checked, a FIFO refused instead of read for ever)
        data = parse_toml(read_text_file(p, "credentials file"))
    except ConfigError as exc:
        raise MqttSettingsError(f"--mqtt-credentials {exc}") from None
    except TomlError as exc:
        raise MqttSettingsError(f"--mqtt-credentials {p}: {exc}") from None
    allowed = {"username", "password", "ca_file", "cert_file", "key_file"}
    for key, value in data.items():
        if key not in allowed:
            raise MqttSettingsError(f"--mqtt-credentials {p}: {key}: unknown key (allowed: "
                                    f"{', '.join(sorted(allowed))})")
        if not isinstance(value, str):
            raise MqttSettingsError(f"--mqtt-credentials {p}: {key}: must be a string")
        setattr(settings, key, value)


# ---------------------------------------------------------------------------------------------- fault commands
FAULT_COMMAND_KEYS = ("action", "kind", "duty", "period_s", "magnitude", "id")
FAULT_COMMAND_MAX_BYTES = 4096
FAULT_COMMAND_ID_MAX_CHARS = 128
GATED_MIN_PERIOD_S = 0.004  # telemetry periods from 4 ms (<= 250 Hz) are sampled in the gap after the PDOs
FAULT_COMMANDS_IN_FLIGHT = 16  # per axis: commands forwarded to serve and not answered yet (more: "busy")
ABORT_DEVICE_STATE = 0x08000022  # (drive.injection's codes; this module must not import the drive)


#: magnitude range of a fault command: the i32 of 0x5FF4 (CANopen) and 40603-40604 (Modbus)
MAGNITUDE_MIN, MAGNITUDE_MAX = -(2**31), 2**31 - 1
#: what an axis or machine name in a topic may hold (no topic level separator, no wildcard, no control character)
TOPIC_NAME = re.compile(r"[A-Za-z0-9_.\-]+")


def topic_name_problem(name: str) -> str | None:
    """Why ``name`` cannot be a level of a topic of this service (None: it can)."""
    if TOPIC_NAME.fullmatch(name):
        return None
    return f"{name!r} is not usable in an MQTT topic: use letters, digits, '_', '-', '.'"


def _reject_constant(name: str):
    raise ValueError(f"{name} is not a JSON number")


class _DuplicateKey(ValueError):
    pass


def _unique_keys(pairs: list[tuple[str, object]]) -> dict:
    """A JSON object whose keys are all different (json.loads keeps the last of a repeated key silently)."""
    out: dict = {}
    for key, value in pairs:
        if key in out:
            raise _DuplicateKey(key)
        out[key] = value
    return out


def _is_number(x) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool)


def parse_fault_command(payload: bytes | bytearray | str | None) -> tuple[dict | None, dict | None]:
    """A ``fault/set`` payload checked for form (not for the drive's rules: kind names, ranges and the
    permission are checked by ``FaultInjector.command`` in serve). Returns ``(command, None)`` with ``command``
    = ``{"action", "kind", "options", ["id"]}``, or ``(None, result)`` with the ``ok: false`` result that names
    what is wrong (the command's ``id`` echoed when it could be read)."""
    ident: dict = {}

    def refuse(message: str) -> tuple[None, dict]:
        return None, ident | {"ok": False, "error": message}

    if payload is None:
        payload = b""
    if isinstance(payload, str):
        payload = payload.encode("utf-8", "surrogatepass")
    if len(payload) > FAULT_COMMAND_MAX_BYTES:
        return refuse(f"payload is {len(payload)} bytes (at most {FAULT_COMMAND_MAX_BYTES})")
    try:
        text = bytes(payload).decode("utf-8")
    except UnicodeDecodeError:
        return refuse("payload is not UTF-8 text")
    try:
        data = json.loads(text, parse_constant=_reject_constant, object_pairs_hook=_unique_keys)
    except _DuplicateKey as exc:
        return refuse(f"duplicate key {str(exc.args[0])[:60]!r} (each key at most once)")
    except RecursionError:
        return refuse("payload is not JSON (nested too deeply)")
    except ValueError as exc:
        return refuse(f"payload is not JSON ({exc})")
    if not isinstance(data, dict):
        return refuse(f"payload must be a JSON object (got {type(data).__name__})")
    if "id" in data:
        i = data["id"]
        if isinstance(i, str) and len(i) <= FAULT_COMMAND_ID_MAX_CHARS or (
                isinstance(i, int) and not isinstance(i, bool) and abs(i) < 2**53):
            ident = {"id": i}
        else:
            return refuse(f"id: must be a string of at most {FAULT_COMMAND_ID_MAX_CHARS} characters or an integer "
                          f"(|id| < 2^53)")
    unknown = sorted(k for k in data if k not in FAULT_COMMAND_KEYS)
    if unknown:
        return refuse(f"unknown key{'s' if len(unknown) > 1 else ''} {', '.join(map(repr, unknown))[:200]} "
                      f"(allowed: {', '.join(FAULT_COMMAND_KEYS)})")
    action = data.get("action")
    if action not in ("inject", "clear"):
        if "action" not in data:
            return refuse('action: missing ("inject" or "clear")')
        return refuse(f'action: must be "inject" or "clear" (got {json.dumps(action)[:60]})')
    kind = data.get("kind")
    if isinstance(kind, float) and kind.is_integer():  # JSON Schema's "integer" includes 4.0: the number 4
        kind = int(kind)
    if kind is not None and not isinstance(kind, str) and not (isinstance(kind, int) and not isinstance(kind, bool)):
        return refuse(f"kind: must be a fault kind name or number (got {type(kind).__name__})")
    if isinstance(kind, str) and len(kind) > 64:
        return refuse("kind: unknown fault kind (name longer than 64 characters)")
    if isinstance(kind, int) and abs(kind) > 0xFFFF:
        return refuse(f"kind: unknown fault kind number {kind}")
    if action == "inject" and kind is None:
        return refuse("kind: missing (inject needs a fault kind name or number)")
    options: dict = {}
    for key in ("duty", "period_s", "magnitude"):
        if key not in data:
            continue
        value = data[key]
        if action == "clear":
            return refuse(f"{key}: only with action inject")
        if value is None and key == "magnitude":
            continue
        if not _is_number(value):
            return refuse(f"{key}: must be a number (got {type(value).__name__})")
        try:
            value = float(value)
        except OverflowError:
            return refuse(f"{key}: number out of range")
        if value != value or value in (float("inf"), float("-inf")):
            return refuse(f"{key}: must be finite")
        if key == "magnitude" and not MAGNITUDE_MIN <= value <= MAGNITUDE_MAX:
            return refuse(f"magnitude: must be {MAGNITUDE_MIN}..{MAGNITUDE_MAX} (the range of 0x5FF4 on CANopen "
                          f"and 40603-40604 on Modbus; got {value:g})")
        options[key] = value
    return ident | {"action": action, "kind": kind, "options": options}, None


def apply_fault_command(injector, command: dict) -> dict:
    """Apply a command of :func:`parse_fault_command` with ``injector`` (a ``FaultInjector`` or None: refused
    as not allowed); returns the result fields (``ok``, ``error``, ``abort_code``, ``active``, the ``id``)."""
    out = {k: command[k] for k in ("id",) if k in command} | {"action": command.get("action")}
    if command.get("kind") is not None:
        out["kind"] = command["kind"]
    if injector is None:
        return out | {"ok": False, "error": "fault injection is not available on this axis",
                      "abort_code": f"0x{ABORT_DEVICE_STATE:08X}", "active": []}
    from virtualaxis.drive.injection import KINDS, InjectionRefused

    try:
        injector.command(command["action"], command.get("kind"), **command.get("options", {}))
        out["ok"] = True
    except InjectionRefused as exc:
        out |= {"ok": False, "error": str(exc), "abort_code": f"0x{exc.code:08X}"}
    except Exception as exc:  # noqa: BLE001 - a command never takes serve down
        out |= {"ok": False, "error": f"internal error: {type(exc).__name__}: {exc}"}
    out["active"] = sorted(injector.active, key=lambda k: KINDS.get(k, 99))
    return out


# ---------------------------------------------------------------------------------------------- buffers
class SampleBuffer:
    """Bounded ring buffer of telemetry samples of one axis with exact counters (thread-safe)."""

    def __init__(self, capacity: int):
        self.capacity = capacity
        self._q: deque[dict] = deque()
        self._lock = threading.Lock()
        self.taken = 0
        self.dropped = 0
        self.published = 0

    def add(self, sample: dict) -> None:
        with self._lock:
            if len(self._q) >= self.capacity:
                self._q.popleft()
                self.dropped += 1
            self._q.append(sample)
            self.taken += 1

    def lose(self, n: int) -> None:
        """``n`` samples taken but lost before they reached the buffer (overwritten in the shared-memory
        ring while the publisher process stalled): counted taken and dropped."""
        with self._lock:
            self.taken += n
            self.dropped += n

    def peek(self, n: int) -> list[dict]:
        with self._lock:
            return [self._q[i] for i in range(min(n, len(self._q)))]

    def commit(self, batch: list[dict]) -> None:
        """Remove the published ``batch`` from the head and count all of it published.

        A sample of the batch that the sampler dropped from the full buffer while the batch was being written
        (``add`` drops the oldest, which may be in flight) was delivered all the same: it moves from
        ``dropped`` to ``published``, so the counters stay exact (``taken = published + dropped + buffered``)
        and ``dropped`` counts exactly the samples a subscriber never sees."""
        with self._lock:
            first = batch[0]["seq"]
            last = batch[-1]["seq"]
            popped = 0
            while self._q and first <= self._q[0]["seq"] <= last:
                self._q.popleft()
                popped += 1
            dropped_in_flight = len(batch) - popped
            self.dropped -= dropped_in_flight
            self.published += len(batch)

    def __len__(self) -> int:
        return len(self._q)

    def counters(self) -> dict:
        with self._lock:
            return {
                "samples_taken": self.taken,
                "samples_published": self.published,
                "samples_dropped": self.dropped,
                "samples_buffered": len(self._q),
            }


# ---------------------------------------------------------------------------------------------- shared memory
_U64 = struct.Struct("=Q")
_SLOT = struct.Struct("=Q6d")  # seq, drive time [s], position [m], following error [m], velocity [m/s], I [A], T [Nm]
RING_SLOTS = 4096  # per axis: 41 s at 100 Hz of publisher-process stall before samples are lost in the ring
# header words (u64) of one axis block
_W_BEGIN, _W_END, _SAMPLER_LATE, _CSEQ = 0, 1, 2, 3  # written by serve (0-2) / the publisher (3 on)
_COUNTER_NAMES = ("samples_taken", "samples_published", "samples_dropped", "samples_buffered", "batches_published",
                  "connects", "connect_attempts", "disconnects", "events_published", "events_dropped",
                  "events_buffered", "connected", "ring_next")
_COUNTERS = struct.Struct(f"={len(_COUNTER_NAMES)}Q")
_COUNTERS_AT = 4 * 8
_ERROR_AT = _COUNTERS_AT + _COUNTERS.size
_ERROR_BYTES = 256  # u16 length + UTF-8 text of the last connection error
_SLOTS_AT = _ERROR_AT + _ERROR_BYTES + (-(_ERROR_AT + _ERROR_BYTES) % 8)
BLOCK_BYTES = _SLOTS_AT + RING_SLOTS * _SLOT.size


class TelemetryRing:
    """One block per axis in shared memory: the sample ring (serve writes, the publisher reads) and the
    publisher's counters (the publisher writes under a sequence lock, serve reads).

    Sample ring: serve announces slot ``w`` by setting ``w_begin = w + 1``, writes the slot (its ``seq`` = w)
    and then sets ``w_end = w + 1``. A reader takes the slots below ``w_end``; a slot whose seq is no longer
    the one expected, or that ``w_begin`` has lapped while it was copied, was overwritten and counts as
    dropped -- so no torn sample is ever published."""

    def __init__(self, buf: memoryview, n_axes: int):
        self.buf = buf
        self.n = n_axes

    @staticmethod
    def size(n_axes: int) -> int:
        return BLOCK_BYTES * max(1, n_axes)

    def _word(self, axis: int, i: int) -> int:
        return _U64.unpack_from(self.buf, axis * BLOCK_BYTES + 8 * i)[0]

    def _set(self, axis: int, i: int, value: int) -> None:
        _U64.pack_into(self.buf, axis * BLOCK_BYTES + 8 * i, value)

    # ---------------------------------------------------------------- serve's side
    def write(self, axis: int, values: tuple) -> None:
        """Append one sample (the six floats of ``_SLOT`` after seq) of ``axis``."""
        w = self._word(axis, _W_END)
        self._set(axis, _W_BEGIN, w + 1)
        _SLOT.pack_into(self.buf, axis * BLOCK_BYTES + _SLOTS_AT + (w % RING_SLOTS) * _SLOT.size, w, *values)
        self._set(axis, _W_END, w + 1)

    def written(self, axis: int) -> int:
        """Samples serve wrote into the ring of ``axis`` (the next seq)."""
        return self._word(axis, _W_END)

    def set_sampler_late(self, axis: int, n: int) -> None:
        self._set(axis, _SAMPLER_LATE, n)

    def counters(self, axis: int) -> tuple[dict, str]:
        """The publisher's counters of ``axis`` and its last error (consistent: sequence-locked)."""
        base = axis * BLOCK_BYTES
        for _ in range(10_000):  # (a publisher that died mid-export leaves the lock odd: last read is returned)
            s1 = self._word(axis, _CSEQ)
            values = _COUNTERS.unpack_from(self.buf, base + _COUNTERS_AT)
            n = struct.unpack_from("=H", self.buf, base + _ERROR_AT)[0]
            err = bytes(self.buf[base + _ERROR_AT + 2 : base + _ERROR_AT + 2 + min(n, _ERROR_BYTES - 2)])
            if s1 == self._word(axis, _CSEQ) and not s1 & 1:
                break
            time.sleep(0)
        return dict(zip(_COUNTER_NAMES, values, strict=True)), err.decode("utf-8", "replace")

    # ---------------------------------------------------------------- the publisher's side
    def sampler_late(self, axis: int) -> int:
        return self._word(axis, _SAMPLER_LATE)

    def read(self, axis: int, start: int) -> tuple[list[tuple], int, int]:
        """Samples of ``axis`` from seq ``start`` on: (samples ``(seq, t, x, fe, v, i, tq)``, next seq, lost)."""
        w_end = self._word(axis, _W_END)
        lost = 0
        if w_end - start > RING_SLOTS:
            lost = w_end - RING_SLOTS - start
            start = w_end - RING_SLOTS
        base = axis * BLOCK_BYTES + _SLOTS_AT
        out = []
        for seq in range(start, w_end):
            sample = _SLOT.unpack_from(self.buf, base + (seq % RING_SLOTS) * _SLOT.size)
            if sample[0] != seq or self._word(axis, _W_BEGIN) > seq + RING_SLOTS:
                lost += 1  # overwritten while we read it
                continue
            out.append(sample)
        return out, w_end, lost

    def export(self, axis: int, counters: dict, last_error: str) -> None:
        base = axis * BLOCK_BYTES
        s = self._word(axis, _CSEQ)
        self._set(axis, _CSEQ, s + 1)  # odd: being written
        _COUNTERS.pack_into(self.buf, base + _COUNTERS_AT, *(int(counters.get(k, 0)) for k in _COUNTER_NAMES))
        err = last_error.encode("utf-8", "replace")[: _ERROR_BYTES - 2]
        struct.pack_into("=H", self.buf, base + _ERROR_AT, len(err))
        self.buf[base + _ERROR_AT + 2 : base + _ERROR_AT + 2 + len(err)] = err
        self._set(axis, _CSEQ, s + 2)


# ---------------------------------------------------------------------------------------------- serve's side
def state_fields(s, nmt_state: str) -> dict:
    """The drive part of a ``state`` message from a ``DriveState`` (JSON-ready; the publisher adds the head,
    the time stamp and its counters)."""
    active = [f.as_dict() for f in s.faults if not f.acknowledged] if s.fault_active else []
    return {
        "time_s": round(s.time_s, 6),
        "nmt_state": nmt_state,
        "cia402_state": s.cia402_state,
        "mode": s.mode,
        "mode_name": s.mode_name,
        "statusword": s.statusword,
        "fault_active": s.fault_active,
        "error_code": f"0x{s.error_code:04X}",
        "active_faults": active,
        "alarm_number": s.alarm_number,
        "homed": s.homed,
        "position_mm": round(s.position_actual_m * 1e3, 6),
    }


def project_pending(c: dict, written: int, capacity: int) -> dict:
    """The publisher's counters ``c`` with the samples serve wrote but the publisher has not drained yet
    (``written - ring_next``; e.g. while the publisher process is still starting) counted as the next drain
    will count them: taken; lost if the ring was lapped; added to the buffer, whose oldest beyond ``capacity``
    are dropped. So ``taken = published + dropped + buffered`` holds from serve's view at any time."""
    pending = max(0, written - c["ring_next"])
    if not pending:
        return c
    lost = max(0, pending - RING_SLOTS)
    buffered = c["samples_buffered"] + pending - lost
    over = max(0, buffered - capacity)
    return c | {"samples_taken": c["samples_taken"] + pending,
                "samples_dropped": c["samples_dropped"] + lost + over,
                "samples_buffered": buffered - over}


class BufferView:
    """serve's view of an axis' sample buffer in the publisher process (counters as in :class:`SampleBuffer`)."""

    def __init__(self, ch: AxisChannel):
        self._ch = ch

    def counters(self) -> dict:
        c = self._ch.counters()
        return {k: c[k] for k in ("samples_taken", "samples_published", "samples_dropped", "samples_buffered")}

    @property
    def taken(self) -> int:
        return self._ch.counters()["samples_taken"]

    @property
    def published(self) -> int:
        return self._ch.counters()["samples_published"]

    @property
    def dropped(self) -> int:
        return self._ch.counters()["samples_dropped"]

    def __len__(self) -> int:
        return self._ch.counters()["samples_buffered"]


class AxisChannel:
    """One axis' MQTT side as ``serve`` sees it: its drive, the events waiting to be forwarded, and the
    publisher process' counters (read from shared memory; kept after stop)."""

    def __init__(self, service: MqttService, index: int, name: str, node_id: int, drive: Drive,
                 nmt_state: Callable[[], str] | None, injector=None):
        self.service = service
        self.injector = injector  # FaultInjector of the axis (fault/set commands), None: refused
        self.commands = 0  # fault/set commands applied (ok or refused by the injector)
        self.index = index
        self.name = name
        self.node_id = node_id
        self.drive = drive
        self.nmt_state = nmt_state
        self.states: deque = deque(maxlen=32)  # DriveState snapshots of drive events, not yet forwarded
        self.events: deque = deque(maxlen=1024)  # fault events, not yet forwarded
        self.buffer = BufferView(self)
        self.sampler_late = 0
        self.last_nmt = ""  # NMT state last forwarded (a change is an event: a state message of its own)
        lead = drive.cfg.mechanics.lead_m
        self.lead_m = lead if lead > 0 else 0.01
        self._final: tuple[dict, str] | None = None

    def nmt(self) -> str:
        if self.nmt_state is None:  # a drive not served on CANopen has no NMT state
            return "UNKNOWN"
        try:
            return str(self.nmt_state())
        except Exception:  # noqa: BLE001 - a diagnostic field, never worth a crash
            return "UNKNOWN"

    def counters_and_error(self) -> tuple[dict, str]:
        """The publisher process' counters of this axis and its last connection error (after stop: as kept by
        :meth:`keep_final`)."""
        if self._final is not None:
            return self._final
        ring = self.service.ring
        if ring is None:
            return dict.fromkeys(_COUNTER_NAMES, 0), ""
        c, err = ring.counters(self.index)
        return project_pending(c, ring.written(self.index), self.service.settings.buffer_samples), err

    def counters(self) -> dict:
        return self.counters_and_error()[0]

    @property
    def last_error(self) -> str:
        return self.counters_and_error()[1]

    def keep_final(self, counters: dict, error: str) -> None:
        """The counters and error as the publisher left them (the shared memory goes with the stop)."""
        self._final = (counters, error)

    connects = property(lambda self: self.counters()["connects"])
    connect_attempts = property(lambda self: self.counters()["connect_attempts"])
    disconnects = property(lambda self: self.counters()["disconnects"])
    batches_published = property(lambda self: self.counters()["batches_published"])
    events_published = property(lambda self: self.counters()["events_published"])
    events_dropped = property(lambda self: self.counters()["events_dropped"])
    connected = property(lambda self: bool(self.counters()["connected"]))


class MqttService:
    """MQTT telemetry of ``axes`` (``(name, node_id, drive, nmt_state_getter[, fault_injector])``): a sampler
    thread and a command thread here, the publisher in a process of its own (module doc)."""

    def __init__(self, settings: MqttSettings, axes: list[tuple], gate=None):
        settings.validate()
        self.settings = settings
        self.gate = gate  # CycleGate or None: samples taken in the gap after a SYNC's PDOs (cycle_gate.py)
        self.channels: list[AxisChannel] = []
        for i, (name, node_id, drive, nmt, *injector) in enumerate(axes):
            problem = topic_name_problem(name)
            if problem is not None:
                raise MqttSettingsError(f"axis name {problem}")
            self.channels.append(AxisChannel(self, i, name, node_id, drive, nmt, *injector[:1]))
        self.ring: TelemetryRing | None = None
        self._shm = None
        self._proc: subprocess.Popen | None = None
        self._conn = None
        self._ctl = None
        self._stop = threading.Event()
        self._sampler: threading.Thread | None = None
        self._commands: threading.Thread | None = None
        self._send_lock = threading.Lock()  # the sampler and the command thread both send to the publisher
        self.wakes_skipped = 0  # wakes of a publisher process far behind, not sent (see _send_tick)
        #: messages waiting for a publisher process far behind (see _send); the newest state per axis only
        self.backlog: deque[tuple[int, bytes]] = deque(maxlen=BACKLOG_MESSAGES)  # (axis index, message)
        self._pending_state: dict[int, tuple[int, bytes]] = {}  # axis -> its state message waiting in the backlog
        self.messages_dropped = 0  # the oldest waiting messages dropped beyond BACKLOG_MESSAGES
        self._observers: list[tuple[Drive, Callable]] = []

    def _observer(self, ch: AxisChannel) -> Callable:
        active: set[tuple[int, float]] = set()  # the faults not yet acknowledged at the last event

        def record(event: str, state, rec) -> None:
            ch.events.append({
                "event": event,
                "time_s": round(state.time_s, 6),
                "ts_unix_s": round(time.time(), 3),
                "cia402_state": state.cia402_state,
                "error_code": f"0x{state.error_code:04X}",
                "emcy_code": f"0x{rec.emcy_code:04X}" if rec else "0x0000",
                "fault_number": f"F{rec.fault_number:05d}" if rec else "",
                "fault_value": int(rec.value) if rec else 0,
                "text": rec.text if rec else "",
                "injected": bool(rec.injected) if rec else False,
            })

        def on_event(event: str, state) -> None:  # runs under the drive's lock: cheap and non-blocking only
            ch.states.append(state)  # each transition gets its own state message (bounded: the newest 32)
            if event == "fault":
                record(event, state, state.faults[0] if state.faults else None)
            elif event == "fault_cleared":  # one event per fault the reset acknowledged (oldest first)
                cleared = [f for f in state.faults if f.acknowledged and (f.emcy_code, f.time_s) in active]
                for rec in reversed(cleared) if cleared else [state.faults[0] if state.faults else None]:
                    record(event, state, rec)
                active.clear()  # (the state event before it already shows them acknowledged: kept until here)
            active.update((f.emcy_code, f.time_s) for f in state.faults if not f.acknowledged)

        return on_event

    # -------------------------------------------------------------------------------- lifecycle
    def start(self) -> MqttService:
        import socket
        from multiprocessing import shared_memory
        from multiprocessing.connection import Connection

        short_gil_slices()
        self._shm = shared_memory.SharedMemory(create=True, size=TelemetryRing.size(len(self.channels)))
        self._shm.buf[:] = b"\x00" * self._shm.size
        self.ring = TelemetryRing(self._shm.buf, len(self.channels))
        spec = {
            "settings": {k: getattr(self.settings, k) for k in self.settings.__dataclass_fields__},
            "axes": [{"name": ch.name, "node_id": ch.node_id, "lead_m": ch.lead_m} for ch in self.channels],
            "shm": self._shm.name,
        }
        msg_ours, msg_theirs = socket.socketpair()
        ctl_ours, ctl_theirs = socket.socketpair()
        src = str(Path(__file__).resolve().parents[2])  # the virtualaxis package this process runs
        env = dict(os.environ, PYTHONPATH=os.pathsep.join([src, *filter(None, [os.environ.get("PYTHONPATH")])]))
        code = (f"import sys; {CHILD_PROLOGUE}from virtualaxis.services.mqtt_child import publisher_child; "
                "publisher_child(int(sys.argv[1]), int(sys.argv[2]), sys.argv[3])")
        self._proc = subprocess.Popen(
            [sys.executable, "-c", code, str(msg_theirs.fileno()), str(ctl_theirs.fileno()), json.dumps(spec)],
            pass_fds=(msg_theirs.fileno(), ctl_theirs.fileno()), env=env,
        )
        msg_theirs.close()
        ctl_theirs.close()
        self._conn = Connection(msg_ours.detach())
        self._ctl = Connection(ctl_ours.detach())
        for ch in self.channels:
            cb = self._observer(ch)
            ch.drive.add_observer(cb)
            self._observers.append((ch.drive, cb))
            ch.last_nmt = ch.nmt()
            self._send(ch, "state", state_fields(ch.drive.state, ch.last_nmt))
        self._sampler = threading.Thread(target=self._sample_loop, name="virtualaxis-mqtt-sampler", daemon=True)
        self._sampler.start()
        self._commands = threading.Thread(target=self._command_loop, name="virtualaxis-mqtt-commands", daemon=True)
        self._commands.start()
        return self

    def _send(self, ch: AxisChannel, kind: str, data: dict) -> None:
        """A message to the publisher process, in order, never blocking: while the process' socket is more than
        a quarter full (a publisher starved by other work, or stopped) messages wait in :attr:`backlog`, where a
        newer ``state`` of an axis replaces the older one still waiting (it is the whole current state); at most
        :data:`BACKLOG_MESSAGES` wait, the oldest beyond that dropped and counted (:attr:`messages_dropped`)."""
        msg = json.dumps({"axis": ch.index, "kind": kind, "data": data}).encode()
        with self._send_lock:
            backlog = self.backlog
            if backlog:
                self._flush_backlog()
            if not backlog:
                try:
                    if self._writable():
                        self._conn.send_bytes(msg)
                        return
                except (OSError, ValueError, AttributeError):  # the publisher process is gone: the drive goes on
                    return
            item = (ch.index, msg)
            if kind == "state":
                pending = self._pending_state.get(ch.index)
                if pending is not None:
                    try:
                        backlog.remove(pending)
                    except ValueError:  # (already dropped as the oldest)
                        pass
                self._pending_state[ch.index] = item
            if len(backlog) == backlog.maxlen:
                self.messages_dropped += 1
            backlog.append(item)

    def _writable(self, timeout_s: float = 0.0) -> bool:
        """Whether the publisher's message socket takes a message without blocking (at most a quarter full: what a
        socket reports writable), waiting up to ``timeout_s``."""
        return bool(select.select((), (self._conn.fileno(),), (), timeout_s)[1])

    def _flush_backlog(self) -> None:
        """Send the waiting messages while the publisher's socket takes them (under ``_send_lock``)."""
        backlog, conn = self.backlog, self._conn
        try:
            pending = self._pending_state
            while backlog and self._writable():
                item = backlog.popleft()
                conn.send_bytes(item[1])
                if pending.get(item[0]) is item:
                    del pending[item[0]]
        except (OSError, ValueError, AttributeError):  # the publisher process is gone
            backlog.clear()
            self._pending_state.clear()

    def _send_tick(self) -> None:
        """Wake the publisher process: not while its message socket is more than a quarter full (what a socket
        reports writable). A publisher that far behind (starved by other work: it runs below the drive) takes
        every sample in the ring at its next wake anyway; a full socket would block the sampler, and the periods
        it blocked would lose their samples. Skipped wakes are counted in :attr:`wakes_skipped`."""
        conn = self._conn
        try:
            with self._send_lock:
                if self.backlog:
                    self._flush_backlog()
                if self.backlog or not self._writable():
                    self.wakes_skipped += 1
                    return
                conn.send_bytes(b'{"kind": "tick"}')
        except (OSError, ValueError, AttributeError):
            pass

    def _command_loop(self) -> None:
        """fault/set commands the publisher process checked and forwarded: applied here, in serve's process but
        outside the drive's cycle (the injector takes the drive's lock like any API user), answered at once."""
        conn = self._conn
        while True:
            try:
                raw = conn.recv_bytes()
            except (EOFError, OSError):  # the publisher process ended
                return
            try:
                m = json.loads(raw)
                if m.get("kind") != "command":
                    continue
                ch = self.channels[int(m["axis"])]
                cmd = m["data"]
            except Exception:  # noqa: BLE001 - never from our own publisher; ignored, never fatal
                continue
            try:
                result = apply_fault_command(ch.injector, cmd)
            except Exception as exc:  # noqa: BLE001 - a command never takes serve down
                result = {k: cmd[k] for k in ("id",) if isinstance(cmd, dict) and k in cmd} | {
                    "ok": False, "error": f"internal error: {type(exc).__name__}: {exc}"}
            ch.commands += 1
            self._send(ch, "result", result)

    def _forward(self, ch: AxisChannel, s, current: bool) -> None:
        while ch.states:
            self._send(ch, "snapshot", state_fields(ch.states.popleft(), ch.nmt()))
        while ch.events:
            self._send(ch, "event", ch.events.popleft())
        if current:
            self._send(ch, "state", state_fields(s, ch.nmt()))

    def _sample_loop(self) -> None:
        # (keeps the process' priority: a thread that takes the drive's lock must not be preempted holding it)
        period = 1.0 / self.settings.rate_hz
        # in the gap after a SYNC's PDOs while a sample may wait up to a communication cycle for it; at higher
        # rates (a period under GATED_MIN_PERIOD_S) waiting for the next PDO burst would miss every other cycle:
        # those run at their own phase
        gate = self.gate if period >= GATED_MIN_PERIOD_S else None
        state_every = max(1, round(STATE_FORWARD_PERIOD_S / period))
        ring = self.ring
        nxt = time.perf_counter()
        tick = 0
        while not self._stop.is_set():
            now = time.perf_counter()
            if now < nxt:
                self._stop.wait(nxt - now)
                continue
            late = int((now - nxt) / period)  # whole periods missed (machine stalled): counted, not faked
            if late:
                for ch in self.channels:
                    ch.sampler_late += late
                    ring.set_sampler_late(ch.index, ch.sampler_late)
                nxt += late * period
            if gate is not None:
                gate.wait_next()
            for ch in self.channels:
                s = ch.drive.state
                ring.write(ch.index, (s.time_s, s.position_actual_m, s.following_error_m, s.velocity_actual_m_s,
                                      s.current_a, s.torque_nm))
                nmt = ch.nmt()
                if nmt != ch.last_nmt:  # NMT transitions (boot, start, stop) are events too
                    ch.last_nmt = nmt
                    self._send(ch, "snapshot", state_fields(s, nmt))
                if ch.states or ch.events or tick % state_every == 0:
                    self._forward(ch, s, tick % state_every == 0)
            self._send_tick()
            tick += 1
            nxt += period
        for ch in self.channels:  # the last events and the final state before the publisher flushes
            self._forward(ch, ch.drive.state, True)

    def stop(self, timeout_s: float = 5.0) -> None:
        """Stop sampling; the publisher publishes what is buffered when connected, sends ``offline`` and
        disconnects; its final counters are kept."""
        self._stop.set()
        if self._sampler is not None:
            self._sampler.join(timeout=timeout_s)
            self._sampler = None
        for drive, cb in self._observers:
            drive.remove_observer(cb)
        self._observers.clear()
        if self._conn is not None:  # after the last forwarded messages, on the same socket: in order
            end = time.monotonic() + timeout_s
            try:
                with self._send_lock:
                    while time.monotonic() < end:
                        self._flush_backlog()
                        if self._writable(0.05) and not self.backlog:
                            self._conn.send_bytes(json.dumps({"kind": "stop"}).encode())
                            break
            except (OSError, ValueError):
                pass
        if self._proc is not None:
            try:
                self._proc.wait(timeout=timeout_s + 2.0)
            except subprocess.TimeoutExpired:
                self._proc.kill()
                self._proc.wait(timeout=5.0)
            self._proc = None
        if self._commands is not None:  # the publisher's exit closed its end: the command thread saw EOF
            self._commands.join(timeout=timeout_s)
            self._commands = None
        if self.ring is not None:
            for ch in self.channels:
                c, err = self.ring.counters(ch.index)
                ch.keep_final(project_pending(c, self.ring.written(ch.index), self.settings.buffer_samples), err)
            self.ring = None
        for c in (self._conn, self._ctl):
            if c is not None:
                c.close()
        self._conn = self._ctl = None
        if self._shm is not None:
            try:
                self._shm.close()
                self._shm.unlink()
            except (FileNotFoundError, BufferError):
                pass
            self._shm = None

    def stats(self) -> dict:
        out = {}
        for ch in self.channels:
            c, err = ch.counters_and_error()
            out[ch.name] = {k: c[k] for k in ("samples_taken", "samples_published", "samples_dropped",
                                              "samples_buffered", "connects", "disconnects", "batches_published",
                                              "events_published", "events_dropped")}
            out[ch.name] |= {"sampler_late_samples": ch.sampler_late, "last_error": err,
                             "fault_commands": ch.commands}
        return out


# ---------------------------------------------------------------------------------------------- publisher process
@dataclass
class PubChannel:
    """One axis in the publisher process: its buffer, pending events / state messages, connection counters."""

    index: int
    name: str
    node_id: int
    lead_m: float
    buffer: SampleBuffer
    event_capacity: int
    events: deque = field(default_factory=deque)
    states: deque = field(default_factory=lambda: deque(maxlen=32))  # state fields of drive events
    # fault/result payloads to publish: one per fault/set message, none dropped (a bounded queue would lose the
    # answers of a long burst); each is answered at once, so the queue holds what the broker delivered faster than
    # the results go out
    results: deque = field(default_factory=deque)
    commands_in_flight: int = 0  # fault/set commands forwarded to serve, not answered yet
    current: dict | None = None  # the latest state fields serve forwarded
    events_dropped: int = 0
    events_published: int = 0
    state_dirty: bool = True
    connects: int = 0
    connect_attempts: int = 0
    disconnects: int = 0
    batches_published: int = 0
    connected: bool = False
    last_error: str = ""
    ring_next: int = 0  # next ring seq to drain
    sampler_late: int = 0
    auth_warned: bool = False  # the broker's refusal of the credentials was reported on stderr
    mqtt5: bool = True  # MQTT 5 (retain-as-published for fault/set); False after a 3.1.1 broker refused it
    mqtt5_unanswered: bool = False  # 3.1.1 because an MQTT 5 CONNECT got no CONNACK (not a refusal)
    birth_seq: int = 0  # the connection's birth sequence (its birth and will carry it; mqtt_presence)

    def counters(self) -> dict:
        return self.buffer.counters() | {
            "ring_next": self.ring_next,
            "batches_published": self.batches_published, "connects": self.connects,
            "connect_attempts": self.connect_attempts, "disconnects": self.disconnects,
            "events_published": self.events_published, "events_dropped": self.events_dropped,
            "events_buffered": len(self.events), "connected": int(self.connected),
        }


class Publisher:
    """The publisher process' work: drain the ring, keep the buffers, publish (asyncio + aiomqtt)."""

    def __init__(self, settings: MqttSettings, axes: list[dict], ring: TelemetryRing):
        self.settings = settings
        self.ring = ring
        self.channels = [
            PubChannel(i, a["name"], a["node_id"], a["lead_m"], SampleBuffer(settings.buffer_samples),
                       settings.event_buffer)
            for i, a in enumerate(axes)
        ]
        self._stop = threading.Event()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._lock = threading.Lock()  # the message reader thread vs the event loop (deques, dicts)
        self._tick: asyncio.Event | None = None  # set by serve's tick: new samples in the ring
        self._work: list[asyncio.Event] = []  # per axis: drained, publish now
        self.to_serve: Callable[[bytes], None] | None = None  # sends a message to serve (the command thread)
        self.instance_id = new_instance_id()  # this process' identity on the broker (mqtt_presence)
        self.connection_log = ConnectionLog(settings.host, settings.port)
        self.serve_pid = os.getppid()  # this publisher process is serve's child

    @property
    def stopping(self) -> bool:
        """serve asked this publisher to stop (its ``stop`` message): the run is ending cleanly."""
        return self._stop.is_set()

    # -------------------------------------------------------------------------------- inputs
    def on_message(self, raw: bytes) -> None:
        m = json.loads(raw)
        if m["kind"] == "stop":
            self._stop.set()
            return
        if m["kind"] == "tick":  # serve's sampler wrote samples (in the gap after a SYNC): work now
            loop, tick = self._loop, self._tick
            if loop is not None and tick is not None:
                try:
                    loop.call_soon_threadsafe(tick.set)
                except RuntimeError:  # the loop closed meanwhile
                    pass
            return
        ch = self.channels[m["axis"]]
        with self._lock:
            if m["kind"] == "state":
                ch.current = m["data"]
            elif m["kind"] == "snapshot":
                ch.states.append(m["data"])
                ch.current = m["data"]  # (serve forwards in time order: the newest state known)
                ch.state_dirty = True
            elif m["kind"] == "event":
                if len(ch.events) >= ch.event_capacity:
                    ch.events.popleft()
                    ch.events_dropped += 1
                ch.events.append(m["data"])
                ch.state_dirty = True
            elif m["kind"] == "result":  # serve applied a fault/set command
                ch.commands_in_flight = max(0, ch.commands_in_flight - 1)
                ch.results.append(m["data"])
        if m["kind"] == "result":
            self._wake(ch)

    def _wake(self, ch: PubChannel) -> None:
        """Publish now (from any thread)."""
        loop = self._loop
        if loop is None or not self._work:
            return
        try:
            loop.call_soon_threadsafe(self._work[ch.index].set)
        except RuntimeError:  # the loop closed meanwhile
            pass

    def on_command(self, ch: PubChannel, payload, retained: bool = False) -> None:
        """A ``fault/set`` message (in the event loop): checked here, forwarded to serve when well-formed, else
        answered at once with ``ok: false``. Never raises."""
        try:
            cmd, refusal = parse_fault_command(payload)
            if retained:  # replayed by the broker at each subscription: stale, never applied
                ident = {k: v for k, v in (cmd or refusal).items() if k == "id"}
                cmd, refusal = None, ident | {"ok": False, "error": "retained fault/set message ignored (a command "
                                                                     "is applied once: publish it with retain=false)"}
            if cmd is not None:
                with self._lock:
                    busy = ch.commands_in_flight >= FAULT_COMMANDS_IN_FLIGHT
                    if not busy:
                        ch.commands_in_flight += 1
                if busy:
                    refusal = {k: cmd[k] for k in ("id",) if k in cmd} | {
                        "ok": False, "error": f"busy: {FAULT_COMMANDS_IN_FLIGHT} commands of this axis in progress"}
                else:
                    try:
                        self.to_serve(json.dumps({"kind": "command", "axis": ch.index, "data": cmd}).encode())
                    except Exception:  # noqa: BLE001 - serve is gone
                        with self._lock:
                            ch.commands_in_flight = max(0, ch.commands_in_flight - 1)
                        refusal = {k: cmd[k] for k in ("id",) if k in cmd} | {"ok": False,
                                                                              "error": "serve is not reachable"}
        except Exception as exc:  # noqa: BLE001 - a bad message never takes the publisher down
            refusal = {"ok": False, "error": f"internal error: {type(exc).__name__}"}
        if refusal is not None:
            with self._lock:
                ch.results.append(refusal)
            if self._work:
                self._work[ch.index].set()

    def drain(self) -> None:
        """Move the new samples of every axis from the ring into its buffer; export the counters."""
        ring = self.ring
        for ch in self.channels:
            samples, ch.ring_next, lost = ring.read(ch.index, ch.ring_next)
            if lost:
                ch.buffer.lose(lost)
            lead = ch.lead_m
            for seq, t, x, fe, v, i, tq in samples:
                ch.buffer.add({
                    "seq": seq,
                    "t_s": round(t, 6),
                    "position_mm": round(x * 1e3, 6),
                    "following_error_um": round(fe * 1e6, 4),
                    "velocity_mm_min": round(v * 6e4, 3),
                    "speed_rpm": round(v / lead * 60.0, 3),
                    "current_a": round(i, 4),
                    "torque_nm": round(tq, 4),
                })
            ch.sampler_late = ring.sampler_late(ch.index)
            self.export(ch)

    def export(self, ch: PubChannel) -> None:
        self.ring.export(ch.index, ch.counters(), ch.last_error)

    # -------------------------------------------------------------------------------- topics / payloads
    def topic(self, ch: PubChannel, leaf: str) -> str:
        return f"{TOPIC_ROOT}/{self.settings.machine}/{ch.name}/{leaf}"

    def _head(self, ch: PubChannel) -> dict:
        return {"schema": SCHEMA_VERSION, "machine": self.settings.machine, "axis": ch.name, "node_id": ch.node_id}

    def status_payload(self, ch: PubChannel, online: bool) -> bytes:
        d = self._head(ch) | {"status": "online" if online else "offline", "ts_unix_s": round(time.time(), 3)}
        d |= presence_fields(self.instance_id, ch.birth_seq, self.serve_pid)
        if online:
            d["telemetry_rate_hz"] = self.settings.rate_hz
            d["telemetry_batch_size"] = self.settings.batch_size
            d["telemetry_buffer_samples"] = self.settings.buffer_samples
        return json.dumps(d).encode()

    def result_payload(self, ch: PubChannel, result: dict) -> bytes:
        return json.dumps(self._head(ch) | {"ts_unix_s": round(time.time(), 3)} | result).encode()

    def will_payload(self, ch: PubChannel) -> bytes:
        presence = presence_fields(self.instance_id, ch.birth_seq, self.serve_pid)
        return json.dumps(self._head(ch) | {"status": "offline"} | presence).encode()

    def state_payload(self, ch: PubChannel, fields: dict, online: bool = True) -> bytes:
        d = self._head(ch) | {"ts_unix_s": round(time.time(), 3), "online": online} | fields | {
            "telemetry": ch.buffer.counters()
            | {
                "rate_hz": self.settings.rate_hz,
                "batch_size": self.settings.batch_size,
                "buffer_samples": self.settings.buffer_samples,
                "batches_published": ch.batches_published,
                "sampler_late_samples": ch.sampler_late,
            },
            "events": {"events_published": ch.events_published, "events_dropped": ch.events_dropped,
                       "events_buffered": len(ch.events)},
            "connection": {"connects": ch.connects, "disconnects": ch.disconnects,
                           "connect_attempts": ch.connect_attempts},
        }
        return json.dumps(d).encode()

    def telemetry_payload(self, ch: PubChannel, batch: list[dict]) -> bytes:
        c = ch.buffer.counters()
        d = self._head(ch) | {
            "ts_unix_s": round(time.time(), 3),
            "rate_hz": self.settings.rate_hz,
            "seq_first": batch[0]["seq"],
            "samples_dropped": c["samples_dropped"],
            "samples": batch,
        }
        return json.dumps(d, separators=(",", ":")).encode()

    # -------------------------------------------------------------------------------- the loop
    def run(self) -> None:
        loop = asyncio.new_event_loop()
        self._loop = loop
        asyncio.set_event_loop(loop)
        try:
            loop.run_until_complete(self._main())
        finally:
            loop.close()

    async def _main(self) -> None:
        self._work = [asyncio.Event() for _ in self.channels]
        self._tick = asyncio.Event()
        drainer = asyncio.ensure_future(self._drain_loop())
        try:
            await asyncio.gather(*(self._axis_loop(ch) for ch in self.channels))
        finally:
            drainer.cancel()
            try:
                await drainer
            except asyncio.CancelledError:
                pass
            self.drain()  # the last samples (serve's sampler has stopped): counted exactly

    async def _drain_loop(self) -> None:
        """Drain when serve's sampler says it wrote samples (its tick comes in the gap after a SYNC's PDOs, so
        this process' work -- JSON, the TCP send to the broker and the broker's forwarding -- happens there too,
        not when the next SYNC arrives); at least every 50 ms without ticks."""
        tick = self._tick
        while True:
            try:
                await asyncio.wait_for(tick.wait(), 0.05)
            except asyncio.TimeoutError:
                pass
            tick.clear()
            self.drain()
            for ev in self._work:
                ev.set()

    async def _wait_work(self, ch: PubChannel) -> None:
        ev = self._work[ch.index]
        try:
            await asyncio.wait_for(ev.wait(), 0.05)
        except asyncio.TimeoutError:
            pass
        ev.clear()

    def _tls_context(self) -> ssl.SSLContext | None:
        st = self.settings
        if not st.tls:
            return None
        ctx = ssl.create_default_context(cafile=st.ca_file) if st.ca_file else ssl.create_default_context()
        if st.cert_file:
            ctx.load_cert_chain(st.cert_file, st.key_file)
        return ctx

    async def _axis_loop(self, ch: PubChannel) -> None:
        import aiomqtt

        st = self.settings
        backoff = st.backoff_min_s
        tls = self._tls_context()
        while not self._stop.is_set():
            ch.connect_attempts += 1
            self.export(ch)
            v5 = ch.mqtt5
            accepted = False  # CONNACK with success received
            ch.birth_seq = ch.connects + 1  # the will of this attempt carries the birth sequence it would have
            try:
                client = aiomqtt.Client(
                    st.host,
                    st.port,
                    username=st.username,
                    password=st.password,
                    identifier=client_identifier(st.machine, ch.name, self.instance_id),
                    will=aiomqtt.Will(self.topic(ch, "status"), self.will_payload(ch), qos=1, retain=True),
                    keepalive=st.keepalive_s,
                    timeout=st.publish_timeout_s,
                    tls_context=tls,
                    protocol=aiomqtt.ProtocolVersion.V5 if v5 else aiomqtt.ProtocolVersion.V311,
                    clean_session=None if v5 else True,
                    clean_start=True if v5 else 3,
                )
                async with client:
                    accepted = True
                    tcp_no_delay(client)
                    ch.connects += 1
                    ch.connected = True
                    self.connection_log.connected(ch.name, ch.birth_seq, "MQTT 5" if v5 else "MQTT 3.1.1")
                    self.export(ch)
                    backoff = st.backoff_min_s
                    await self._session(client, ch)
                    self.connection_log.stopped(ch.name)
                    return  # clean stop
            except aiomqtt.MqttError as exc:
                ch.last_error = str(exc)
                rc = getattr(getattr(exc, "rc", None), "value", getattr(exc, "rc", None))
                if rc in (4, 5, 134, 135) and not ch.auth_warned:  # bad user name or password / not authorized
                    ch.auth_warned = True  # (once: the backoff retries on, the --json summary has last_error)
                    print(f"warning: mqtt {st.host}:{st.port}: the broker refused axis {ch.name}: {exc} (check "
                          f"--mqtt-credentials / {ENV_USERNAME} / {ENV_PASSWORD}); retrying", file=sys.stderr,
                          flush=True)
                if v5 and rc in (1, 132):
                    ch.mqtt5 = False  # an MQTT 3.1.1 broker ("unsupported protocol version"): again at once in 3.1.1
                    ch.mqtt5_unanswered = False
                    continue
                if v5 and not accepted and rc is None and "timed out" in str(exc).lower():
                    # no CONNACK at all: some 3.1.1 brokers cannot parse an MQTT 5 CONNECT with a will (amqtt 0.12)
                    ch.mqtt5 = False  # and say nothing; again at once in 3.1.1
                    ch.mqtt5_unanswered = True
                    # aiomqtt leaves the unanswered client's socket open: closed here, while the event loop
                    # runs (collected after it has closed, paho prints 'Event loop is closed' tracebacks)
                    with contextlib.suppress(aiomqtt.MqttError):
                        await client.__aexit__(None, None, None)
                    continue
                if not v5 and ch.mqtt5_unanswered:
                    if accepted or rc is not None:
                        ch.mqtt5_unanswered = False  # answered in 3.1.1: a 3.1.1 broker
                    else:
                        ch.mqtt5 = True  # 3.1.1 went unanswered too: a broker away, not a 3.1.1 one
            except OSError as exc:
                ch.last_error = str(exc)
            if not self._stop.is_set():
                self.connection_log.failed(ch.name, ch.last_error, ch.connected, backoff)
            if ch.connected:
                ch.disconnects += 1
                ch.connected = False
                ch.state_dirty = True
            self.export(ch)
            await self._sleep(backoff)
            backoff = min(backoff * 2.0, st.backoff_max_s)
        # stopped while the broker was away: nothing more can be sent

    async def _sleep(self, seconds: float) -> None:
        end = time.monotonic() + seconds
        while not self._stop.is_set() and time.monotonic() < end:
            await asyncio.sleep(min(0.05, max(0.0, end - time.monotonic())))

    async def _session(self, client, ch: PubChannel) -> None:
        """Publish while connected; raises aiomqtt.MqttError when the connection is lost."""
        st = self.settings
        watcher = asyncio.ensure_future(self._watch(client, ch))
        try:
            # subscribed (SUBACK) before the birth message: a client that saw ``online`` can send commands
            if ch.mqtt5:  # the retain flag as the commanding client published it (3.1.1: only a replay has it)
                from paho.mqtt.subscribeoptions import SubscribeOptions

                await client.subscribe(self.topic(ch, "fault/set"),
                                       options=SubscribeOptions(qos=1, retainAsPublished=True))
            else:
                await client.subscribe(self.topic(ch, "fault/set"), qos=1)
            # the status topic too: a retained or live birth of another process there is a clash, named
            await client.subscribe(self.topic(ch, "status"), qos=1)
            await client.publish(self.topic(ch, "status"), self.status_payload(ch, True), qos=1, retain=True)
            while ch.current is None and not self._stop.is_set():  # serve forwards the state right at start
                await asyncio.sleep(0.01)
            if ch.current is None:
                return
            # the state right after the birth message, before any backlog of telemetry ("on connect")
            ch.state_dirty = False
            published = ch.current  # the state fields last published (an event's state goes out once)
            await client.publish(self.topic(ch, "state"), self.state_payload(ch, published), qos=1, retain=True)
            next_state = time.monotonic() + st.state_interval_s
            while True:
                stopping = self._stop.is_set()
                if stopping:
                    self.drain()  # serve's sampler stopped before it said stop: these are the last samples
                if watcher.done():
                    watcher.result()  # raises the disconnect
                while ch.results:
                    res = ch.results[0]
                    await client.publish(self.topic(ch, "fault/result"), self.result_payload(ch, res), qos=1)
                    with self._lock:
                        if ch.results and ch.results[0] is res:
                            ch.results.popleft()
                while ch.events:
                    ev = ch.events[0]
                    payload = json.dumps(self._head(ch) | ev).encode()
                    await client.publish(self.topic(ch, "faults"), payload, qos=1)
                    with self._lock:
                        if ch.events and ch.events[0] is ev:
                            ch.events.popleft()
                            ch.events_published += 1
                while len(ch.buffer) >= st.batch_size or (stopping and len(ch.buffer)):
                    batch = ch.buffer.peek(st.batch_size)
                    await client.publish(self.topic(ch, "telemetry"), self.telemetry_payload(ch, batch), qos=0)
                    ch.buffer.commit(batch)
                    ch.batches_published += 1
                while ch.states:
                    snap = ch.states[0]
                    if snap != published:  # (a fault and its state transition are two drive events, one state)
                        published = snap
                        await client.publish(self.topic(ch, "state"), self.state_payload(ch, snap), qos=1,
                                             retain=True)
                    with self._lock:
                        if ch.states and ch.states[0] is snap:
                            ch.states.popleft()
                now = time.monotonic()
                dirty, ch.state_dirty = ch.state_dirty, False
                if (ch.current != published and (dirty or stopping)) or (now >= next_state and not stopping):
                    # (the current state last, so the retained message is the newest; not again when it is
                    # the event's state just published: one state message per drive event; at a stop the
                    # offline state below carries it when it is)
                    published = ch.current
                    await client.publish(self.topic(ch, "state"), self.state_payload(ch, published), qos=1,
                                         retain=True)
                    next_state = now + st.state_interval_s
                if stopping:
                    # the retained state says it is no longer live (a consumer reads ``online``), then the status
                    await client.publish(self.topic(ch, "state"), self.state_payload(ch, published, online=False),
                                         qos=1, retain=True)
                    await client.publish(self.topic(ch, "status"), self.status_payload(ch, False), qos=1, retain=True)
                    self.export(ch)
                    return
                self.export(ch)
                await self._wait_work(ch)
        finally:
            watcher.cancel()

    async def _watch(self, client, ch: PubChannel) -> None:
        """Takes the ``fault/set`` commands; ends with aiomqtt.MqttError when the connection drops."""
        topic = self.topic(ch, "fault/set")
        status = self.topic(ch, "status")
        async for message in client.messages:
            if str(message.topic) == topic:
                self.on_command(ch, message.payload, bool(message.retain))
            elif str(message.topic) == status:
                other = other_publisher(self.instance_id, message.payload)
                if other is not None:
                    self.connection_log.clash(ch.name, status, other)


def tcp_no_delay(client) -> None:
    """TCP_NODELAY on the client's socket: a small QoS 1 message (a fault event, a fault/result) leaves at once
    instead of waiting, behind the unacknowledged telemetry, for the broker's delayed ACK (Nagle: ~40 ms)."""
    import socket

    try:
        sock = client._client.socket()  # (paho's socket; aiomqtt has no option for it)
        if sock is not None:
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    except (AttributeError, OSError):
        pass


def machine_name_from(config_path: str | Path | None, default: str = "machine") -> str:
    """The machine name for topics when --machine is not given: the main axis config's file stem."""
    if config_path is None:
        return default
    stem = Path(config_path).stem
    name = re.sub(r"[^A-Za-z0-9_.\-]", "_", stem)
    return name or default

