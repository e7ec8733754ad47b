"""Sparkplug B 3.0 telemetry of the served axes (``serve --mqtt URL --sparkplug [GROUP]``).

The ``serve`` process is one Sparkplug **edge node** (group id ``GROUP``, default ``virtualaxis``; edge node id
= ``--machine``) and each axis one **device** (device id = the axis name). Topics::

    spBv1.0/<group>/NBIRTH/<edge node>            node birth: bdSeq, Node Control/Rebirth, Properties/*
    spBv1.0/<group>/NDEATH/<edge node>            node death: bdSeq (the MQTT will; also sent on a clean stop)
    spBv1.0/<group>/NCMD/<edge node>              subscribed: Node Control/Rebirth = true -> NBIRTH + DBIRTHs
    spBv1.0/<group>/DBIRTH/<edge node>/<axis>     every metric of the axis: name, alias, datatype, value, unit
    spBv1.0/<group>/DDATA/<edge node>/<axis>      changed metrics by alias only (report by exception)
    spBv1.0/<group>/DDEATH/<edge node>/<axis>     on a clean stop
    spBv1.0/<group>/DCMD/<edge node>/<axis>       subscribed: Fault Injection/Command (String, JSON)

Payloads are Sparkplug B protobuf messages (``sparkplug_proto/sparkplug_b.proto``, encoded with Google's
``protobuf``; ``pip install 'virtualaxis[sparkplug]'``). Sequence rules: ``bdSeq`` counts the connection
attempts (0..255, wrapping) and the NBIRTH carries the one of its CONNECT's will; ``seq`` is 0 on NBIRTH and
counts every NBIRTH / DBIRTH / NDATA / DDATA / DDEATH after it (0..255, wrapping).

The work is the plain MQTT publisher's (:class:`virtualaxis.services.mqtt.Publisher`: the same shared-memory
ring, sample buffer, counters and fault-command path); only the encoding and the session differ: one MQTT
connection for the edge node (its will is the NDEATH), MQTT 3.1.1 with a clean session.
"""

from __future__ import annotations

import asyncio
import json
import sys
import time
from dataclasses import dataclass

from virtualaxis.services.mqtt import (
    MqttSettingsError,
    PubChannel,
    Publisher,
    tcp_no_delay,
)
from virtualaxis.services.mqtt_presence import client_identifier

NAMESPACE = "spBv1.0"
DEFAULT_GROUP = "virtualaxis"
EXTRA = "sparkplug"  # pip install 'virtualaxis[sparkplug]'
REFUSALS_LOGGED = 100  # stderr lines about refused commands before they are only counted

# Sparkplug B data types (sparkplug_b.proto, DataType)
INT8, INT16, INT32, INT64, UINT8, UINT16, UINT32, UINT64, FLOAT, DOUBLE, BOOLEAN, STRING = range(1, 13)
DATATYPE_NAMES = {INT8: "Int8", INT16: "Int16", INT32: "Int32", INT64: "Int64", UINT8: "UInt8", UINT16: "UInt16",
                  UINT32: "UInt32", UINT64: "UInt64", FLOAT: "Float", DOUBLE: "Double", BOOLEAN: "Boolean",
                  STRING: "String"}


@dataclass(frozen=True)
class MetricDef:
    """One metric of a device (an axis) or of the edge node."""

    name: str
    datatype: int
    unit: str  # engineering unit ("" for none): the property engUnit in the birth
    source: str  # "sample": a telemetry sample's field; "state": the state fields; "counter"; "command"; "node"
    key: str  # the field of the sample / state / counters it comes from
    writable: bool = False  # accepted in DCMD / NCMD
    description: str = ""


#: the metrics of each axis (device), in alias order (alias = 1000 * (axis index + 1) + position)
DEVICE_METRICS: tuple[MetricDef, ...] = (
    MetricDef("Position", DOUBLE, "mm", "sample", "position_mm", description="position actual (0x6064)"),
    MetricDef("Following Error", DOUBLE, "um", "sample", "following_error_um", description="0x60F4"),
    MetricDef("Velocity", DOUBLE, "mm/min", "sample", "velocity_mm_min", description="velocity actual"),
    MetricDef("Speed", DOUBLE, "rpm", "sample", "speed_rpm", description="motor speed (velocity / lead)"),
    MetricDef("Current", DOUBLE, "A", "sample", "current_a", description="q current"),
    MetricDef("Torque", DOUBLE, "N.m", "sample", "torque_nm", description="torque actual (0x6077)"),
    MetricDef("State/NMT", STRING, "", "state", "nmt_state", description="NMT state of the CANopen node"),
    MetricDef("State/CiA402", STRING, "", "state", "cia402_state", description="CiA 402 state"),
    MetricDef("State/Mode", INT8, "", "state", "mode", description="mode of operation display (0x6061)"),
    MetricDef("State/Mode Name", STRING, "", "state", "mode_name"),
    MetricDef("State/Statusword", UINT16, "", "state", "statusword", description="0x6041"),
    MetricDef("State/Fault Active", BOOLEAN, "", "state", "fault_active"),
    MetricDef("State/Error Code", UINT16, "", "state", "error_code", description="0x603F"),
    MetricDef("State/Alarm Number", UINT32, "", "state", "alarm_number", description="0x2031"),
    MetricDef("State/Homed", BOOLEAN, "", "state", "homed"),
    MetricDef("State/Active Faults", STRING, "", "state", "active_faults",
              description="JSON list of the faults not yet acknowledged"),
    MetricDef("Telemetry/Samples Taken", UINT64, "", "counter", "samples_taken"),
    MetricDef("Telemetry/Samples Dropped", UINT64, "", "counter", "samples_dropped",
              description="samples lost while the broker was away (buffer full)"),
    MetricDef("Fault Injection/Command", STRING, "", "command", "command", writable=True,
              description="DCMD: a fault command, JSON as on the fault/set topic (needs --allow-fault-injection)"),
    MetricDef("Fault Injection/Result", STRING, "", "command", "result",
              description="JSON answer to each DCMD (ok, error, abort_code, active, id)"),
)

#: the metrics of the edge node (aliases 1..)
NODE_METRICS: tuple[MetricDef, ...] = (
    MetricDef("bdSeq", UINT64, "", "node", "bdseq", description="birth / death sequence of the connection"),
    MetricDef("Node Control/Rebirth", BOOLEAN, "", "node", "rebirth", writable=True,
              description="NCMD true: a new NBIRTH and DBIRTHs"),
    MetricDef("Properties/Software", STRING, "", "node", "software"),
    MetricDef("Properties/Axes", STRING, "", "node", "axes", description="JSON list of the devices (axes)"),
)

_RESULT = DEVICE_METRICS.index(next(m for m in DEVICE_METRICS if m.key == "result"))
_COMMAND = DEVICE_METRICS.index(next(m for m in DEVICE_METRICS if m.key == "command"))


def device_alias(axis_index: int, position: int) -> int:
    """The alias of metric ``position`` of ``DEVICE_METRICS`` on axis ``axis_index`` (unique in the edge node)."""
    return 1000 * (axis_index + 1) + position


def metric_table_markdown() -> str:
    """The device and node metrics as a Markdown table (docs/side-channels.md shows it)."""
    rows = ["| metric | alias | datatype | unit | in | description |", "| --- | --- | --- | --- | --- | --- |"]
    for i, m in enumerate(NODE_METRICS):
        where = "NBIRTH, NCMD" if m.writable else ("NBIRTH, NDEATH" if m.key == "bdseq" else "NBIRTH")
        rows.append(f"| {m.name} | {i + 1} | {DATATYPE_NAMES[m.datatype]} | {m.unit} | {where} | {m.description} |")
    for i, m in enumerate(DEVICE_METRICS):
        where = "DBIRTH, DCMD" if m.writable else "DBIRTH, DDATA"
        rows.append(f"| {m.name} | 1000·(n+1)+{i} | {DATATYPE_NAMES[m.datatype]} | {m.unit} | {where} | "
                    f"{m.description} |")
    return "\n".join(rows) + "\n"


def check_available() -> None:
    """Raise MqttSettingsError naming the extra when the protobuf runtime is missing or too old."""
    try:
        from virtualaxis.services.sparkplug_proto import sparkplug_b_pb2  # noqa: F401
    except Exception as exc:  # noqa: BLE001 - ImportError, or protobuf's VersionError of an old runtime
        raise MqttSettingsError(
            f"--sparkplug needs the protobuf package (>= 7.35): pip install 'virtualaxis[{EXTRA}]' "
            f"({type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''})") from None


# ---------------------------------------------------------------------------------------------- payloads
def _pb():
    from virtualaxis.services.sparkplug_proto import sparkplug_b_pb2

    return sparkplug_b_pb2


def _now_ms() -> int:
    return int(time.time() * 1000)


def _value(m: MetricDef, raw) -> object:
    """The metric's value from its source field (state fields are JSON-ready: error_code is a hex string)."""
    if m.key == "error_code" and isinstance(raw, str):
        return int(raw, 16)
    if m.key == "active_faults":
        return json.dumps(raw, separators=(",", ":"))
    return raw


def _set_value(metric, datatype: int, value) -> None:
    if value is None:
        metric.is_null = True
    elif datatype in (INT8, INT16, INT32):
        metric.int_value = int(value) & 0xFFFFFFFF  # (two's complement in the uint32 field, as the spec says)
    elif datatype in (UINT8, UINT16, UINT32):
        metric.int_value = int(value)
    elif datatype in (INT64, UINT64):
        metric.long_value = int(value) & 0xFFFFFFFFFFFFFFFF
    elif datatype == FLOAT:
        metric.float_value = float(value)
    elif datatype == DOUBLE:
        metric.double_value = float(value)
    elif datatype == BOOLEAN:
        metric.boolean_value = bool(value)
    else:
        metric.string_value = str(value)


def _add_unit(metric, unit: str) -> None:
    if unit:
        metric.properties.keys.append("engUnit")
        pv = metric.properties.values.add()
        pv.type = STRING
        pv.string_value = unit


def _birth_metric(payload, m: MetricDef, alias: int, value, ts_ms: int) -> None:
    metric = payload.metrics.add()
    metric.name = m.name
    metric.alias = alias
    metric.timestamp = ts_ms
    metric.datatype = m.datatype
    _set_value(metric, m.datatype, value)
    _add_unit(metric, m.unit)


def node_death_payload(bdseq: int) -> bytes:
    """The NDEATH (the MQTT will of the connection and the last message of a clean stop)."""
    pb = _pb()
    p = pb.Payload()
    p.timestamp = _now_ms()
    metric = p.metrics.add()
    metric.name = "bdSeq"
    metric.datatype = UINT64
    metric.long_value = bdseq
    return p.SerializeToString()


def decode_command(payload: bytes) -> tuple[list[tuple[str | None, int | None, object]], str | None]:
    """An NCMD / DCMD payload as ``[(name, alias, value)]``, or ``([], reason)`` when it is no Sparkplug
    payload."""
    pb = _pb()
    p = pb.Payload()
    try:
        p.ParseFromString(bytes(payload))
    except Exception as exc:  # noqa: BLE001 - protobuf's DecodeError and friends
        return [], f"not a Sparkplug B payload ({type(exc).__name__})"
    out = []
    for metric in p.metrics:
        which = metric.WhichOneof("value")
        value = None if which is None or metric.is_null else getattr(metric, which)
        out.append((metric.name if metric.HasField("name") else None,
                    metric.alias if metric.HasField("alias") else None, value))
    if not out:
        return [], "no metric in the payload"
    return out, None


# ---------------------------------------------------------------------------------------------- the edge node
class SparkplugPublisher(Publisher):
    """The publisher process' work in Sparkplug B: one edge node connection, a device per axis."""

    def __init__(self, settings, axes, ring):
        super().__init__(settings, axes, ring)
        self.group = settings.sparkplug_group or DEFAULT_GROUP
        self.node = settings.machine
        self.bdseq = -1  # incremented before each CONNECT: 0 for the first
        self.seq = 0
        self.rebirths = 0
        self.refusals = 0
        # per axis: the last value reported of each metric (report by exception), reset by each birth
        self._last: list[dict[int, object]] = [{} for _ in self.channels]
        self._last_counters_at = [0.0 for _ in self.channels]
        self._rebirth: asyncio.Event | None = None  # created in the event loop
        self._last_line = ""  # the connection state last said on stderr (each change once)

    # -------------------------------------------------------------------------------- topics
    def node_topic(self, kind: str) -> str:
        return f"{NAMESPACE}/{self.group}/{kind}/{self.node}"

    def device_topic(self, kind: str, ch: PubChannel) -> str:
        return f"{NAMESPACE}/{self.group}/{kind}/{self.node}/{ch.name}"

    def _say(self, text: str, force: bool = False) -> None:
        """One stderr line per change of the connection's state (the same failure again is not repeated)."""
        key = text.split(";")[0].split(" (")[0]
        if force or key != self._last_line:
            print(f"mqtt: sparkplug edge node {self.group}/{self.node}: {text}", file=sys.stderr, flush=True)
        self._last_line = "" if force else key

    def _next_seq(self) -> int:
        s = self.seq
        self.seq = (self.seq + 1) % 256
        return s

    # -------------------------------------------------------------------------------- payloads
    def node_birth_payload(self) -> bytes:
        pb = _pb()
        from virtualaxis import __version__

        ts = _now_ms()
        p = pb.Payload()
        p.timestamp = ts
        self.seq = 0
        p.seq = self._next_seq()
        values = {"bdseq": self.bdseq, "rebirth": False, "software": f"virtualaxis {__version__}",
                  "axes": json.dumps([ch.name for ch in self.channels])}
        for i, m in enumerate(NODE_METRICS):
            _birth_metric(p, m, i + 1, values[m.key], ts)
        return p.SerializeToString()

    def _source_values(self, ch: PubChannel, sample: dict | None, state: dict | None,
                       counters: bool = False) -> dict[int, object]:
        """position in DEVICE_METRICS -> value, for the metrics of the sources given."""
        out: dict[int, object] = {}
        counts = ch.buffer.counters() if counters else {}
        for i, m in enumerate(DEVICE_METRICS):
            if m.source == "sample" and sample is not None:
                out[i] = sample[m.key]
            elif m.source == "state" and state is not None and m.key in state:
                out[i] = _value(m, state[m.key])
            elif m.source == "counter" and counters:
                out[i] = counts[m.key]
        return out

    def device_birth_payload(self, ch: PubChannel) -> bytes:
        pb = _pb()
        ts = _now_ms()
        p = pb.Payload()
        p.timestamp = ts
        p.seq = self._next_seq()
        newest = ch.buffer.peek(len(ch.buffer))[-1:] or [None]
        values = self._source_values(ch, newest[0], ch.current, counters=True)
        values[_COMMAND] = ""
        last = self._last[ch.index]
        values = {i: last.get(i) for i in range(len(DEVICE_METRICS))} | values  # (a rebirth: the values known)
        last.clear()
        for i, m in enumerate(DEVICE_METRICS):
            value = values.get(i)
            if value is None and m.datatype == STRING:
                value = ""  # (no result yet)
            _birth_metric(p, m, device_alias(ch.index, i), value, ts)
            last[i] = value
        return p.SerializeToString()

    def device_data_payload(self, ch: PubChannel, changes: list[tuple[int, object, int]]) -> bytes:
        """DDATA of ``changes`` = ``[(position in DEVICE_METRICS, value, timestamp ms)]``: alias only."""
        pb = _pb()
        p = pb.Payload()
        p.timestamp = _now_ms()
        p.seq = self._next_seq()
        for i, value, ts in changes:
            metric = p.metrics.add()
            metric.alias = device_alias(ch.index, i)
            metric.timestamp = ts
            _set_value(metric, DEVICE_METRICS[i].datatype, value)
        return p.SerializeToString()

    def device_death_payload(self) -> bytes:
        pb = _pb()
        p = pb.Payload()
        p.timestamp = _now_ms()
        p.seq = self._next_seq()
        return p.SerializeToString()

    def _changes(self, ch: PubChannel, values: dict[int, object], ts_ms: int,
                 out: list[tuple[int, object, int]]) -> None:
        last = self._last[ch.index]
        for i, value in values.items():
            if last.get(i, _UNSET) != value:
                last[i] = value
                out.append((i, value, ts_ms))

    # -------------------------------------------------------------------------------- the loop
    async def _main(self) -> None:
        self._work = [asyncio.Event() for _ in self.channels]
        self._tick = asyncio.Event()
        self._rebirth = asyncio.Event()
        drainer = asyncio.ensure_future(self._drain_loop())
        try:
            await self._node_loop()
        finally:
            drainer.cancel()
            try:
                await drainer
            except asyncio.CancelledError:
                pass
            self.drain()

    async def _wait_any_work(self) -> None:
        waits = [asyncio.ensure_future(ev.wait()) for ev in self._work]
        waits.append(asyncio.ensure_future(self._rebirth.wait()))
        try:
            await asyncio.wait(waits, timeout=0.05, return_when=asyncio.FIRST_COMPLETED)
        finally:
            for w in waits:
                w.cancel()
        for ev in self._work:
            ev.clear()

    async def _node_loop(self) -> None:
        import aiomqtt

        st = self.settings
        backoff = st.backoff_min_s
        tls = self._tls_context()
        while not self._stop.is_set():
            self.bdseq = (self.bdseq + 1) % 256
            for ch in self.channels:
                ch.connect_attempts += 1
                self.export(ch)
            accepted = False
            try:
                client = aiomqtt.Client(
                    st.host, st.port, username=st.username, password=st.password,
                    identifier=client_identifier(st.machine, "sparkplug", self.instance_id),
                    will=aiomqtt.Will(self.node_topic("NDEATH"), node_death_payload(self.bdseq), qos=1,
                                      retain=False),
                    keepalive=st.keepalive_s, timeout=st.publish_timeout_s, tls_context=tls,
                    protocol=aiomqtt.ProtocolVersion.V311, clean_session=True,
                )
                async with client:
                    accepted = True
                    tcp_no_delay(client)
                    for ch in self.channels:
                        ch.connects += 1
                        ch.connected = True
                        self.export(ch)
                    self._say(f"connected to {st.host}:{st.port} (MQTT 3.1.1, bdSeq {self.bdseq})", force=True)
                    backoff = st.backoff_min_s
                    await self._session(client)
                    self._say(f"disconnected from {st.host}:{st.port} (stop; NDEATH bdSeq {self.bdseq} sent)",
                              force=True)
                    return
            except aiomqtt.MqttError as exc:
                err = str(exc)
            except OSError as exc:
                err = str(exc)
            for ch in self.channels:
                ch.last_error = err
                if ch.connected:
                    ch.disconnects += 1
                    ch.connected = False
                self.export(ch)
            if not self._stop.is_set():
                what = "connection lost" if accepted else "cannot connect"
                self._say(f"{what} to {st.host}:{st.port}: {err.strip() or 'no reason given'}; retrying with "
                          f"backoff (next in {backoff:g} s)")
            await self._sleep(backoff)
            backoff = min(backoff * 2.0, st.backoff_max_s)

    async def _births(self, client) -> None:
        await client.publish(self.node_topic("NBIRTH"), self.node_birth_payload(), qos=0)
        for ch in self.channels:
            await client.publish(self.device_topic("DBIRTH", ch), self.device_birth_payload(ch), qos=0)
            self._last_counters_at[ch.index] = time.monotonic()

    async def _session(self, client) -> None:
        """Publish while connected; raises aiomqtt.MqttError when the connection is lost."""
        await client.subscribe(self.node_topic("NCMD"), qos=0)
        await client.subscribe(f"{NAMESPACE}/{self.group}/DCMD/{self.node}/+", qos=0)
        watcher = asyncio.ensure_future(self._watch_commands(client))
        try:
            while any(ch.current is None for ch in self.channels) and not self._stop.is_set():
                await asyncio.sleep(0.01)  # serve forwards each axis' state right at start
            if self._stop.is_set() and any(ch.current is None for ch in self.channels):
                return
            self._rebirth.clear()
            await self._births(client)
            while True:
                stopping = self._stop.is_set()
                if stopping:
                    self.drain()
                if watcher.done():
                    watcher.result()  # raises the disconnect
                if self._rebirth.is_set():
                    self._rebirth.clear()
                    self.rebirths += 1
                    await self._births(client)
                for ch in self.channels:
                    await self._publish_device(client, ch, stopping)
                if stopping:
                    for ch in self.channels:
                        await client.publish(self.device_topic("DDEATH", ch), self.device_death_payload(), qos=0)
                    await client.publish(self.node_topic("NDEATH"), node_death_payload(self.bdseq), qos=1)
                    for ch in self.channels:
                        self.export(ch)
                    return
                for ch in self.channels:
                    self.export(ch)
                await self._wait_any_work()
        finally:
            watcher.cancel()

    async def _publish_device(self, client, ch: PubChannel, stopping: bool) -> None:
        st = self.settings
        topic = self.device_topic("DDATA", ch)
        changes: list[tuple[int, object, int]] = []
        # command results: one DDATA each (a host sees every answer, none coalesced)
        while ch.results:
            res = ch.results[0]
            await client.publish(topic, self.device_data_payload(ch, [(_RESULT, json.dumps(res), _now_ms())]), qos=0)
            self._last[ch.index][_RESULT] = json.dumps(res)
            with self._lock:
                if ch.results and ch.results[0] is res:
                    ch.results.popleft()
        # drive events: the state of each (a fault and its transition in order), then the fault events counted
        while ch.states:
            snap = ch.states[0]
            self._changes(ch, self._source_values(ch, None, snap), _now_ms(), changes)
            with self._lock:
                if ch.states and ch.states[0] is snap:
                    ch.states.popleft()
        while ch.events:
            with self._lock:
                if ch.events:
                    ch.events.popleft()
                    ch.events_published += 1  # (the fault shows in State/*: Fault Active, Error Code, Active Faults)
        if ch.current is not None:
            self._changes(ch, self._source_values(ch, None, ch.current), _now_ms(), changes)
        if changes:  # a state change goes out at once, before the samples that follow it
            await client.publish(topic, self.device_data_payload(ch, changes), qos=0)
            changes = []
        # samples: each batch one DDATA with the metrics that changed from sample to sample
        while len(ch.buffer) >= st.batch_size or (stopping and len(ch.buffer)):
            batch = ch.buffer.peek(st.batch_size)
            now_ms = _now_ms()
            t_last = batch[-1]["t_s"]
            for sample in batch:
                ts = now_ms - max(0, round((t_last - sample["t_s"]) * 1000))
                values = {i: sample[m.key] for i, m in enumerate(DEVICE_METRICS) if m.source == "sample"}
                self._changes(ch, values, ts, changes)
            if changes:
                await client.publish(topic, self.device_data_payload(ch, changes), qos=0)
                changes = []
            ch.buffer.commit(batch)
            ch.batches_published += 1
        now = time.monotonic()
        if now - self._last_counters_at[ch.index] >= st.state_interval_s or stopping:
            self._last_counters_at[ch.index] = now
            self._changes(ch, self._source_values(ch, None, None, counters=True), _now_ms(), changes)
            if changes:
                await client.publish(topic, self.device_data_payload(ch, changes), qos=0)

    # -------------------------------------------------------------------------------- commands
    def _refuse(self, where: str, reason: str, ch: PubChannel | None = None) -> None:
        """A command that is not applied: one stderr line (the first REFUSALS_LOGGED), and on a device its
        ``Fault Injection/Result``."""
        self.refusals += 1
        if self.refusals <= REFUSALS_LOGGED:
            more = " (further refusals are not logged)" if self.refusals == REFUSALS_LOGGED else ""
            print(f"warning: sparkplug: {where}: command refused: {reason}{more}", file=sys.stderr, flush=True)
        if ch is not None:
            with self._lock:
                ch.results.append({"ok": False, "error": reason})
            self._work[ch.index].set()

    async def _watch_commands(self, client) -> None:
        ncmd = self.node_topic("NCMD")
        dcmd = f"{NAMESPACE}/{self.group}/DCMD/{self.node}/"
        by_name = {ch.name: ch for ch in self.channels}
        async for message in client.messages:
            topic = str(message.topic)
            try:
                if topic == ncmd:
                    self.on_node_command(message.payload)
                elif topic.startswith(dcmd):
                    ch = by_name.get(topic[len(dcmd):])
                    if ch is None:
                        self._refuse(topic, f"no device {topic[len(dcmd):]!r} on this edge node")
                    else:
                        self.on_device_command(ch, message.payload)
            except Exception as exc:  # noqa: BLE001 - a bad message never takes the publisher down
                self._refuse(topic, f"internal error: {type(exc).__name__}")

    def on_node_command(self, payload) -> None:
        metrics, problem = decode_command(payload)
        if problem is not None:
            self._refuse("NCMD", problem)
            return
        for name, alias, value in metrics:
            if name == "Node Control/Rebirth" or (name is None and alias == 1 + [m.key for m in NODE_METRICS]
                                                 .index("rebirth")):
                if value is True:
                    self._rebirth.set()
                else:
                    self._refuse("NCMD", f"Node Control/Rebirth: must be Boolean true (got {value!r})")
            else:
                self._refuse("NCMD", f"metric {name if name is not None else alias!r}: not writable (writable: "
                                     "Node Control/Rebirth)")

    def on_device_command(self, ch: PubChannel, payload) -> None:
        metrics, problem = decode_command(payload)
        where = f"DCMD {ch.name}"
        if problem is not None:
            self._refuse(where, problem, ch)
            return
        command_alias = device_alias(ch.index, _COMMAND)
        for name, alias, value in metrics:
            if name == DEVICE_METRICS[_COMMAND].name or (name is None and alias == command_alias):
                if not isinstance(value, str):
                    self._refuse(where, f"{DEVICE_METRICS[_COMMAND].name}: must be a String (JSON as on fault/set)",
                                 ch)
                else:
                    self.on_command(ch, value.encode("utf-8", "surrogatepass"))
            else:
                writable = ", ".join(m.name for m in DEVICE_METRICS if m.writable)
                self._refuse(where, f"metric {name if name is not None else alias!r}: not writable (writable: "
                                    f"{writable})", ch)


_UNSET = object()
