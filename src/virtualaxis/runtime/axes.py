"""Axes on a bus: a drive, its CiA 402 application and its CiA 301 slave, built from an axis config."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import can

from virtualaxis.config import AxisConfig, ConfigError, load_axis_config
from virtualaxis.drive.canopen_app import Cia402Application
from virtualaxis.drive.core import DEFAULT_EDS, Drive
from virtualaxis.drive.injection import serve_with_injection
from virtualaxis.resources import project_file

DEFAULT_CONFIG = project_file("configs/seed000-hust.toml")


@dataclass(frozen=True)
class AxisSpec:
    """``NAME=ID:CONFIG`` of ``virtualaxis serve --axis``."""

    name: str
    node_id: int
    config: Path

    @staticmethod
    def parse(text: str) -> AxisSpec:
        if "=" not in text or ":" not in text.split("=", 1)[1]:
            raise ConfigError("--axis", text, "expected NAME=ID:CONFIG, e.g. X=1:configs/seed000-hust.toml")
        name, rest = text.split("=", 1)
        node, config = rest.split(":", 1)
        try:
            node_id = int(node, 0)
        except ValueError:
            raise ConfigError("--axis", text, f"node id {node!r} is not an integer") from None
        if not 1 <= node_id <= 127:
            raise ConfigError("--axis", text, f"node id must be 1..127 (got {node_id})")
        if not name:
            raise ConfigError("--axis", text, "axis name is empty")
        return AxisSpec(name, node_id, Path(config))


class AxisNode:
    """One axis served on a bus (call :meth:`boot` once the bus listener is running)."""

    def __init__(
        self,
        bus: can.BusABC,
        node_id: int,
        cfg: AxisConfig,
        *,
        name: str | None = None,
        eds_path: str | Path = DEFAULT_EDS,
        store_path: str | Path | None = None,
        seed: int | None = None,
        initial_position_m: float = 0.0,
        discrete=None,
        allow_fault_injection: bool = False,
    ):
        self.name = name or cfg.axis.name
        self.node_id = node_id
        self.drive = Drive(
            cfg,
            name=self.name,
            eds_path=eds_path,
            seed=seed,
            initial_position_m=initial_position_m,
            discrete=discrete,
        )
        self.app = Cia402Application(self.drive)
        # the fault-injection channel (0x5FF0.., refused unless allowed) in front of the application
        self.slave, self.injection = serve_with_injection(bus, node_id, self.drive, self.app, eds_path,
                                                          allowed=allow_fault_injection, store_path=store_path)
        self.app.attach(self.slave)
        #: drive cycles one SYNC runs at most in lockstep (see :meth:`limit_sync_period`)
        self.max_sync_cycles = 1 << 31
        #: drive cycles run by the runtime (the drive's own clock, see :attr:`drive_time_s`)
        self.drive_cycles = 0
        #: lockstep: the slave's clock at drive time 0 once SYNCs started (None before the first SYNC after a boot)
        self.lockstep_origin_s: float | None = None
        #: lockstep: slave clock - runtime clock while no SYNC runs (keeps the slave's clock continuous)
        self.wall_offset_s = 0.0
        self.clock_boots = 0  # the slave's boot count the lockstep origin belongs to
        self.exceptions = 0  # exceptions caught from this axis's drive cycles (see runtime.pacing)
        #: the live 0x1006 entry (read every SYNC in lockstep; None when the EDS has no 0x1006)
        self._comm_period = self.slave.entry(0x1006, 0) if (0x1006, 0) in self.slave.od.entries else None
        self._sync_cycles_key: tuple[int, int, float] | None = None  # what :meth:`sync_cycles` last computed from
        self._sync_cycles = 1

    def fault_internal(self, code: int) -> None:
        """Put the drive in FAULT with ``code`` (EMCY through the slave) after an exception in its cycle; not
        again while it is still in fault from it (no EMCY flood when every cycle raises)."""
        drive = self.drive
        state = getattr(drive.cia402_state, "name", "")
        if state not in ("FAULT", "FAULT_REACTION_ACTIVE"):
            drive.raise_fault(code)
        self.app.flush()

    @property
    def drive_time_s(self) -> float:
        """The drive's own clock [s]: drive cycles run x position cycle (the slave's timers in lockstep)."""
        return self.drive_cycles * self.drive.cycle_s

    def limit_sync_period(self, max_period_s: float) -> None:
        """Lockstep: a SYNC advances the drive by at most ``max_period_s``; a larger 0x1006 is refused by SDO
        (abort 0x06090031) and, when one comes from a stored parameter set, bounded in :meth:`sync_cycles`."""
        self.max_sync_cycles = max(1, int(round(max_period_s / self.drive.cycle_s)))
        self.slave.sync.max_period_us = int(round(max_period_s * 1e6))

    def sync_cycles(self) -> int:
        """Drive cycles per SYNC in lockstep: 0x1006 (communication cycle) / position cycle, at least 1 and at
        most :attr:`max_sync_cycles`."""
        period_us = self._comm_period.value if self._comm_period is not None else 0
        if not period_us:
            return 1
        key = (period_us, self.max_sync_cycles, self.drive.cycle_s)
        if key != self._sync_cycles_key:  # (recomputed only when 0x1006, the bound or the cycle changed)
            self._sync_cycles_key = key
            self._sync_cycles = min(self.max_sync_cycles, max(1, int(round(period_us * 1e-6 / self.drive.cycle_s))))
        return self._sync_cycles


def build_axes(bus: can.BusABC, specs: list[AxisSpec], *, eds_path: str | Path = DEFAULT_EDS) -> list[AxisNode]:
    """Axes from ``--axis`` specs; node ids must be unique."""
    seen: dict[int, str] = {}
    axes = []
    for spec in specs:
        if spec.node_id in seen:
            raise ConfigError("--axis", spec.name, f"node id {spec.node_id} already used by axis {seen[spec.node_id]}")
        seen[spec.node_id] = spec.name
        cfg = load_axis_config(spec.config)
        axes.append(AxisNode(bus, spec.node_id, cfg, name=spec.name, eds_path=eds_path))
    return axes
