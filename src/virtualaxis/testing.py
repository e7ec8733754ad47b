"""pytest plugin: a ``virtual_axis`` fixture that serves a CiA 402 drive for a test and hands back a master.

Registered through the ``pytest11`` entry point ``virtualaxis`` (active once the package is installed; before
that, or to be explicit: ``pytest -p virtualaxis.testing``; never both, pytest refuses a plugin registered
twice). In a test::

    import pytest

    @pytest.mark.virtual_axis(transport="udp", node_id=(1, 2))
    def test_my_controller(virtual_axis):
        node = virtual_axis.node                      # canopen.BaseNode402, SDO ready
        node.sdo[0x6060].raw = 8
        virtual_axis.inject("encoder_loss")           # fault injection (Python API or over CAN)
        virtual_axis.sync(10)                         # lockstep (the default): ten drive cycles

Marker ``virtual_axis`` keywords (all optional): ``transport`` ``"virtual"`` (python-can ``virtual`` bus, drive in
this process; default) or ``"udp"`` (``virtualaxis serve`` in a child process on ``udp_multicast``, hop_limit 0);
``config`` (axis config TOML path, or a preset name of ``configs/`` such as ``"tuned-drive"``; default the seed
axis as published, ``seed000-hust``), ``node_id`` (an int or a tuple of ints: several axes
on one bus), ``pacing`` ``"lockstep"`` (the plant advances only on SYNC, every timer of the drive runs on its
cycle clock: a test gives the same answer on a busy CI runner; default) or ``"realtime"`` (the drive's own wall
clock: for what only real time shows, e.g. latency); or ``lockstep=True|False``,
``allow_fault_injection`` (default True),
``heartbeat_ms`` (0x1017 set on start, default 100). Command-line options ``--virtual-axis-transport``,
``--virtual-axis-config`` and ``--virtual-axis-pacing`` set the defaults for tests without those keywords;
``@pytest.mark.parametrize`` on
``virtual_axis`` with ``indirect=True`` and a dict of the same keywords parametrises it.

Clean-up runs when the test fails and on Ctrl-C: the child process is terminated (killed after 10 s), buses
are shut down; children still alive at interpreter exit are killed. A test run that is itself killed (SIGTERM or
SIGKILL: a CI job cancelled or timed out) runs no clean-up; on Linux its served drive is then sent SIGTERM by the
kernel (``PR_SET_PDEATHSIG``), so nothing outlives the run.
"""

from __future__ import annotations

import atexit
import contextlib
import difflib
import inspect
import os
import queue
import random
import subprocess
import sys
import tempfile
import threading
import time
import uuid
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest

_CHILDREN: set[subprocess.Popen] = set()
_CLI = [sys.executable, "-c", "import sys; from virtualaxis.cli.main import main; sys.exit(main())"]


def _die_with_parent():
    """A ``preexec_fn`` that has the child sent SIGTERM when this process dies however it dies (Linux
    ``PR_SET_PDEATHSIG``): a test run ended by SIGTERM or SIGKILL (a CI job cancelled or timed out) runs no
    clean-up of its own, and its served drive would live on. None where the call does not exist."""
    if not sys.platform.startswith("linux"):
        return None
    import ctypes
    import signal

    try:
        libc = ctypes.CDLL(None, use_errno=True)
        prctl = libc.prctl
    except (OSError, AttributeError):
        return None
    parent = os.getpid()

    def arm() -> None:  # (in the child, between fork and exec)
        prctl(1, int(signal.SIGTERM), 0, 0, 0)  # PR_SET_PDEATHSIG
        if os.getppid() != parent:  # the parent died before the call: nobody would send it
            os._exit(1)

    return arm


def _kill_children() -> None:
    for proc in list(_CHILDREN):
        if proc.poll() is None:
            proc.kill()
            with contextlib.suppress(Exception):
                proc.wait(5)
        _CHILDREN.discard(proc)


atexit.register(_kill_children)


class RemoteInjector:
    """Fault injection over CAN (objects 0x5FF0..0x5FF6), the same calls as
    :class:`virtualaxis.drive.injection.FaultInjector`."""

    def __init__(self, node: Any):
        self.node = node

    def inject(self, kind: str, *, duty: float = 1.0, period_s: float = 1.0, magnitude: float | None = None) -> None:
        from virtualaxis.drive.injection import KINDS, OBJ_DUTY, OBJ_INJECT, OBJ_MAGNITUDE, OBJ_PERIOD

        if kind not in KINDS:
            raise ValueError(f"unknown fault kind {kind!r} (known: {', '.join(KINDS)})")
        sdo = self.node.sdo
        sdo[OBJ_DUTY].raw = round(duty * 1000)
        sdo[OBJ_PERIOD].raw = round(period_s * 1000)
        sdo[OBJ_MAGNITUDE].raw = round(magnitude or 0)
        sdo[OBJ_INJECT].raw = KINDS[kind]

    def clear(self, kind: str | None = None) -> None:
        from virtualaxis.drive.injection import KINDS, OBJ_CLEAR

        self.node.sdo[OBJ_CLEAR].raw = KINDS[kind] if kind else 0xFF

    @property
    def active(self) -> list[str]:
        from virtualaxis.drive.injection import KIND_NAMES, OBJ_ACTIVE

        bits = self.node.sdo[OBJ_ACTIVE].raw
        return [name for n, name in KIND_NAMES.items() if bits >> (n - 1) & 1]


@dataclass
class VirtualAxis:
    """What the fixture yields: the bus, the node(s), a connected master network and fault injection."""

    transport: str  # "virtual" or "udp"
    bus_spec: str  # INTERFACE:CHANNEL[,k=v] as `virtualaxis serve --can` / `conformance --can` take it
    bus_kwargs: dict  # keyword arguments of can.Bus / canopen.Network.connect for another master
    node_ids: tuple[int, ...]
    network: Any  # canopen.Network, connected
    nodes: dict[int, Any]  # node id -> canopen.BaseNode402 (SDO ready; PDO set-up left to the test)
    injectors: dict[int, Any]  # node id -> FaultInjector (in-process) or RemoteInjector (udp)
    lockstep: bool = False
    drives: dict[int, Any] = field(default_factory=dict)  # in-process only: node id -> Drive
    runtime: Any = None  # in-process only: virtualaxis.runtime.Runtime
    process: subprocess.Popen | None = None  # udp only: the `virtualaxis serve` child

    @property
    def node_id(self) -> int:
        return self.node_ids[0]

    @property
    def node(self) -> Any:
        return self.nodes[self.node_ids[0]]

    @property
    def injector(self) -> Any:
        return self.injectors[self.node_ids[0]]

    def inject(self, kind: str, node_id: int | None = None, **options: Any) -> None:
        """Inject a fault (see docs/fault-injection.md) on ``node_id`` (default: the first axis)."""
        self.injectors[node_id or self.node_id].inject(kind, **options)

    def clear(self, kind: str | None = None, node_id: int | None = None) -> None:
        self.injectors[node_id or self.node_id].clear(kind)

    def sync(self, n: int = 1, period_s: float = 0.001) -> None:
        """Send ``n`` SYNC frames ``period_s`` apart (a lockstep drive advances one cycle per SYNC)."""
        for _ in range(n):
            self.network.sync.transmit()
            time.sleep(period_s)


def _private_udp_spec() -> tuple[str, dict]:
    rng = random.Random(os.getpid() * 7919 + time.perf_counter_ns())
    group, port = f"239.74.{rng.randint(100, 250)}.{rng.randint(1, 250)}", rng.randint(46000, 49000)
    return f"udp_multicast:{group},port={port}", {"interface": "udp_multicast", "channel": group, "port": port,
                                                   "hop_limit": 0}


def preset_path(config: str | Path) -> Path:
    """An axis config: a TOML path, or the name of a preset shipped in ``configs/`` (``"tuned-drive"``,
    ``"seed000-hust"``, ...), found in the repository or the installed data files."""
    path = Path(config)
    if path.suffix or len(path.parts) > 1 or path.is_file():
        return path
    from virtualaxis.resources import project_file

    return project_file(f"configs/{path.name}.toml")


@contextlib.contextmanager
def start_virtual_axis(*, transport: str = "virtual", config: str | Path | None = None,
                       node_id: int | tuple[int, ...] = 1, lockstep: bool = False, allow_fault_injection: bool = True,
                       heartbeat_ms: int = 100, ready_timeout_s: float = 180.0,
                       pacing: str | None = None) -> Iterator[VirtualAxis]:
    """Serve drive(s) and connect a master; the context manager behind the fixture (usable on its own).
    ``pacing`` ``"realtime"`` / ``"lockstep"`` is another way to say ``lockstep``."""
    if pacing is not None:
        if pacing not in ("realtime", "lockstep"):
            raise ValueError(f"virtual_axis: pacing must be 'realtime' or 'lockstep' (got {pacing!r})")
        lockstep = pacing == "lockstep"
    import canopen

    from virtualaxis.master import DEFAULT_EDS
    from virtualaxis.runtime.axes import DEFAULT_CONFIG

    ids = (node_id,) if isinstance(node_id, int) else tuple(node_id)
    if not ids or any(not isinstance(i, int) or not 1 <= i <= 127 for i in ids) or len(set(ids)) != len(ids):
        raise ValueError(f"virtual_axis: node_id must be 1..127, unique (got {node_id!r})")
    if transport not in ("virtual", "udp"):
        raise ValueError(f"virtual_axis: transport must be 'virtual' or 'udp' (got {transport!r})")
    cfg_path = preset_path(config) if config is not None else Path(DEFAULT_CONFIG)
    if not cfg_path.is_file():
        from virtualaxis.resources import project_file

        presets = ", ".join(sorted(p.stem for p in project_file("configs").glob("*.toml")))
        raise ValueError(f"virtual_axis: config {cfg_path} not found (a relative path is taken from "
                         f"{Path.cwd()}; or name a preset: {presets})")
    runtime = bus = proc = err_file = None
    net = canopen.Network()
    try:
        drives: dict[int, Any] = {}
        injectors: dict[int, Any] = {}
        if transport == "virtual":
            from virtualaxis.config import load_axis_config
            from virtualaxis.runtime import AxisNode, Runtime, open_bus

            channel = f"va-fixture-{uuid.uuid4().hex[:12]}"
            spec, kwargs = f"virtual:{channel}", {"interface": "virtual", "channel": channel}
            bus = open_bus(spec)
            cfg = load_axis_config(cfg_path)
            axes = [AxisNode(bus, i, cfg, name=f"axis{i}", allow_fault_injection=allow_fault_injection) for i in ids]
            runtime = Runtime(bus, axes, lockstep=lockstep)
            runtime.start()
            drives = {ax.node_id: ax.drive for ax in axes}
            injectors = {ax.node_id: ax.injection for ax in axes}
        else:
            spec, kwargs = _private_udp_spec()
            axis_args: list[str] = []
            for i in ids:
                axis_args += ["--axis", f"axis{i}={i}:{cfg_path}"]
            cmd = [*_CLI, "serve", "--can", spec, "--status-interval", "0", *axis_args]
            if lockstep:
                cmd.append("--lockstep")
            if allow_fault_injection:
                cmd.append("--allow-fault-injection")
            # stderr to a file and stdout drained by a thread: a chatty drive never blocks on a full pipe, and a
            # silent or hung one cannot hold the start-up past ready_timeout_s
            err_file = tempfile.TemporaryFile(mode="w+")
            proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=err_file, text=True,
                                    env={**os.environ, "PYTHONUNBUFFERED": "1"}, preexec_fn=_die_with_parent())
            _CHILDREN.add(proc)
            lines: queue.Queue[str] = queue.Queue()

            def pump() -> None:
                for out_line in proc.stdout:
                    lines.put(out_line)
                lines.put("")

            threading.Thread(target=pump, name="virtual-axis-stdout", daemon=True).start()
            deadline = time.monotonic() + ready_timeout_s
            line = ""
            while True:
                try:
                    line = lines.get(timeout=max(0.01, deadline - time.monotonic()))
                except queue.Empty:
                    line = "(no ready line in time)"
                    break
                if not line or line.startswith("ready:"):
                    break
            if not line.startswith("ready:"):
                proc.kill()
                proc.wait()
                err_file.seek(0)
                raise RuntimeError(f"virtual_axis: `virtualaxis serve` did not start in {ready_timeout_s} s: "
                                   f"{line!r} {err_file.read()[-2000:]}")
        from virtualaxis.master import connect

        net = connect(spec)
        nodes: dict[int, Any] = {}
        for i in ids:
            node = canopen.BaseNode402(i, DEFAULT_EDS)
            node.sdo.RESPONSE_TIMEOUT = 2.0
            net.add_node(node)
            nodes[i] = node
            if transport == "udp":
                injectors[i] = RemoteInjector(node)
        for node in nodes.values():
            node.sdo[0x1017].raw = heartbeat_ms
            if heartbeat_ms:
                node.nmt.wait_for_heartbeat(5.0)
        yield VirtualAxis(transport, spec, kwargs, ids, net, nodes, injectors, lockstep, drives, runtime, proc)
    finally:
        with contextlib.suppress(Exception):
            net.disconnect()
        if runtime is not None:
            with contextlib.suppress(Exception):
                runtime.stop()
        if bus is not None:
            with contextlib.suppress(Exception):
                bus.shutdown()
        if proc is not None:
            proc.terminate()
            try:
                proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
            _CHILDREN.discard(proc)
        if err_file is not None:
            err_file.close()


# ============================================================================ pytest hooks
def pytest_addoption(parser: pytest.Parser) -> None:
    group = parser.getgroup("virtualaxis", "virtual CiA 402 axis fixture")
    group.addoption("--virtual-axis-transport", choices=("virtual", "udp"), default=None,
                    help="default transport of the virtual_axis fixture (virtual: in-process; udp: a child process)")
    group.addoption("--virtual-axis-config", default=None, help="default axis config TOML of the virtual_axis fixture")
    group.addoption("--virtual-axis-pacing", choices=("lockstep", "realtime"), default=None,
                    help="default pacing of the virtual_axis fixture: lockstep (the drive advances only on SYNC, its "
                         "timers on its cycle clock; the default) or realtime (its own wall clock)")


def pytest_configure(config: pytest.Config) -> None:
    config.addinivalue_line(
        "markers",
        "virtual_axis(transport='virtual'|'udp', config=PATH, node_id=1|(1, 2), pacing='lockstep'|'realtime', "
        "allow_fault_injection=True, heartbeat_ms=100): how the virtual_axis fixture serves the drive",
    )


def pytest_unconfigure(config: pytest.Config) -> None:
    _kill_children()


def _option(config: pytest.Config, name: str) -> Any:
    try:
        return config.getoption(name)
    except ValueError:  # plugin registered after the command line was parsed (conftest fallback)
        return None


@pytest.fixture
def virtual_axis(request: pytest.FixtureRequest) -> Iterator[VirtualAxis]:
    """A served virtual axis and a connected ``canopen`` master (see the module docstring)."""
    #: lockstep unless the test or the command line asks for real time (as `virtualaxis conformance`)
    options: dict[str, Any] = {"pacing": _option(request.config, "virtual_axis_pacing") or "lockstep"}
    transport = _option(request.config, "virtual_axis_transport")
    cfg = _option(request.config, "virtual_axis_config")
    if transport:
        options["transport"] = transport
    if cfg:
        options["config"] = cfg
    marker = request.node.get_closest_marker("virtual_axis")
    if marker is not None:
        if marker.args:
            raise pytest.UsageError("virtual_axis marker: keywords only (transport=..., config=..., node_id=...)")
        options.update(marker.kwargs)
    param = getattr(request, "param", None)
    if isinstance(param, dict):
        options.update(param)
    given = {**(marker.kwargs if marker is not None else {}), **(param if isinstance(param, dict) else {})}
    if "lockstep" in given and "pacing" not in given:
        del options["pacing"]  # (lockstep=True|False given: it says the pacing)
    known = inspect.signature(start_virtual_axis).parameters
    unknown = [key for key in options if key not in known]
    if unknown:
        key = unknown[0]
        close = difflib.get_close_matches(key, list(known), n=1)
        pytest.fail(f"virtual_axis: unknown option {key!r}" + (f" (did you mean {close[0]}?)" if close else "")
                    + f"; the options are {', '.join(known)}", pytrace=False)
    cm = start_virtual_axis(**options)
    try:
        axis = cm.__enter__()
    except ValueError as exc:  # a value the options do not allow (a config not found, a node id out of range)
        pytest.fail(str(exc), pytrace=False)
    try:
        yield axis
    finally:
        cm.__exit__(None, None, None)
