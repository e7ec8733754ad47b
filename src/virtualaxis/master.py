"""Helpers for a CANopen master (the `canopen` package) talking to served drives.

    import canopen
    from virtualaxis.master import DEFAULT_EDS, connect

    net = connect("udp_multicast:239.74.163.2")       # the same bus string as `virtualaxis serve --can`
    node = canopen.BaseNode402(1, DEFAULT_EDS)
    net.add_node(node)

:func:`connect` opens the bus with :func:`virtualaxis.runtime.open_bus` (``hop_limit=0`` for udp_multicast and
the master's own frames filtered out, as a CAN controller does: without that, ``canopen`` takes the master's
own RPDOs for periodic PDOs sent by the drive and ``BaseNode402`` waits for them in vain).
"""

from __future__ import annotations

import math
import queue
import re
import struct
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import canopen
import canopen.sdo
import numpy as np

from virtualaxis.resources import project_file
from virtualaxis.runtime.bus import DEFAULT_BUS, open_bus

#: the drive's EDS (``eds/virtualaxis.eds``), as a string for ``canopen`` nodes
DEFAULT_EDS = str(project_file("eds/virtualaxis.eds"))


def connect(spec: str = DEFAULT_BUS, *, bitrate: int = 0) -> canopen.Network:
    """A connected ``canopen.Network`` on the bus ``spec`` names (``INTERFACE:CHANNEL[,key=value...]``).

    ``bitrate`` (bit/s, 0 = off): the master's frames go out with the timing of a CAN bus at that rate
    (:class:`virtualaxis.runtime.bitrate.BitRateBus`: frame times, arbitration, transmit queue), so that a
    master that would overload a real bus sees the delays (``net.bus.stats()``) and, when its transmit queue is
    full, ``can.CanOperationError`` from ``send``."""
    bus = open_bus(spec)
    if bitrate:
        from virtualaxis.runtime.bitrate import BitRateBus

        bus = BitRateBus(bus, bitrate)
    net = canopen.Network(bus)
    net.connect()
    return net


#: SDO abort code the master sends when it ends a transfer that does not end (CiA 301: SDO protocol timed out)
ABORT_SDO_TIMED_OUT = 0x05040000
#: an SDO transfer (initiate to last frame) may last this many response timeouts at most (at least 1 s)
TRANSFER_TIMEOUTS = 10
#: ... and this many server frames at most (70 kB of segments: far more than any object of a drive's EDS)
MAX_TRANSFER_FRAMES = 10_000


class SdoTransferOverrun(Exception):  # noqa: N818 - the name says what happened
    """An SDO transfer that did not end: more frames or more time than any object needs (a server sending
    segments for ever, or answering each segment request without finishing). Not an ``SdoCommunicationError``:
    the node's SDO server is broken, which is no answer about the object asked for."""


class BoundedSdoClient(canopen.sdo.SdoClient):
    """``canopen``'s SDO client with the guards a master talking to an unknown node needs:

    - every server frame must be 8 bytes (CiA 301 SDO frames always are); a shorter one is an
      ``SdoCommunicationError`` naming it (``canopen`` itself would raise ``struct.error``);
    - a transfer ends within ``transfer_timeout_s`` (default :data:`TRANSFER_TIMEOUTS` response timeouts, at
      least 1 s) and :data:`MAX_TRANSFER_FRAMES` frames; else it is aborted (0x05040000) and
      :class:`SdoTransferOverrun` raised, then and for every later request of this client (:attr:`overrun`);
    - :attr:`unanswered` counts the exchanges that ended without a valid answer (timeouts, malformed frames),
      :attr:`unanswered_in_row` those since the last valid answer, :attr:`stalled` those in the middle of a
      transfer the node had begun (segments stopped coming).
    """

    def __init__(self, rx_cobid: int, tx_cobid: int, od, *, transfer_timeout_s: float | None = None):
        super().__init__(rx_cobid, tx_cobid, od)
        self.transfer_timeout_s = transfer_timeout_s
        self.overrun: str | None = None
        self.unanswered = 0
        self.unanswered_in_row = 0
        self.stalled = 0
        self.last_failure = ""
        self._t0 = time.monotonic()
        self._frames = 0
        self._received = 0
        self._what = ""
        self._ended = False  # the transfer under way was aborted: no segment request may follow

    def _limit_s(self) -> float:
        if self.transfer_timeout_s is not None:
            return self.transfer_timeout_s
        return max(1.0, TRANSFER_TIMEOUTS * float(self.RESPONSE_TIMEOUT))

    def send_request(self, request) -> None:
        if self.overrun:
            raise SdoTransferOverrun(self.overrun)
        b = bytes(request)
        ccs = b[0] >> 5 if b else 0
        if ccs in (1, 2) or (ccs == 5 and b[0] & 0x03 == 0) or (ccs == 6 and b[0] & 0x01 == 0) or ccs == 4:
            self._t0 = time.monotonic()  # an initiate (or an abort) starts a new transfer
            self._frames = 0
            self._received = 0
            self._what = f"0x{b[2] << 8 | b[1]:04X}:{b[3]}" if len(b) >= 4 and ccs != 4 else self._what
            self._ended = False
        elif ccs in (0, 3) and self._ended:
            # a segment of a transfer the server aborted: canopen's stream sends the closing segment of an
            # aborted download when it is collected, and would wait out a response timeout in a finalizer
            raise canopen.SdoCommunicationError(f"the transfer of {self._what or 'an object'} was aborted")
        super().send_request(request)

    def read_response(self) -> bytes:
        if self.overrun:
            raise SdoTransferOverrun(self.overrun)
        self._frames += 1
        elapsed = time.monotonic() - self._t0
        if self._frames > MAX_TRANSFER_FRAMES or elapsed > self._limit_s():
            self.overrun = (f"the SDO transfer of {self._what or 'an object'} did not end ({self._frames - 1} frames "
                            f"in {elapsed:.1f} s; at most {MAX_TRANSFER_FRAMES} frames and {self._limit_s():g} s): "
                            "the node's SDO server does not finish its transfers")
            try:
                super().send_request(_abort_frame(ABORT_SDO_TIMED_OUT))
            except Exception:  # noqa: BLE001 - the abort is a courtesy; the overrun is what is reported
                pass
            raise SdoTransferOverrun(self.overrun)
        try:
            response = self.responses.get(block=True, timeout=self.RESPONSE_TIMEOUT)
        except queue.Empty:
            self._fail("No SDO response received")
        if len(response) != 8:
            self._fail(f"malformed SDO response: {len(response)} byte(s) [{response.hex(' ')}]; an SDO frame has 8")
        if response[0] == 0x80:  # abort transfer
            self._ended = True
            raise canopen.SdoAbortedError(struct.unpack_from("<L", response, 4)[0])
        self._received += 1
        self.unanswered_in_row = 0
        return response

    def _fail(self, text: str):
        self.unanswered += 1
        self.unanswered_in_row += 1
        if self._received:  # the node began this transfer and stopped answering in its middle
            self.stalled += 1
            text = f"{text} after {self._received} frame(s) of the transfer"
        self.last_failure = f"{text} ({self._what})" if self._what else text
        raise canopen.SdoCommunicationError(text)


def _abort_frame(code: int) -> bytes:
    return bytes((0x80, 0, 0, 0)) + struct.pack("<L", code)


def install_bounded_sdo(node, *, transfer_timeout_s: float | None = None) -> BoundedSdoClient:
    """Replace ``node``'s default SDO client (before ``network.add_node(node)``) by a :class:`BoundedSdoClient`
    on the same COB-IDs; returns it."""
    old = node.sdo
    client = BoundedSdoClient(old.rx_cobid, old.tx_cobid, node.object_dictionary,
                              transfer_timeout_s=transfer_timeout_s)
    client.RESPONSE_TIMEOUT = old.RESPONSE_TIMEOUT
    node.sdo_channels[:] = [client if c is old else c for c in node.sdo_channels]
    node.sdo = client
    return client


# ============================================================================ lockstep master
MODES = {"csp": 8, "csv": 9, "cst": 10}
#: RPDO1 target object and its size [bits] per mode
_TARGETS = {"csp": (0x607A, 32, True), "csv": (0x60FF, 32, True), "cst": (0x6071, 16, True)}
_OPERATION_ENABLED = 0x27
_STATE_MASK = 0x6F
_ENABLE_SEQUENCE = (0x06, 0x07, 0x0F)
_GCODE_WORD = re.compile(r"([A-Z])\s*([-+]?\d*\.?\d+)", re.IGNORECASE)


class LockstepError(RuntimeError):
    """The drive did not answer a SYNC, or did not reach OPERATION ENABLED; the message says which node and when."""


class SetpointError(ValueError):
    """Set-points that cannot be streamed (wrong shape, not finite, an unreadable G-code line); the message names
    the file / line or the sample."""


@dataclass
class LockstepTrace:
    """What a :class:`LockstepMaster` run measured, one row per SYNC (drive time ``t_s = k x period_s``).

    ``setpoint[k]`` is what was sent with SYNC k (SI: m, m/s or N m by mode); ``position_m[k]``,
    ``velocity_m_s[k]``, ``torque_nm[k]`` and ``statusword[k]`` are the drive's values at the end of the
    communication cycle that set-point drove (its answer to SYNC k + 1). Columns: one per node of ``node_ids``."""

    mode: str
    period_s: float
    node_ids: tuple[int, ...]
    t_s: np.ndarray
    setpoint: np.ndarray
    position_m: np.ndarray
    velocity_m_s: np.ndarray
    torque_nm: np.ndarray
    statusword: np.ndarray

    def columns(self, node_id: int | None = None) -> dict[str, np.ndarray]:
        """The trace-format columns of one node (``t``, ``pos_cmd`` in CSP, ``pos_fb``, ``vel_meas``,
        ``torque_meas``); see docs/diagnosis.md."""
        j = self.node_ids.index(node_id if node_id is not None else self.node_ids[0])
        out = {"t": self.t_s.copy()}
        if self.mode == "csp":
            out["pos_cmd"] = self.setpoint[:, j].copy()
        out.update(pos_fb=self.position_m[:, j].copy(), vel_meas=self.velocity_m_s[:, j].copy(),
                   torque_meas=self.torque_nm[:, j].copy())
        return out

    def write(self, path: str | Path, node_id: int | None = None) -> Path:
        """One node's trace as a trace-format CSV file (CSP runs: the command is ``pos_cmd``)."""
        from virtualaxis.diagnosis.trace import write_trace

        if self.mode != "csp":
            raise SetpointError(f"{path}: the trace format needs pos_cmd; only a CSP run writes one (got "
                                f"{self.mode})")
        write_trace(path, self.columns(node_id))
        return Path(path)


class _Answers:
    """The latest frame of each COB-ID the master waits for, with a count of arrivals."""

    def __init__(self, network: canopen.Network, cobs: list[int]):
        self.cond = threading.Condition()
        self.count = dict.fromkeys(cobs, 0)
        self.data: dict[int, bytes] = {}
        self.network = network
        self.cobs = cobs
        for cob in cobs:
            network.subscribe(cob, self._on_frame)

    def _on_frame(self, cob: int, data: bytearray, _timestamp: float) -> None:
        with self.cond:
            self.data[cob] = bytes(data)
            self.count[cob] += 1
            self.cond.notify_all()

    def mark(self) -> dict[int, int]:
        with self.cond:
            return dict(self.count)

    def wait(self, mark: dict[int, int], timeout_s: float) -> dict[int, bytes] | None:
        """Every COB-ID's frame once more since ``mark`` (its newest data), None after ``timeout_s``."""
        end = time.monotonic() + timeout_s
        with self.cond:
            while True:
                if all(self.count[c] > mark[c] for c in self.cobs):
                    return {c: self.data[c] for c in self.cobs}
                left = end - time.monotonic()
                if left <= 0:
                    return None
                self.cond.wait(left)

    def close(self) -> None:
        for cob in self.cobs:
            self.network.unsubscribe(cob, self._on_frame)


class LockstepMaster:
    """A CANopen master that runs CiA 402 drives served with ``--lockstep`` one SYNC at a time.

        net = connect("udp_multicast:239.74.163.2,port=43113")
        with LockstepMaster(net, [1, 2], mode="csp") as m:
            trace = m.run(setpoints_m)          # array (n,) or (n, nodes), a generator of rows, or a G-code file

    :meth:`configure` (called on entry) writes by SDO, in PRE-OPERATIONAL: 0x1006 = ``period_s``, 0x60C2 = the
    same period, 0x6060 = the mode, RPDO1 = controlword + target (0x607A CSP, 0x60FF CSV, 0x6071 CST; synchronous),
    TPDO1 = statusword + 0x6064, TPDO2 = 0x606C + 0x6077 (both on every SYNC); then NMT start and the enable
    sequence (fault reset if needed, then 0x06, 0x07, 0x0F, each sent on every SYNC until every node shows its state,
    for at most ``enable_timeout_s`` of drive time: a drive that opens its holding brake first stays SWITCHED ON for
    its brake opening delay) with the target on the actual position.
    Every step sends each node's RPDO1, one SYNC, and waits (``answer_timeout_s`` of wall time) for every node's
    TPDO1 and TPDO2: the master may be as slow as the host makes it, the drives see one communication cycle per
    SYNC. Units: positions in m, velocities in m/s (``units_per_m`` drive units per m, default 1e6: 1 um), torques
    in N m (0x6071 / 0x6077 are per mille of the rated torque 0x6076, read from each node).
    """

    def __init__(self, network: canopen.Network, node_ids: int | list[int] | tuple[int, ...], *, mode: str = "csp",
                 period_s: float = 0.001, units_per_m: float = 1e6, answer_timeout_s: float = 5.0,
                 eds: str = DEFAULT_EDS, enable_timeout_s: float = 2.0):
        if mode not in MODES:
            raise ValueError(f"mode must be one of {', '.join(MODES)} (got {mode!r})")
        if not 0.0 < period_s <= 0.1:
            raise ValueError(f"period_s must be > 0 and <= 0.1 s (got {period_s})")
        if not 0.0 < enable_timeout_s <= 3600.0:
            raise ValueError(f"enable_timeout_s must be > 0 and <= 3600 s (got {enable_timeout_s})")
        self.network = network
        self.enable_timeout_s = enable_timeout_s
        self.node_ids = (node_ids,) if isinstance(node_ids, int) else tuple(node_ids)
        if not self.node_ids:
            raise ValueError("no node ids")
        self.mode = mode
        self.period_s = period_s
        self.units_per_m = units_per_m
        self.answer_timeout_s = answer_timeout_s
        self.nodes = {}
        for nid in self.node_ids:
            node = network.get(nid)
            if node is None:
                node = canopen.RemoteNode(nid, eds)
                network.add_node(node)
            self.nodes[nid] = node
        self.rated_torque_nm: dict[int, float] = {}
        self.syncs = 0  # SYNCs sent by this master
        self._answers: _Answers | None = None
        self._targets = dict.fromkeys(self.node_ids, 0)
        self._cw = 0x06
        self.last_answer: dict[int, bytes] = {}  # COB-ID -> data of the latest TPDO1 / TPDO2 of every node

    def position_m(self, node_id: int) -> float:
        """A node's position actual value (0x6064) of the latest answer [m]."""
        return _i32(self.last_answer[0x180 + node_id][2:6]) / self.units_per_m

    # ---------------------------------------------------------------- set-up
    def __enter__(self) -> LockstepMaster:
        try:
            self.configure()
        except BaseException:  # (nothing to exit from: the answer listener goes now)
            self.close()
            raise
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _map(self, sdo, comm: int, mapping: int, cob: int, entries: list[int], ttype: int) -> None:
        sdo[comm][1].raw = cob | 0x80000000
        sdo[mapping][0].raw = 0
        for i, e in enumerate(entries, 1):
            sdo[mapping][i].raw = e
        sdo[mapping][0].raw = len(entries)
        sdo[comm][2].raw = ttype
        sdo[comm][1].raw = cob

    def configure(self) -> None:
        """PDOs, period and mode by SDO, NMT start, drives enabled (see the class doc)."""
        index, bits, _ = _TARGETS[self.mode]
        period_ms = self.period_s * 1e3
        for nid, node in self.nodes.items():
            sdo = node.sdo
            self.network.send_message(0x000, bytes((0x80, nid)))  # NMT enter PRE-OPERATIONAL
            time.sleep(0.01)
            sdo[0x1006].raw = round(self.period_s * 1e6)
            if abs(period_ms - round(period_ms)) < 1e-9:
                sdo[0x60C2][1].raw, sdo[0x60C2][2].raw = round(period_ms), -3
            else:
                sdo[0x60C2][1].raw, sdo[0x60C2][2].raw = round(self.period_s * 1e4), -4
            self._map(sdo, 0x1800, 0x1A00, 0x180 + nid, [0x60410010, 0x60640020], 1)
            self._map(sdo, 0x1801, 0x1A01, 0x280 + nid, [0x606C0020, 0x60770010], 1)
            self._map(sdo, 0x1400, 0x1600, 0x200 + nid, [0x60400010, (index << 16) | bits], 1)
            sdo[0x6060].raw = MODES[self.mode]
            self.rated_torque_nm[nid] = sdo[0x6076].raw * 1e-3
            self._targets[nid] = sdo[0x6064].raw if self.mode == "csp" else 0
        self._answers = _Answers(self.network, [c + n for n in self.node_ids for c in (0x180, 0x280)])
        for nid in self.node_ids:
            self.network.send_message(0x000, bytes((0x01, nid)))  # NMT start
        time.sleep(0.01)
        self.enable()

    def enable(self, max_syncs: int | None = None) -> None:
        """Fault reset when needed, then 0x06, 0x07, 0x0F until every node is OPERATION ENABLED (at most
        ``max_syncs`` SYNCs per step; by default those of ``enable_timeout_s``); CSP targets held on the actual
        position."""
        if max_syncs is None:
            max_syncs = max(1, math.ceil(self.enable_timeout_s / self.period_s))
        answer = self.step_raw()
        if any(sw & 0x4F == 0x08 for sw in self._statuswords(answer).values()):
            self._cw = 0x80
            self.step_raw()
            self._cw = 0x00
            answer = self.step_raw()
        want = {0x06: 0x21, 0x07: 0x23, 0x0F: 0x27}
        for cw in _ENABLE_SEQUENCE:
            self._cw = cw
            for _ in range(max_syncs):
                answer = self.step_raw()
                if self.mode == "csp":
                    self._targets = {n: _i32(answer[0x180 + n][2:6]) for n in self.node_ids}
                sws = self._statuswords(answer)
                if all(sw & _STATE_MASK == want[cw] for sw in sws.values()):
                    break
            else:
                raise LockstepError(f"controlword 0x{cw:02X}: statuswords {self._hex(sws)} after {max_syncs} SYNCs "
                                    f"({max_syncs * self.period_s:g} s of drive time, enable_timeout_s)")

    def close(self) -> None:
        if self._answers is not None:
            self._answers.close()
            self._answers = None

    # ---------------------------------------------------------------- streaming
    @staticmethod
    def _statuswords(answer: dict[int, bytes]) -> dict[int, int]:
        return {cob - 0x180: int.from_bytes(d[0:2], "little") for cob, d in answer.items() if cob < 0x200}

    @staticmethod
    def _hex(sws: dict[int, int]) -> str:
        return ", ".join(f"node {n}: 0x{sw:04X}" for n, sw in sws.items())

    def step_raw(self, targets: dict[int, int] | None = None) -> dict[int, bytes]:
        """One communication cycle: each node's RPDO1 (controlword + target in drive units), one SYNC, and the
        answers (COB-ID -> data of TPDO1 / TPDO2 of every node)."""
        if self._answers is None:
            raise LockstepError("not configured: call configure() or use the master as a context manager")
        if targets:
            self._targets.update(targets)
        _, bits, _ = _TARGETS[self.mode]
        for nid in self.node_ids:
            t = int(self._targets[nid])
            self.network.send_message(0x200 + nid, self._cw.to_bytes(2, "little") +
                                      t.to_bytes(bits // 8, "little", signed=True))
        mark = self._answers.mark()
        self.network.send_message(0x080, b"")
        self.syncs += 1
        answer = self._answers.wait(mark, self.answer_timeout_s)
        if answer is None:
            missing = [f"0x{c:03X}" for c in self._answers.cobs if self._answers.count[c] <= mark[c]]
            raise LockstepError(f"SYNC {self.syncs}: no answer within {self.answer_timeout_s:g} s from "
                                f"{', '.join(missing)}")
        self.last_answer = answer
        return answer

    def _to_units(self, nid: int, value: float) -> int:
        if self.mode == "cst":
            return round(value / self.rated_torque_nm[nid] * 1e3)
        return round(value * self.units_per_m)

    def run(self, setpoints, *, axes: str = "XYZABC", stop_on_fault: bool = True) -> LockstepTrace:
        """Stream ``setpoints`` one SYNC each and return the measured trace. ``setpoints``: an array (n,) or
        (n, nodes), an iterable / generator of numbers or rows, or the path of a G-code-like file (CSP only;
        see :func:`gcode_setpoints`; the letters of ``axes`` name the nodes in order). A node in FAULT ends the
        run with :class:`LockstepError` (``stop_on_fault``)."""
        if isinstance(setpoints, (str, Path)):
            if self.mode != "csp":
                raise SetpointError(f"{setpoints}: a G-code file gives positions; mode is {self.mode}")
            setpoints = gcode_setpoints(setpoints, axes=axes[:len(self.node_ids)], period_s=self.period_s)
        self._cw = 0x0F
        k_nodes = len(self.node_ids)
        rows: list[np.ndarray] = []
        meas: list[dict[int, bytes]] = []
        for k, row in enumerate(setpoints):
            values = np.atleast_1d(np.asarray(row, dtype=float))
            if values.shape != (k_nodes,) or not np.all(np.isfinite(values)):
                raise SetpointError(f"set-point {k}: expected {k_nodes} finite number(s), got {row!r}")
            answer = self.step_raw({n: self._to_units(n, v) for n, v in zip(self.node_ids, values, strict=True)})
            if k:
                meas.append(answer)
            rows.append(values)
            if stop_on_fault:
                self._check_fault(answer, k)
        if not rows:
            raise SetpointError("no set-points")
        meas.append(self.step_raw())  # the answer to the cycle of the last set-point
        return self._trace(np.array(rows), meas)

    def _check_fault(self, answer: dict[int, bytes], k: int) -> None:
        sws = self._statuswords(answer)
        if any(sw & 0x4F == 0x08 for sw in sws.values()):
            raise LockstepError(f"set-point {k}: drive in FAULT ({self._hex(sws)})")

    def _trace(self, sp: np.ndarray, meas: list[dict[int, bytes]]) -> LockstepTrace:
        n, m = len(meas), len(self.node_ids)
        pos, vel, tq = np.empty((n, m)), np.empty((n, m)), np.empty((n, m))
        sw = np.empty((n, m), dtype=np.uint16)
        for k, answer in enumerate(meas):
            for j, nid in enumerate(self.node_ids):
                d1, d2 = answer[0x180 + nid], answer[0x280 + nid]
                sw[k, j] = int.from_bytes(d1[0:2], "little")
                pos[k, j] = _i32(d1[2:6]) / self.units_per_m
                vel[k, j] = _i32(d2[0:4]) / self.units_per_m
                tq[k, j] = int.from_bytes(d2[4:6], "little", signed=True) * 1e-3 * self.rated_torque_nm[nid]
        return LockstepTrace(self.mode, self.period_s, self.node_ids, np.arange(n) * self.period_s, sp, pos, vel,
                             tq, sw)


def _i32(b: bytes) -> int:
    return int.from_bytes(b[0:4], "little", signed=True)


def gcode_setpoints(path: str | Path, *, axes: str = "X", period_s: float = 0.001, accel_m_s2: float = 1.0,
                    rapid_m_min: float = 6.0, start_m: tuple[float, ...] | None = None) -> np.ndarray:
    """CSP set-points [m], shape (n, len(axes)), from a G-code-like file: G0 / G1 straight moves in mm with the
    axis letters of ``axes`` (absolute, G90), feed F in mm/min (modal), G4 P<s> dwell; each block a trapezoidal
    speed profile from rest to rest (``accel_m_s2``), G0 at ``rapid_m_min``; comments after ';' or in '()'.
    Anything else (arcs, other words) is refused with :class:`SetpointError` naming the file and line."""
    path = Path(path)
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise SetpointError(f"{path}: cannot read ({exc})") from None
    axes = axes.upper()
    pos = np.array(start_m if start_m is not None else [0.0] * len(axes), dtype=float) * 1e3  # mm
    g, feed_mm_min = 0, 0.0
    out: list[np.ndarray] = [pos.copy() * 1e-3]
    for number, raw in enumerate(text.splitlines(), 1):
        line = re.sub(r"\(.*?\)", "", raw.split(";")[0]).strip().upper()
        if not line:
            continue
        words = _GCODE_WORD.findall(line)
        if _GCODE_WORD.sub("", line).strip():
            raise SetpointError(f"{path}:{number}: cannot read {raw.strip()!r}")
        w: dict[str, float] = {}
        for letter, value in words:
            if letter in w:
                raise SetpointError(f"{path}:{number}: {letter} twice in {raw.strip()!r}")
            w[letter] = float(value)
        if "G" in w and w["G"] not in (0, 1, 4, 90):
            raise SetpointError(f"{path}:{number}: G{w['G']:g} not supported (G0, G1, G4, G90)")
        unknown = set(w) - set(axes) - {"G", "F", "P", "N"}
        if unknown:
            raise SetpointError(f"{path}:{number}: word(s) {', '.join(sorted(unknown))} not supported (axes "
                                f"{axes}, G, F, P)")
        if "G" in w:
            if w["G"] == 4:
                dwell_s = w.get("P", 0.0)
                if not 0 <= dwell_s < 1e5:
                    raise SetpointError(f"{path}:{number}: G4 dwell P must be 0..1e5 s")
                out.extend([pos * 1e-3] * round(dwell_s / period_s))
                continue
            if w["G"] in (0, 1):
                g = int(w["G"])
        if "F" in w:
            if not 0 < w["F"] < 1e6:
                raise SetpointError(f"{path}:{number}: feed F must be > 0 mm/min")
            feed_mm_min = w["F"]
        end = np.array([w.get(a, p) for a, p in zip(axes, pos, strict=True)])
        if not np.all(np.isfinite(end)):
            raise SetpointError(f"{path}:{number}: coordinate not finite")
        if g == 1 and feed_mm_min <= 0:
            raise SetpointError(f"{path}:{number}: G1 without a feed (F)")
        speed = (rapid_m_min * 1e3 if g == 0 else feed_mm_min) / 60.0  # mm/s
        out.extend(_trapezoid(pos, end, speed, accel_m_s2 * 1e3, period_s))
        pos = end
    return np.array(out)


def _trapezoid(start: np.ndarray, end: np.ndarray, v_mm_s: float, a_mm_s2: float, period_s: float) -> list:
    """Points [m] of a straight move, one per period, trapezoidal speed from rest to rest."""
    length = float(np.linalg.norm(end - start))
    if length == 0.0:
        return []
    v = min(v_mm_s, math.sqrt(length * a_mm_s2))
    t_acc = v / a_mm_s2
    total = length / v + t_acc
    n = max(1, math.ceil(total / period_s))
    pts = []
    for i in range(1, n + 1):
        t = min(i * period_s, total)
        if t < t_acc:
            s = 0.5 * a_mm_s2 * t * t
        elif t <= total - t_acc:
            s = 0.5 * a_mm_s2 * t_acc * t_acc + v * (t - t_acc)
        else:
            r = total - t
            s = length - 0.5 * a_mm_s2 * r * r
        pts.append((start + (end - start) * min(s / length, 1.0)) * 1e-3)
    return pts
