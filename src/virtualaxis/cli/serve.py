"""``virtualaxis serve``: serve one or more CiA 402 axes on a CAN bus until interrupted.

    virtualaxis serve --config configs/seed000-hust.toml --can socketcan:vcan0 --node-id 1
    virtualaxis serve --can udp_multicast:239.74.163.2 --axis X=1:configs/seed000-hust.toml \
        --axis Y=2:configs/seed000-hust.toml --lockstep

Prints one ``ready:`` line when the axes have booted, then a status line per axis every
``--status-interval`` seconds (state, position, following error, overruns); ``--json`` writes the final
statistics. Real-time pacing by default; ``--lockstep`` advances the plants only on SYNC.
"""

from __future__ import annotations

import json
import signal
import sys
import threading
import time
from pathlib import Path


def register(sub) -> None:
    p = sub.add_parser("serve", help="serve CiA 402 drive(s) on a CAN bus (socketcan:vcan0, udp_multicast:...)")
    p.add_argument(
        "--config",
        default=None,
        help="axis config TOML of the main axis (default: configs/seed000-hust.toml)",
    )
    p.add_argument("--can", default="socketcan:vcan0", help="bus INTERFACE:CHANNEL (default socketcan:vcan0)")
    p.add_argument("--node-id", type=int, default=None,
                   help="node id of the main axis (default 1; with --axis, the main axis is served only with --config)")
    p.add_argument(
        "--axis",
        action="append",
        default=[],
        metavar="NAME=ID:CONFIG",
        help="a (further) axis on the same bus, e.g. X=1:configs/seed000-hust.toml (repeatable)",
    )
    p.add_argument("--lockstep", action="store_true", help="advance the plants only on SYNC (deterministic)")
    p.add_argument("--stall-s", type=float, default=None, metavar="S",
                   help="lockstep: wall time one SYNC's cycles may take before the node counts as stalled (then "
                        "'healthy' is false; default 1.0)")
    p.add_argument("--allow-fault-injection", action="store_true",
                   help="accept fault injection (objects 0x5FF0.., `virtualaxis fault`, Modbus 40600.., MQTT "
                        "fault/set); refused otherwise")
    p.add_argument("--eds", default=None, help="EDS file (default eds/virtualaxis.eds)")
    p.add_argument("--duration", type=float, default=None, help="stop after this many seconds")
    p.add_argument("--status-interval", type=float, default=5.0, help="seconds between status lines (0: none)")
    p.add_argument("--json", default=None, help="write final statistics to this JSON file")
    p.add_argument("--force", action="store_true", help="overwrite an existing --json / --latency-probe file")
    p.add_argument(
        "--bitrate",
        type=int,
        default=1_000_000,
        metavar="BIT_S",
        help="emulated CAN bit rate: frame times, arbitration by identifier, bus load in the status and JSON "
        "(default 1000000; 0: off, frames go out as fast as the host bus takes them)",
    )
    p.add_argument(
        "--rt-priority",
        type=int,
        default=0,
        metavar="N",
        help="run the process with SCHED_FIFO priority N (1..99; needs the right to do so; 0: off)",
    )
    p.add_argument(
        "--cpu-latency-us",
        type=int,
        default=None,
        metavar="US",
        help="hold a CPU wake-up latency bound through /dev/cpu_dma_latency while serving (0: idle CPUs poll "
        "instead of sleeping; what cyclictest and real-time hosts do; needs the right to open the file)",
    )
    p.add_argument("--latency-probe", default=None, metavar="FILE",
                   help="benchmarks: record SYNC receive / PDO send timestamps into FILE (a NumPy archive; the name "
                        "must end in .npz) at stop")
    from virtualaxis.services.serve_options import add_arguments as add_side_channel_arguments

    add_side_channel_arguments(p)  # --modbus, --mqtt, ... (virtualaxis.services)
    p.set_defaults(func=run)


def run(args) -> int:
    from virtualaxis.cli.main import CliError
    from virtualaxis.config import ConfigError, load_axis_config
    from virtualaxis.drive.core import DEFAULT_EDS
    from virtualaxis.runtime import AxisNode, AxisSpec, BusOpenError, Runtime, open_bus
    from virtualaxis.runtime.axes import DEFAULT_CONFIG

    eds = Path(args.eds) if args.eds else DEFAULT_EDS
    _check_inputs(args, eds)
    if args.node_id is not None and args.axis and args.config is None:
        raise CliError(f"--node-id {args.node_id} is the main axis's node id, and with --axis but no --config "
                       "there is no main axis (only the --axis axes are served): add --config FILE for a main "
                       "axis on that node, or give each axis its node id in --axis NAME=ID:CONFIG")
    if args.node_id is None:
        args.node_id = 1
    if not 1 <= args.node_id <= 127:
        raise CliError(f"--node-id must be 1..127 (got {args.node_id})")
    if args.duration is not None and not 0 < args.duration < 1e9:  # (also nan and inf: "forever" is no --duration)
        raise CliError(f"--duration must be a finite number of seconds > 0 (got {args.duration}); leave it out to "
                       "serve until interrupted")
    if not 0 <= args.status_interval < 1e9:
        raise CliError(f"--status-interval must be a finite number of seconds >= 0, 0 for none (got "
                       f"{args.status_interval})")
    if args.stall_s is not None and (not args.lockstep or not 0 < args.stall_s < 1e9):
        raise CliError(f"--stall-s must be a finite number of seconds > 0, with --lockstep (got {args.stall_s})")
    specs = [AxisSpec.parse(a) for a in args.axis]
    where = [f"--axis {a!r}" for a in args.axis]  # what names each axis, for the error lines
    if args.config is not None or not specs:
        cfg_path = Path(args.config) if args.config else DEFAULT_CONFIG
        main_cfg = load_axis_config(cfg_path)
        specs.insert(0, AxisSpec(main_cfg.axis.name, args.node_id, cfg_path))
        where.insert(0, f"{cfg_path}: axis.name")
    _check_axis_names([s.name for s in specs], where, mqtt=args.mqtt is not None)
    ids = [s.node_id for s in specs]
    if len(set(ids)) != len(ids):
        raise ConfigError("--axis", "node id", f"node ids must be unique (got {ids})")
    names = [s.name for s in specs]
    if len(set(names)) != len(names):  # status lines, JSON keys and MQTT topics are per axis name
        raise ConfigError("--axis", "name", f"axis names must be unique (got {names})")
    configs = [load_axis_config(s.config) for s in specs]
    _check_outputs(args, [eds, *(s.config for s in specs), *([args.mqtt_credentials] if args.mqtt_credentials
                                                             else [])])
    # ---- side channels (Modbus TCP, MQTT): options checked before the bus opens
    from virtualaxis.services.serve_options import prepare as prepare_side_channels

    try:
        side = prepare_side_channels(args, specs[0].config)
    except ValueError as exc:
        raise CliError(str(exc)) from None
    if args.rt_priority:
        _set_rt_priority(args.rt_priority)
    if args.cpu_latency_us is not None:
        from virtualaxis.runtime.host import HostSettingError, hold_cpu_latency

        try:  # the descriptor stays open for the life of the process (the request ends with it)
            args._cpu_latency_fd = hold_cpu_latency(args.cpu_latency_us)
        except HostSettingError as exc:
            raise CliError(f"--cpu-latency-us: {exc}") from None
    if args.bitrate and not 10_000 <= args.bitrate <= 1_000_000:
        raise CliError(f"--bitrate must be 10000..1000000 bit/s, or 0 for no emulation (got {args.bitrate})")
    try:
        bus = open_bus(args.can)
    except BusOpenError as exc:
        raise CliError(str(exc)) from None
    if args.bitrate:
        from virtualaxis.runtime.bitrate import BitRateBus

        bus = BitRateBus(bus, args.bitrate)
    bus = side.wrap_bus(bus)  # side channels: their periodic jobs wait for the gap after a SYNC's PDOs
    if args.latency_probe:
        from virtualaxis.services.latency_probe import ProbeBus

        bus = ProbeBus(bus)
    try:
        axes = [AxisNode(bus, s.node_id, c, name=s.name, eds_path=eds,
                         allow_fault_injection=args.allow_fault_injection) for s, c in zip(specs, configs, strict=True)]
        # (--latency-probe times the receive thread's hand-over: keep the Notifier thread it probes)
        runtime = Runtime(bus, axes, lockstep=args.lockstep, read_in_loop=not args.latency_probe,
                          **({} if args.stall_s is None else {"stall_s": args.stall_s}))
    except ValueError as exc:
        bus.shutdown()
        raise CliError(str(exc)) from None
    stop = threading.Event()

    def _stop(*_):
        stop.set()

    signal.signal(signal.SIGTERM, _stop)
    _log_to_stderr()
    try:  # before the drive runs: forking the side channels' processes holds the interpreter lock for ms
        # at real-time priority the side channels' readings of the drives run in the runtime thread's gap: a
        # thread of their own would make the drive's thread wait for the interpreter lock (a priority inversion)
        side.start(axes, run_in_gap=runtime.run_in_gap if args.rt_priority else None)
    except OSError as exc:
        side.stop()
        bus.shutdown()
        raise CliError(str(exc)) from None
    from virtualaxis.runtime.pacing import freeze_startup_heap

    freeze_startup_heap()  # no 100 ms collections of the start-up heap while serving
    runtime.start()
    from virtualaxis.services.latency_probe import name_threads

    name_threads()  # OS thread names = Python thread names (top -H, /proc/PID/task/*/comm)
    names = ", ".join(f"{a.name} (node {a.node_id})" for a in axes)
    mode = "lockstep (plant advances on SYNC)" if args.lockstep else f"real time, {runtime.period_s * 1e3:g} ms cycle"
    print(f"ready: serving {names} on {args.can}; {mode}", flush=True)
    for line in side.lines:
        print(line, flush=True)
    t_end = None if args.duration is None else time.monotonic() + args.duration
    next_status = time.monotonic() + args.status_interval if args.status_interval > 0 else None
    try:
        while not stop.is_set():
            if t_end is not None and time.monotonic() >= t_end:
                break
            stop.wait(0.1)
            if runtime.stats.thread_error:
                break  # the runtime thread stopped: nothing is served any more (reported below)
            if next_status is not None and time.monotonic() >= next_status:
                next_status += args.status_interval
                _print_status(runtime)
                if hasattr(bus, "stats"):
                    b = bus.stats()
                    print(f"CAN bus: load {b['load_percent']:.1f} % of {b['bitrate_bit_s']} bit/s (peak "
                          f"{b['peak_load_percent']:.1f} %, mean {b['mean_load_percent']:.1f} %), frames sent / "
                          f"received {b['frames_sent']} / {b['frames_received']}, bits {b['bits_sent']} / "
                          f"{b['bits_received']}, tx delay mean {b['tx_delay_mean_ms']:.3f} ms, max "
                          f"{b['tx_delay_max_ms']:.3f} ms, {b['tx_refused']} frames refused", flush=True)
    except KeyboardInterrupt:
        pass
    finally:
        side.stop()
        runtime.stop()
        bus.shutdown()
    summary = {
        "bus": args.can,
        "lockstep": args.lockstep,
        "runtime": runtime.stats.as_dict(),
        "can_bus": bus.stats() if hasattr(bus, "stats") else {"bitrate_bit_s": 0, "emulated": False},
        "axes": [
            {
                "name": a.name,
                "node_id": a.node_id,
                "drive": a.drive.counters,
                "canopen": dict(a.slave.counters),
                "state": a.drive.state.as_dict(),
            }
            for a in axes
        ],
        **side.stats(),
    }
    st = runtime.stats
    if args.lockstep:  # (no lateness in lockstep: a cycle given up is one of a SYNC backlog the host fell behind)
        behind = (f"{st.syncs_skipped} SYNC whose cycles were given up ({st.skipped} cycles: the host fell more than "
                  f"{runtime.max_sync_backlog} SYNC behind)" if st.syncs_skipped else "no cycle given up")
        print(f"stopped: {st.cycles} drive cycles, {st.syncs} SYNC, {behind}", flush=True)
    else:
        print(
            f"stopped: {st.cycles} drive cycles, {st.syncs} SYNC, {st.overruns} overruns "
            f"(max lateness {st.max_late_s * 1e3:.3f} ms)",
            flush=True,
        )
    healthy = runtime.healthy
    summary["healthy"] = healthy
    summary["drive_exceptions"] = st.drive_exceptions
    summary["thread_error"] = st.thread_error
    summary["axes_exceptions"] = {a.name: a.exceptions for a in axes}
    summary["stalls"] = st.stalls
    if args.json:
        _write_json(Path(args.json), summary)
    if args.latency_probe:
        bus.write(args.latency_probe)
    if not healthy:
        if st.thread_error:
            what = f"the runtime thread stopped: {st.thread_error.strip().splitlines()[-1]} (tracebacks above)"
        elif st.drive_exceptions:
            what = (f"{st.drive_exceptions} drive-cycle exception(s), last: {st.last_exception} (drives faulted "
                    "with 0x6100; tracebacks above)")
        else:
            what = (f"the lockstep cycle stalled {st.stalls} time(s), longest {st.max_sync_work_s:.3f} s > "
                    f"--stall-s {runtime.stall_s:g} s: SDO, NMT and SYNC went unanswered meanwhile")
        print(f"error: {what}", file=sys.stderr, flush=True)
        return 1
    return 0


def _check_axis_names(names: list[str], where: list[str], *, mqtt: bool) -> None:
    """Axis names are printed in the ``ready:`` and status lines and are JSON keys: no control character (a
    newline would start a line of its own); with ``--mqtt`` each is a topic level: letters, digits, '_', '-',
    '.' only (no '/', no wildcard '+' / '#'). A name that breaks a rule is refused naming where it comes from."""
    from virtualaxis.cli.main import CliError

    for name, source in zip(names, where, strict=True):
        if not name.isprintable():
            raise CliError(f"{source}: axis name {name!r} contains a control character (names appear in the "
                           "status lines and the JSON report)")
        if mqtt:
            from virtualaxis.services.mqtt import topic_name_problem

            problem = topic_name_problem(name)
            if problem is not None:
                raise CliError(f"{source}: axis name {problem} (--mqtt publishes under "
                               "virtualaxis/<machine>/<axis>/)")


def _check_inputs(args, eds: Path) -> None:
    """Everything that can be refused is refused before serving: the EDS (file, section, key, the objects the
    slave and the drive need), the --json
    output path (not a folder, its folder exists and takes a new file)."""
    import tempfile

    from virtualaxis.canopen_slave.od import check_served_eds
    from virtualaxis.cli.main import CliError
    from virtualaxis.drive.objects import OBJECTS

    if not eds.is_file():
        raise CliError(f"{eds}: EDS file not found" if not eds.exists() else f"{eds}: EDS path is not a file")
    check_served_eds(eds, tuple((o.index, o.sub, o.name) for o in OBJECTS))  # what the slave and the drive need
    if args.json:
        out = Path(args.json)
        if out.is_dir():
            raise CliError(f"--json {out}: is a folder, expected a file path")
        parent = out.parent if str(out.parent) else Path(".")
        if not parent.is_dir():
            raise CliError(f"--json {out}: folder {parent} does not exist")
        if out.exists() and not out.is_file():
            raise CliError(f"--json {out}: exists and is not a regular file")
        try:
            with tempfile.NamedTemporaryFile(dir=parent, prefix=f".{out.name}.", suffix=".tmp"):
                pass
        except OSError as exc:
            raise CliError(f"--json {out}: cannot write in {parent} ({exc.strerror or exc})") from None


def _check_outputs(args, inputs: list) -> None:
    """The outputs (``--json``, ``--latency-probe``) against the inputs and each other, before the bus opens:
    neither may be an input (the EDS, an axis config, the MQTT credentials; also through a symbolic or hard
    link), even with ``--force``; the two must be distinct; an existing probe file needs ``--force`` like an
    existing report; the probe is a NumPy ``.npz`` archive and its name says so."""
    from virtualaxis.cli.main import CliError
    from virtualaxis.cli.outputs import check_output_file, claim_output, same_file

    if args.json:
        for src in inputs:
            if same_file(args.json, src):
                raise CliError(f"--json {args.json}: is also an input ({src}); it would be overwritten by the "
                               "report (--force does not allow that)")
        if Path(args.json).exists() and not args.force:
            raise CliError(f"--json {args.json}: exists (use --force to overwrite it)")
        claim_output(args.json, "--json")
    if args.latency_probe is not None:
        check_output_file(args.latency_probe, args.force, "--latency-probe", inputs=inputs)
        if Path(args.latency_probe).suffix.lower() != ".npz":
            raise CliError(f"--latency-probe {args.latency_probe}: the probe is written as a NumPy .npz archive; "
                           "give a file name ending in .npz")


def _write_json(path: Path, summary: dict) -> None:
    """Written to a temporary name beside the target and renamed when complete."""
    import os
    import tempfile

    fd, tmp = tempfile.mkstemp(dir=path.parent if str(path.parent) else ".", prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "w") as fh:
            json.dump(summary, fh, indent=2, default=str)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def _log_to_stderr() -> None:
    """The runtime's log (drive-cycle exceptions with tracebacks) goes to stderr unless logging is set up."""
    import logging

    log = logging.getLogger("virtualaxis")
    if not log.handlers and not logging.getLogger().handlers:
        handler = logging.StreamHandler(sys.stderr)
        handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
        log.addHandler(handler)
        log.setLevel(logging.INFO)


def _set_rt_priority(priority: int) -> None:
    """SCHED_FIFO for this process before any thread starts (threads inherit it); the runtime's waits
    yield, so the process takes at most its drive work plus the short spin before each cycle."""
    import os

    from virtualaxis.cli.main import CliError

    if not 1 <= priority <= 99:
        raise CliError(f"--rt-priority must be 1..99 (got {priority})")
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
    except (AttributeError, PermissionError, OSError) as exc:
        raise CliError(f"--rt-priority {priority}: cannot set SCHED_FIFO ({exc})") from None


def _print_status(runtime) -> None:
    st = runtime.stats
    for ax in runtime.axes:
        s = ax.drive.state
        print(
            f"{s.name}: {s.cia402_state}, mode {s.mode}, x = {s.position_actual_m * 1e3:.3f} mm, "
            f"FE = {s.following_error_m * 1e6:.1f} um, overruns {st.overruns}, SYNC {st.syncs}",
            file=sys.stdout,
            flush=True,
        )
