"""The side-channel options of ``virtualaxis serve`` (--modbus, --mqtt, ...) and their start / stop.

``serve`` calls :func:`add_arguments` on its parser, :func:`prepare` before it opens the bus (bad options
end as a CLI error naming the option, the file or the variable) and :meth:`SideChannels.start` /
:meth:`SideChannels.stop` around its run.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

# pymodbus / aiomqtt are imported only when a side channel is requested (every CLI command imports this module)


#: --telemetry-rate [Hz], --telemetry-batch and --telemetry-buffer [samples] when not given
TELEMETRY_DEFAULTS = {"rate": 100.0, "batch": 10, "buffer": 1000}


def add_arguments(p) -> None:
    g = p.add_argument_group("side channels (docs/side-channels.md, docs/modbus-map.md)")
    g.add_argument(
        "--modbus",
        nargs="?",
        const="127.0.0.1:5020",
        default=None,
        metavar="HOST:PORT",
        help="serve the Modbus TCP map (unit id = node id); default off, 127.0.0.1:5020 without a value",
    )
    g.add_argument("--modbus-writable", action="store_true", help="accept Modbus writes (else exception 04)")
    g.add_argument("--mqtt", default=None, metavar="URL", help="publish MQTT telemetry to mqtt://HOST:PORT or mqtts://")
    g.add_argument("--machine", default=None, help="machine name in the MQTT topics (default: the config's file stem)")
    g.add_argument("--sparkplug", nargs="?", const="virtualaxis", default=None, metavar="GROUP",
                   help="with --mqtt: publish Sparkplug B (group GROUP, default virtualaxis; edge node = --machine) "
                        "instead of the JSON topics")
    g.add_argument(
        "--mqtt-credentials",
        default=None,
        metavar="FILE",
        help="TOML file with username / password / ca_file / cert_file / key_file (or VIRTUALAXIS_MQTT_* variables)",
    )
    # (defaults applied in prepare(): None means "not given", which a telemetry option without --mqtt must be)
    g.add_argument("--telemetry-rate", type=float, default=None, metavar="HZ",
                   help=f"telemetry sample rate, > 0 and at most 1000 (default {TELEMETRY_DEFAULTS['rate']:g})")
    g.add_argument("--telemetry-batch", type=int, default=None, metavar="N",
                   help=f"samples per telemetry message ({TELEMETRY_DEFAULTS['batch']})")
    g.add_argument("--telemetry-buffer", type=int, default=None, metavar="N",
                   help=f"samples kept per axis while the broker is away ({TELEMETRY_DEFAULTS['buffer']})")
    g.add_argument("--http", nargs="?", const="127.0.0.1:8080", default=None, metavar="HOST:PORT",
                   help="serve the live drive page (docs/live-page.md); default off, 127.0.0.1:8080 without a value")
    g.add_argument("--http-writable", action="store_true",
                   help="the live page may write objects (as SDO downloads) and, with --allow-fault-injection, "
                        "inject faults; read-only otherwise")
    g.add_argument("--opcua", nargs="?", const="127.0.0.1:4840", default=None, metavar="HOST:PORT",
                   help="serve OPC UA (docs/opcua.md; needs the opcua extra); default off, 127.0.0.1:4840 without a "
                        "value")
    g.add_argument("--opcua-writable", action="store_true", help="accept OPC UA writes of the Parameters nodes")
    g.add_argument("--opcua-users", default=None, metavar="FILE",
                   help="TOML file with a [users] table (name = \"password\"): username login instead of anonymous")
    g.add_argument("--opcua-cert", default=None, metavar="FILE",
                   help="server certificate (with --opcua-key): Basic256Sha256 SignAndEncrypt only")
    g.add_argument("--opcua-key", default=None, metavar="FILE", help="private key of --opcua-cert")


@dataclass
class SideChannels:
    """The services requested on the command line (either may be None)."""

    modbus_address: tuple[str, int] | None = None
    modbus_writable: bool = False
    mqtt: Any = None  # MqttSettings
    modbus: Any = None  # ModbusService
    telemetry: Any = None  # MqttService
    lines: list[str] = field(default_factory=list)
    gate: Any = None  # CycleGate: the periodic jobs run in the gap after a SYNC's PDOs (cycle_gate.py)
    http_address: tuple[str, int] | None = None
    http_writable: bool = False
    http: Any = None  # LivePageService
    frame_log: Any = None  # FrameLog of the live page (EMCY frames, SDO aborts sent)
    bus: Any = None  # the bus as wrapped (its stats(): bus load on the live page)
    opcua_settings: Any = None  # OpcuaSettings
    opcua: Any = None  # OpcuaService

    @property
    def enabled(self) -> bool:
        return (self.modbus_address is not None or self.mqtt is not None or self.opcua_settings is not None
                or self.http_address is not None)

    def wrap_bus(self, bus):
        """With a side channel on: ``bus`` wrapped so that PDO sends mark the cycle gate (else ``bus``)."""
        if not self.enabled:
            return bus
        from virtualaxis.services.cycle_gate import CycleGate, GateBus

        self.gate = CycleGate()
        if self.http_address is not None:
            from virtualaxis.services.http.frames import FrameLog, FrameLogBus

            self.frame_log = FrameLog()
            bus = FrameLogBus(bus, self.frame_log)
        self.bus = GateBus(bus, self.gate)
        return self.bus

    def start(self, axes, run_in_gap=None) -> None:
        """Start for the runtime's ``axes`` (``AxisNode``: name, node_id, drive, slave, injection);
        ``run_in_gap``: the runtime's ``run_in_gap`` (the live page's state messages are made by its thread; the
        Modbus register images stay in their own thread: built in the runtime thread they changed nothing
        measurable, BENCHMARKS.md)."""
        if self.modbus_address is not None:
            from virtualaxis.services.modbus import ModbusService
            from virtualaxis.services.modbus_map import AxisLink

            host, port = self.modbus_address
            links = [AxisLink(a.drive, a.node_id, injector=getattr(a, "injection", None)) for a in axes]
            self.modbus = ModbusService(links, host=host, port=port, writable=self.modbus_writable,
                                        gate=self.gate).start()
            ids = ", ".join(str(a.node_id) for a in axes)
            rw = "read/write" if self.modbus_writable else "read-only"
            self.lines.append(f"modbus: {host}:{self.modbus.bound_port} ({rw}), unit ids {ids}")
        if self.mqtt is not None:
            from virtualaxis.services.mqtt import MqttService

            st = self.mqtt
            chans = [(a.name, a.node_id, a.drive, _nmt_getter(a), getattr(a, "injection", None)) for a in axes]
            self.telemetry = MqttService(st, chans, gate=self.gate).start()
            scheme = "mqtts" if st.tls else "mqtt"
            topics = (f"Sparkplug B spBv1.0/{st.sparkplug_group}/<type>/{st.machine}[/<axis>]"
                      if st.sparkplug_group is not None else f"topics virtualaxis/{st.machine}/<axis>/...")
            self.lines.append(f"mqtt: {scheme}://{st.host}:{st.port}, {topics}, telemetry {st.rate_hz:g} Hz in "
                              f"batches of {st.batch_size}")

        if self.http_address is not None:
            from virtualaxis.services.http import AxisPage, LivePageService

            host, port = self.http_address
            pages = [AxisPage(a.name, a.node_id, a.drive, a.slave, getattr(a, "injection", None), _nmt_getter(a))
                     for a in axes]
            self.http = LivePageService(pages, host=host, port=port, writable=self.http_writable, bus=self.bus,
                                        frame_log=self.frame_log, gate=self.gate, run_in_gap=run_in_gap).start()
            rw = "objects writable" if self.http_writable else "read-only"
            shown = f"[{host}]" if ":" in host else host
            self.lines.append(f"http: live page at http://{shown}:{self.http.bound_port}/ ({rw})")

        if self.opcua_settings is not None:
            from virtualaxis.services.opcua import AxisSource, OpcuaService

            st = self.opcua_settings
            sources = [AxisSource(a.name, a.node_id, a.drive, _nmt_getter(a), getattr(a, "injection", None))
                       for a in axes]
            self.opcua = OpcuaService(st, sources, gate=self.gate).start()
            access = "read/write parameters" if st.writable else "read-only"
            who = "username/password" if st.users else "anonymous"
            sec = "Basic256Sha256 SignAndEncrypt" if st.cert_file else "no security"
            self.lines.append(f"opcua: {self.opcua.url} ({access}, {who}, {sec}), objects VirtualAxis/<axis>")

    def stop(self) -> None:
        if self.http is not None:
            self.http.stop()
        if self.opcua is not None:
            self.opcua.stop()
        if self.telemetry is not None:
            self.telemetry.stop()
        if self.modbus is not None:
            self.modbus.stop()

    def stats(self) -> dict:
        out: dict = {}
        if self.modbus is not None:
            out["modbus"] = self.modbus.stats()
        if self.telemetry is not None:
            out["mqtt"] = self.telemetry.stats()
        if self.http is not None:
            out["http"] = self.http.stats()
        if self.opcua is not None:
            out["opcua"] = self.opcua.stats()
        if self.gate is not None:
            out["cycle_gate"] = self.gate.stats()
        return out


def _nmt_getter(axis):
    slave = getattr(axis, "slave", None)
    if slave is None:
        return None
    return lambda: getattr(slave.nmt_state, "name", str(slave.nmt_state)).replace("_", "-")


def prepare(args, main_config) -> SideChannels:
    """Validate the options (raises ValueError with a message naming the option, file or variable)."""
    sc = SideChannels()
    if args.modbus is not None:
        from virtualaxis.services.modbus import check_listen, parse_host_port
    if args.mqtt is not None:
        from virtualaxis.services.mqtt import load_credentials, machine_name_from, parse_mqtt_url
    if args.modbus is not None:
        sc.modbus_address = parse_host_port(args.modbus)
        check_listen(*sc.modbus_address)
        sc.modbus_writable = args.modbus_writable
    elif args.modbus_writable:
        raise ValueError("--modbus-writable needs --modbus")
    telemetry = {"--telemetry-rate": getattr(args, "telemetry_rate", None),
                 "--telemetry-batch": getattr(args, "telemetry_batch", None),
                 "--telemetry-buffer": getattr(args, "telemetry_buffer", None)}
    if args.machine is not None and not args.machine.strip():
        raise ValueError("--machine: empty name; leave the option out for the config's name")
    if args.mqtt is not None:
        machine = args.machine or machine_name_from(main_config)
        st = parse_mqtt_url(args.mqtt, machine)
        rate, batch, buffer = telemetry.values()
        st.rate_hz = TELEMETRY_DEFAULTS["rate"] if rate is None else rate
        st.batch_size = TELEMETRY_DEFAULTS["batch"] if batch is None else batch
        st.buffer_samples = TELEMETRY_DEFAULTS["buffer"] if buffer is None else buffer
        st.sparkplug_group = getattr(args, "sparkplug", None)
        if st.sparkplug_group is not None:
            from virtualaxis.services.sparkplug import check_available

            check_available()
        load_credentials(st, args.mqtt_credentials)
        st.validate()
        sc.mqtt = st
    elif args.mqtt_credentials or args.machine or getattr(args, "sparkplug", None) is not None:
        raise ValueError("--machine / --mqtt-credentials / --sparkplug need --mqtt")
    elif given := [opt for opt, value in telemetry.items() if value is not None]:
        raise ValueError(f"{' / '.join(given)} need(s) --mqtt (the telemetry is published over MQTT)")
    if args.http is not None:
        from virtualaxis.services.http.server import check_listen, parse_host_port

        sc.http_address = parse_host_port(args.http)
        check_listen(*sc.http_address)
        sc.http_writable = args.http_writable
    elif args.http_writable:
        raise ValueError("--http-writable needs --http")
    if getattr(args, "opcua", None) is not None or any(
            getattr(args, k, None) for k in ("opcua_writable", "opcua_users", "opcua_cert", "opcua_key")):
        from virtualaxis.services.opcua import prepare as prepare_opcua

        sc.opcua_settings = prepare_opcua(args)
    return sc


__all__ = ["SideChannels", "add_arguments", "prepare"]
