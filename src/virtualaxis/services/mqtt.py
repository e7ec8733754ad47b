"""MQTT telemetry of the served axes (aiomqtt), in its own thread and asyncio loop.

Topics per axis under ``virtualaxis/<machine>/<axis>/`` (payloads JSON, units in the field names, schemas in
``docs/schemas/``):

- ``status``: ``online`` birth message (retained, QoS 1) and the retained last will ``offline`` (also sent on a
  clean stop);
- ``state``: NMT and CiA 402 state, mode, active faults, telemetry counters (retained, QoS 1; on connect, on
  every drive event and every ``state_interval_s``);
- ``telemetry``: batches of samples (QoS 0, not retained; default 100 Hz in batches of 10);
- ``faults``: fault raised / cleared events (QoS 1, not retained).

The drive never waits for the broker: a sampler thread copies ``drive.state`` into a bounded ring buffer per
axis at the sample rate; the publisher (one MQTT connection per axis) drains it in batches. With the broker
absent, restarted or lost, samples stay in the buffer; when it is full the oldest are dropped and counted
(``samples_dropped``), and the connection is retried with exponential backoff. Invariant, exact at any time:
``samples_taken = samples_published + samples_dropped + samples_buffered``.
"""

from __future__ import annotations

import asyncio
import json
import os
import re
import ssl
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from urllib.parse import urlsplit

from virtualaxis.drive.core import Drive
from virtualaxis.services.threads import short_gil_slices

TOPIC_ROOT = "virtualaxis"
SCHEMA_VERSION = 1
ENV_USERNAME = "VIRTUALAXIS_MQTT_USERNAME"
ENV_PASSWORD = "VIRTUALAXIS_MQTT_PASSWORD"
ENV_PASSWORD_FILE = "VIRTUALAXIS_MQTT_PASSWORD_FILE"
ENV_CA_FILE = "VIRTUALAXIS_MQTT_CA_FILE"


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

    def validate(self) -> None:
        if not self.rate_hz > 0 or self.rate_hz > 1000:
            raise MqttSettingsError(f"telemetry rate must be in (0, 1000] Hz (got {self.rate_hz})")
        if self.batch_size < 1:
            raise MqttSettingsError(f"telemetry batch size must be >= 1 (got {self.batch_size})")
        if self.buffer_samples < self.batch_size:
            raise MqttSettingsError(
                f"telemetry buffer ({self.buffer_samples}) must hold at least one batch ({self.batch_size})"
            )
        if not re.fullmatch(r"[A-Za-z0-9_.\-]+", self.machine):
            raise MqttSettingsError(f"machine name {self.machine!r}: use letters, digits, '_', '-', '.'")


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
            raise MqttSettingsError(f"{pw_path} ({ENV_PASSWORD_FILE}): {exc.strerror}") from None
    settings.ca_file = env.get(ENV_CA_FILE) or settings.ca_file
    if path is None:
        return
    try:
        import tomllib
    except ModuleNotFoundError:  # Python 3.10
        import tomli as tomllib

    p = Path(path)
    try:
        data = tomllib.loads(p.read_text())
    except OSError as exc:
        raise MqttSettingsError(f"{p}: {exc.strerror}") from None
    except tomllib.TOMLDecodeError as exc:
        raise MqttSettingsError(f"{p}: not valid TOML ({exc})") from None
    allowed = {"username", "password", "ca_file", "cert_file", "key_file"}
    for key, value in data.items():
        if key not in allowed:
            raise MqttSettingsError(f"{p}: {key}: unknown key (allowed: {', '.join(sorted(allowed))})")
        if not isinstance(value, str):
            raise MqttSettingsError(f"{p}: {key}: must be a string")
        setattr(settings, key, value)


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


@dataclass
class AxisChannel:
    """One axis' MQTT side: its drive, node id, NMT state getter, sample buffer and pending fault events."""

    name: str
    node_id: int
    drive: Drive
    nmt_state: Callable[[], str] | None
    buffer: SampleBuffer
    event_capacity: int
    events: deque = field(default_factory=deque)
    states: deque = field(default_factory=lambda: deque(maxlen=32))  # DriveState snapshots of drive events
    events_dropped: int = 0
    events_published: int = 0
    state_dirty: bool = True
    connects: int = 0
    connect_attempts: int = 0
    disconnects: int = 0
    batches_published: int = 0
    connected: bool = False
    last_error: str = ""
    seq: int = 0
    lead_m: float = 0.01
    sampler_late: int = 0

    def nmt(self) -> str:
        if self.nmt_state is None:  # a drive not served on CANopen has no NMT state
            return "UNKNOWN"
        try:
            return str(self.nmt_state())
        except Exception:  # noqa: BLE001 - a diagnostic field, never worth a crash
            return "UNKNOWN"


def sample_of(ch: AxisChannel, seq: int) -> dict:
    """One telemetry sample of the axis' current drive state (units in the field names)."""
    s = ch.drive.state
    return {
        "seq": seq,
        "t_s": round(s.time_s, 6),
        "position_mm": round(s.position_actual_m * 1e3, 6),
        "following_error_um": round(s.following_error_m * 1e6, 4),
        "velocity_mm_min": round(s.velocity_actual_m_s * 6e4, 3),
        "speed_rpm": round(s.velocity_actual_m_s / ch.lead_m * 60.0, 3),
        "current_a": round(s.current_a, 4),
        "torque_nm": round(s.torque_nm, 4),
    }


# ---------------------------------------------------------------------------------------------- service
class MqttService:
    """MQTT telemetry of ``axes`` (``(name, node_id, drive, nmt_state_getter)``) in a background thread."""

    def __init__(self, settings: MqttSettings, axes: list[tuple[str, int, Drive, Callable[[], str] | None]]):
        settings.validate()
        self.settings = settings
        self.channels: list[AxisChannel] = []
        for name, node_id, drive, nmt in axes:
            if not re.fullmatch(r"[A-Za-z0-9_.\-]+", name):
                raise MqttSettingsError(f"axis name {name!r} is not usable in an MQTT topic")
            ch = AxisChannel(name, node_id, drive, nmt, SampleBuffer(settings.buffer_samples), settings.event_buffer)
            lead = drive.cfg.mechanics.lead_m
            ch.lead_m = lead if lead > 0 else 0.01
            self.channels.append(ch)
        self._stop = threading.Event()
        self._sampler: threading.Thread | None = None
        self._thread: threading.Thread | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._observers: list[tuple[Drive, Callable]] = []

    # -------------------------------------------------------------------------------- topics / payloads
    def topic(self, ch: AxisChannel, leaf: str) -> str:
        return f"{TOPIC_ROOT}/{self.settings.machine}/{ch.name}/{leaf}"

    def _head(self, ch: AxisChannel) -> dict:
        return {"schema": SCHEMA_VERSION, "machine": self.settings.machine, "axis": ch.name, "node_id": ch.node_id}

    def status_payload(self, ch: AxisChannel, online: bool) -> bytes:
        d = self._head(ch) | {"status": "online" if online else "offline", "ts_unix_s": round(time.time(), 3)}
        if online:
            d["telemetry_rate_hz"] = self.settings.rate_hz
            d["telemetry_batch_size"] = self.settings.batch_size
            d["telemetry_buffer_samples"] = self.settings.buffer_samples
        return json.dumps(d).encode()

    def will_payload(self, ch: AxisChannel) -> bytes:
        d = self._head(ch) | {"status": "offline"}
        return json.dumps(d).encode()

    def state_payload(self, ch: AxisChannel, snapshot=None) -> bytes:
        s = snapshot if snapshot is not None else ch.drive.state
        active = [f.as_dict() for f in s.faults if not f.acknowledged] if s.fault_active else []
        d = self._head(ch) | {
            "ts_unix_s": round(time.time(), 3),
            "time_s": round(s.time_s, 6),
            "nmt_state": ch.nmt(),
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

    def telemetry_payload(self, ch: AxisChannel, batch: list[dict]) -> bytes:
        c = ch.buffer.counters()
        d = self._head(ch) | {
            "rate_hz": self.settings.rate_hz,
            "seq_first": batch[0]["seq"],
            "samples_dropped": c["samples_dropped"],
            "samples": batch,
        }
        return json.dumps(d, separators=(",", ":")).encode()

    # -------------------------------------------------------------------------------- drive side
    def _observer(self, ch: AxisChannel) -> Callable:
        def on_event(event: str, state) -> None:  # runs under the drive's lock: cheap and non-blocking only
            ch.states.append(state)  # each transition gets its own state message (bounded: the newest 32)
            ch.state_dirty = True
            if event not in ("fault", "fault_cleared"):
                return
            rec = state.faults[0] if state.faults else None
            ev = {
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
            }
            if len(ch.events) >= ch.event_capacity:
                ch.events.popleft()
                ch.events_dropped += 1
            ch.events.append(ev)

        return on_event

    def _sample_loop(self) -> None:
        # (keeps the process' priority: a thread that takes the drive's lock must not be preempted holding it)
        period = 1.0 / self.settings.rate_hz
        nxt = time.perf_counter()
        while not self._stop.is_set():
            now = time.perf_counter()
            if now < nxt:
                self._stop.wait(nxt - now)
                continue
            late = int((now - nxt) / period)  # whole periods missed (machine stalled): counted, not faked
            if late:
                for ch in self.channels:
                    ch.sampler_late += late
                nxt += late * period
            for ch in self.channels:
                ch.buffer.add(sample_of(ch, ch.seq))
                ch.seq += 1
            nxt += period

    # -------------------------------------------------------------------------------- lifecycle
    def start(self) -> MqttService:
        short_gil_slices()
        for ch in self.channels:
            cb = self._observer(ch)
            ch.drive.add_observer(cb)
            self._observers.append((ch.drive, cb))
        self._thread = threading.Thread(target=self._run, name="virtualaxis-mqtt", daemon=True)
        self._thread.start()
        self._sampler = threading.Thread(target=self._sample_loop, name="virtualaxis-mqtt-sampler", daemon=True)
        self._sampler.start()
        return self

    def stop(self, timeout_s: float = 5.0) -> None:
        """Stop sampling, publish what is buffered when connected, send ``offline`` and disconnect."""
        self._stop.set()
        if self._sampler is not None:
            self._sampler.join(timeout=timeout_s)
        if self._thread is not None:
            self._thread.join(timeout=timeout_s)
        for drive, cb in self._observers:
            drive.remove_observer(cb)
        self._observers.clear()

    def _run(self) -> None:
        loop = asyncio.new_event_loop()
        self._loop = loop
        asyncio.set_event_loop(loop)
        try:
            loop.run_until_complete(asyncio.gather(*(self._axis_loop(ch) for ch in self.channels)))
        finally:
            loop.close()

    def _tls_context(self) -> ssl.SSLContext | None:
        st = self.settings
        if not st.tls:
            return None
        ctx = ssl.create_default_context(cafile=st.ca_file) if st.ca_file else ssl.create_default_context()
        if st.cert_file:
            ctx.load_cert_chain(st.cert_file, st.key_file)
        return ctx

    async def _axis_loop(self, ch: AxisChannel) -> None:
        import aiomqtt

        st = self.settings
        backoff = st.backoff_min_s
        tls = self._tls_context()
        while not self._stop.is_set():
            ch.connect_attempts += 1
            try:
                client = aiomqtt.Client(
                    st.host,
                    st.port,
                    username=st.username,
                    password=st.password,
                    identifier=f"virtualaxis-{st.machine}-{ch.name}",
                    will=aiomqtt.Will(self.topic(ch, "status"), self.will_payload(ch), qos=1, retain=True),
                    keepalive=st.keepalive_s,
                    timeout=st.publish_timeout_s,
                    tls_context=tls,
                    clean_session=True,
                )
                async with client:
                    ch.connects += 1
                    ch.connected = True
                    backoff = st.backoff_min_s
                    await self._session(client, ch)
                    return  # clean stop
            except aiomqtt.MqttError as exc:
                ch.last_error = str(exc)
            except OSError as exc:
                ch.last_error = str(exc)
            if ch.connected:
                ch.disconnects += 1
                ch.connected = False
                ch.state_dirty = True
            await self._sleep(backoff)
            backoff = min(backoff * 2.0, st.backoff_max_s)
        # stopped while the broker was away: nothing more can be sent

    async def _sleep(self, seconds: float) -> None:
        end = time.monotonic() + seconds
        while not self._stop.is_set() and time.monotonic() < end:
            await asyncio.sleep(min(0.05, max(0.0, end - time.monotonic())))

    async def _session(self, client, ch: AxisChannel) -> None:
        """Publish while connected; raises aiomqtt.MqttError when the connection is lost."""
        st = self.settings
        watcher = asyncio.ensure_future(self._watch(client))
        try:
            await client.publish(self.topic(ch, "status"), self.status_payload(ch, True), qos=1, retain=True)
            next_state = 0.0
            while True:
                stopping = self._stop.is_set()
                if watcher.done():
                    watcher.result()  # raises the disconnect
                while ch.events:
                    ev = ch.events[0]
                    payload = json.dumps(self._head(ch) | ev).encode()
                    await client.publish(self.topic(ch, "faults"), payload, qos=1)
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
                    await client.publish(self.topic(ch, "state"), self.state_payload(ch, snap), qos=1, retain=True)
                    if ch.states and ch.states[0] is snap:
                        ch.states.popleft()
                now = time.monotonic()
                if ch.state_dirty or now >= next_state or stopping:
                    ch.state_dirty = False  # (the current state last: the retained message is the newest)
                    await client.publish(self.topic(ch, "state"), self.state_payload(ch), qos=1, retain=True)
                    next_state = now + st.state_interval_s
                if stopping:
                    await client.publish(self.topic(ch, "status"), self.status_payload(ch, False), qos=1, retain=True)
                    return
                await asyncio.sleep(min(0.01, 1.0 / st.rate_hz))
        finally:
            watcher.cancel()

    @staticmethod
    async def _watch(client) -> None:
        """Ends with aiomqtt.MqttError when the connection drops (we subscribe to nothing)."""
        async for _ in client.messages:
            pass

    def stats(self) -> dict:
        return {
            ch.name: ch.buffer.counters()
            | {
                "connects": ch.connects,
                "disconnects": ch.disconnects,
                "batches_published": ch.batches_published,
                "events_published": ch.events_published,
                "events_dropped": ch.events_dropped,
                "sampler_late_samples": ch.sampler_late,
                "last_error": ch.last_error,
            }
            for ch in self.channels
        }


def machine_name_from(config_path: str | Path | None, default: str = "machine") -> str:
    """The machine name for topics when --machine is not given: the main axis config's file stem."""
    if config_path is None:
        return default
    stem = Path(config_path).stem
    name = re.sub(r"[^A-Za-z0-9_.\-]", "_", stem)
    return name or default

