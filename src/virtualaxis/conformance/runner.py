"""The conformance runner: a CANopen master (the ``canopen`` package) that runs checks against one node.

A check is a function ``fn(ctx) -> str | None`` registered with :func:`check` (id, family, source clause,
stimulus, expected). It raises :class:`Fail` (with what was sent and what came back) or :class:`Skip` (with
the reason); anything it returns is the "got" text of a pass. Every SDO transfer and frame a check sends
or waits for is recorded in ``ctx.trace`` and reported with its result.
"""

from __future__ import annotations

import json
import queue
import re
import threading
import time
import xml.etree.ElementTree as ET
from collections.abc import Callable, Iterable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import can
import canopen

from virtualaxis.master import BoundedSdoClient, SdoTransferOverrun


class Fail(Exception):
    """The node did not behave as the clause requires."""


class Skip(Exception):
    """The check cannot run against this node (the reason says why)."""


class RunError(Exception):
    """The master or the host, not the node, missed the stimulus (e.g. SYNCs not sent in time): an error of
    the run with its cause, never a failure of the node."""


@dataclass(frozen=True)
class Check:
    id: str
    family: str  # planted-defect families: nmt, sdo, pdo, emcy, eds, sm, modes, reaction, rpdo, loss, limits, sync
    clause: str  # source: standard clause / checklist line
    stimulus: str
    expected: str
    fn: Callable[[Context], str | None]


REGISTRY: list[Check] = []


def check(id: str, family: str, clause: str, stimulus: str, expected: str):
    """Register a check (decorator)."""

    def deco(fn: Callable[[Context], str | None]) -> Callable[[Context], str | None]:
        REGISTRY.append(Check(id, family, clause, stimulus, expected, fn))
        return fn

    return deco


@dataclass
class Result:
    id: str
    family: str
    clause: str
    status: str  # pass / fail / skipped / error (of the run: the master or host missed the stimulus)
    detail: str
    trace: list[str] = field(default_factory=list)
    duration_s: float = 0.0
    #: SDO requests of this check that got no answer within the timeout and were sent again (see Context.read)
    sdo_retries: list[str] = field(default_factory=list)
    #: a failure's kind: behaviour (the node did not do what the clause requires), missing-object, sdo-abort,
    #: no-answer, error (the check itself could not go on)
    failure_type: str = ""


class FrameLog:
    """Frames of the node seen by the master: EMCY, heartbeat / boot-up, TPDOs (by COB-ID)."""

    def __init__(self) -> None:
        self.frames: list[tuple[float, int, bytes]] = []
        self._cond = threading.Condition()

    def on_frame(self, can_id: int, data: bytearray, timestamp: float) -> None:
        with self._cond:
            self.frames.append((time.monotonic(), can_id, bytes(data)))
            self._cond.notify_all()

    def mark(self) -> int:
        with self._cond:
            return len(self.frames)

    def since(self, mark: int, cob: int | None = None) -> list[tuple[float, int, bytes]]:
        with self._cond:
            return [f for f in self.frames[mark:] if cob is None or f[1] == cob]

    def wait(self, mark: int, cob: int, pred: Callable[[bytes], bool] | None = None,
             timeout: float = 1.0) -> tuple[float, int, bytes] | None:
        end = time.monotonic() + timeout
        with self._cond:
            while True:
                for f in self.frames[mark:]:
                    if f[1] == cob and (pred is None or pred(f[2])):
                        return f
                left = end - time.monotonic()
                if left <= 0:
                    return None
                self._cond.wait(left)

    def trim(self, keep: int = 20000) -> None:
        with self._cond:
            if len(self.frames) > keep * 2:
                del self.frames[:-keep]


#: lockstep: longest wait for the node's answer to one SYNC [s] (a node that stops answering: the run goes on)
ANSWER_WAIT_S = 0.5
#: lockstep: a wait for ``t`` s of node time whose SYNCs take more than this many times ``t`` of wall time (and
#: at least :data:`STUCK_MIN_S`) is stuck: the master or the host did not send them, an error of the run
LOCKSTEP_WAIT_FACTOR = 100.0
#: lockstep: shortest wall time after which a wait for node time counts as stuck [s]
STUCK_MIN_S = 30.0
#: a wait without SYNC (the node's state changes on the SDO write itself) is over only once this many reads of
#: the node after its timeout showed the old value: a host that stalled for the whole timeout is not a verdict
POLLS_AFTER_TIMEOUT = 3
#: real time: a gap of the master's SYNC / set-point sending longer than this many periods (and
#: :data:`STIMULUS_GAP_MIN_S`) during a check that failed makes the failure an error of the run (the master or
#: the host missed the stimulus, not the node)
STIMULUS_GAP_PERIODS = 5.0
STIMULUS_GAP_MIN_S = 0.02
#: lockstep: SYNCs sent without waiting after one the node did not answer (it may not answer SYNC at all)
UNANSWERED_SKIP = 20


class _SyncThread:
    def __init__(self, thread: threading.Thread, stop: threading.Event):
        self.thread = thread
        self._stop_event = stop

    def stop(self) -> None:
        self._stop_event.set()
        self.thread.join(2.0)


class _FrameTap(can.Listener):
    """Frames of the logged COB-IDs into a :class:`FrameLog`, straight from the bus notifier."""

    def __init__(self, frames: FrameLog, cobs: set[int]):
        self.frames = frames
        self.cobs = cobs

    def on_message_received(self, msg: can.Message) -> None:
        if not msg.is_extended_id and not msg.is_error_frame and msg.arbitration_id in self.cobs:
            self.frames.on_frame(msg.arbitration_id, msg.data, msg.timestamp)


#: objects every CiA 301 / CiA 402 drive has (CiA 301 7.5.2, CiA 402 mandatory objects); any other object a
#: check needs and the node lacks makes that check a skip
MANDATORY_OBJECTS = frozenset({0x1000, 0x1001, 0x1018, 0x6040, 0x6041, 0x6060, 0x6061, 0x6502})
#: SDO abort codes that say the object / sub-index does not exist
NO_OBJECT_ABORTS = frozenset({0x06020000, 0x06090011})
_MISSING_IN_EDS = re.compile(r"(0x[0-9A-Fa-f]{1,4}|[0-9A-Fa-f]{4}|\d+) was not found in Object Dictionary")


def missing_object(exc: BaseException, ctx: Context | None = None) -> int | None:
    """The index of the object whose absence ``exc`` reports (canopen's KeyError for an object the EDS lacks,
    or an SDO abort 0x06020000 / 0x06090011 from the node), else None."""
    if isinstance(exc, KeyError):
        if re.search(r"Subindex \S+ was not found", str(exc)):
            return -1  # (canopen does not name the object of a missing sub-index)
        m = _MISSING_IN_EDS.search(str(exc))
        if m:
            text = m.group(1)
            return int(text, 16) if text.lower().startswith("0x") or len(text) == 4 else int(text)
        return None
    if isinstance(exc, canopen.SdoAbortedError) and exc.code in NO_OBJECT_ABORTS and ctx is not None \
            and ctx.last_abort is not None and ctx.last_abort[2] == exc.code:
        return ctx.last_abort[0]
    return None


class MatchedSdoClient(BoundedSdoClient):
    """The suite's SDO client: an answer is taken only by the exchange it answers. A frame of the server that
    does not answer the request last sent is set aside (kept in :attr:`set_aside`), never taken for it:

    - an initiate (expedited / segmented / block) is answered by its own response type carrying the request's
      index and sub-index, or by an abort carrying them;
    - a segment request is answered by a segment response with the request's toggle bit, or by an abort of the
      transfer (its index and sub-index);
    - frames already queued when a request is sent answer earlier exchanges (late answers, answers to another
      client on the same COB-IDs, the second answer to a request sent again) and are dropped with it.

    Within block transfers (sub-block frames carry no command specifier) only aborts are matched."""

    def __init__(self, rx_cobid: int, tx_cobid: int, od, *, transfer_timeout_s: float | None = None):
        super().__init__(rx_cobid, tx_cobid, od, transfer_timeout_s=transfer_timeout_s)
        self._match_lock = threading.Lock()
        self._mux: bytes | None = None  # index and sub-index of the transfer under way
        self._scs: set[int] | None = None  # server command specifiers that answer the pending request
        self._toggle: int | None = None  # toggle bit the answer to a segment request carries
        self._mux_checked = False  # the pending request is an initiate: its answer carries the mux
        self._block: str | None = None  # a block transfer under way: "up" / "down"
        #: frames of the server that answered no pending request (hex), oldest first
        self.set_aside: list[str] = []

    def send_request(self, request) -> None:
        b = bytes(request)
        ccs = b[0] >> 5 if b else -1
        with self._match_lock:
            self._toggle, self._mux_checked = None, False
            if ccs == 4:  # an abort of the client (a block download's segments never start with 0x80)
                self._mux = self._scs = self._block = None
            elif self._block == "down" and self._scs is None:
                pass  # a sub-block segment (its first byte is its sequence number) or the end of the download
            elif self._block == "up" and ccs == 5:
                self._scs = None  # start / acknowledge / end of a block upload: sub-block frames answer them
                if b[0] & 0x03 == 1:
                    self._block = None
            elif ccs in (1, 2) or (ccs == 6 and b[0] & 0x01 == 0) or (ccs == 5 and b[0] & 0x03 == 0):
                self._mux, self._mux_checked = b[1:4], True
                self._scs = {1: {3}, 2: {2}, 6: {5}, 5: {6, 2}}[ccs]  # (block upload may switch to segmented)
                self._block = {5: "up", 6: "down"}.get(ccs)
            elif ccs in (0, 3):
                self._scs, self._toggle = {0: {1}, 3: {0}}[ccs], b[0] & 0x10
            else:
                self._scs = None
            while True:  # what is queued now answered an earlier exchange
                try:
                    stale = self.responses.get_nowait()
                except queue.Empty:
                    break
                self.set_aside.append(stale.hex(" "))
        super().send_request(request)

    def answers(self, data: bytes) -> bool:
        """Whether the server frame ``data`` answers the request last sent."""
        if len(data) != 8:
            return True  # (malformed: reported as such by the client)
        if data[0] == 0x80:
            return self._mux is None or data[1:4] == self._mux
        if self._scs is None:
            return True
        if data[0] >> 5 not in self._scs:
            return False
        if self._mux_checked:
            return data[1:4] == self._mux
        return self._toggle is None or data[0] & 0x10 == self._toggle

    def on_response(self, can_id: int, data, timestamp: float) -> None:
        frame = bytes(data)
        with self._match_lock:
            if not self.answers(frame):
                self.set_aside.append(frame.hex(" "))
                return
            self.responses.put(frame)
            if self._block == "down":
                if self._mux_checked:  # the initiate's answer: the segments follow
                    self._mux_checked, self._scs = False, None
                elif len(frame) == 8 and (frame[0] == 0x80 or frame[0] & 0xE3 == 0xA1):
                    self._block = None  # aborted, or the end of the download answered


def install_matched_sdo(node) -> MatchedSdoClient:
    """Replace ``node``'s default SDO client (before ``network.add_node(node)``) by a :class:`MatchedSdoClient`
    on the same COB-IDs; returns it."""
    old = node.sdo
    client = MatchedSdoClient(old.rx_cobid, old.tx_cobid, node.object_dictionary)
    client.RESPONSE_TIMEOUT = old.RESPONSE_TIMEOUT
    node.sdo_channels[:] = [client if c is old else c for c in node.sdo_channels]
    node.sdo = client
    return client


class Context:
    """What a check works with: the network, the node (``BaseNode402`` on the EDS), the EDS' dictionary,
    frame logs and helpers that record every exchange in :attr:`trace`."""

    def __init__(self, network: canopen.Network, node_id: int, eds: str, *, sdo_timeout_s: float = 1.0,
                 units_per_mm: float = 1000.0, sync_period_s: float = 0.001, lockstep: bool = True):
        self.net = network
        self.node_id = node_id
        self.eds = eds
        self.node = canopen.BaseNode402(node_id, eds)
        # transfers that never end are cut, short frames named, answers matched to their exchange
        self.sdo_client = install_matched_sdo(self.node)
        self.node.sdo.RESPONSE_TIMEOUT = sdo_timeout_s
        network.add_node(self.node)
        self.od = self.node.object_dictionary
        self.units_per_mm = units_per_mm
        self.sync_period_s = sync_period_s
        self.frames = FrameLog()
        self.trace: list[str] = []
        self._sync_task = None
        self.syncs = 0  # SYNCs sent
        self._answer_skip: dict[int, int] = {}  # COB-ID -> SYNCs not to wait for it (it did not answer lately)
        self._pdos_on = False  # the latest NMT command was a start (PDOs may answer SYNC)
        self.emcy_cob = 0x80 + node_id
        self.hb_cob = 0x700 + node_id
        self.logged_cobs = {self.emcy_cob, self.hb_cob, 0x180 + node_id, 0x280 + node_id, 0x380 + node_id,
                            0x480 + node_id}
        # every frame of these COB-IDs, as received, before (and apart from) canopen's own consumers: a frame
        # they cannot parse (a 3-byte EMCY) is still seen and judged by the checks
        self._listener = _FrameTap(self.frames, self.logged_cobs)
        notifier = getattr(network, "notifier", None)
        self._tapped = notifier is not None
        if self._tapped:
            notifier.add_listener(self._listener)
        else:
            for cob in self.logged_cobs:
                network.subscribe(cob, self.frames.on_frame)
        self.lockstep = lockstep  # the node advances only on SYNC: timings are judged in SYNC counts
        self.last_abort: tuple[int, int, int] | None = None  # (index, sub, abort code) of the latest SDO abort
        self.state: dict[str, Any] = {}  # facts one check learns for later ones (e.g. PDO layout)
        self.sdo_timeout_s = sdo_timeout_s
        self.retries: list[str] = []  # this check's SDO requests sent again after a timeout
        self.late_answers_due = 0  # requests that timed out and may still be answered (across checks)
        self.streams = 0  # set-point streams sending SYNC besides start_sync (see periodic_sender)
        #: real time: the longest gap of the master's periodic SYNC / set-point sending in this check [s]
        self.stimulus_gap_s = 0.0
        self._last_periodic: float | None = None

    @property
    def syncs_running(self) -> bool:
        """SYNCs are being sent periodically (:meth:`start_sync` or a set-point stream)."""
        return self._sync_task is not None or self.streams > 0

    def periodic_sent(self, restart: bool = False) -> None:
        """A periodic sender (SYNC, set-point stream) sent its frame now: the longest gap between two is kept in
        :attr:`stimulus_gap_s` (``restart``: the first frame of a new sender, no gap before it)."""
        now = time.monotonic()
        if self._last_periodic is not None and not restart:
            self.stimulus_gap_s = max(self.stimulus_gap_s, now - self._last_periodic)
        self._last_periodic = now

    def stimulus_missed(self) -> str | None:
        """Real time: why the master missed its stimulus in this check (a gap of its periodic sending longer than
        :data:`STIMULUS_GAP_PERIODS` periods), else None. Lockstep: None (the node's time waits for SYNC)."""
        limit = max(STIMULUS_GAP_PERIODS * self.sync_period_s, STIMULUS_GAP_MIN_S)
        if self.lockstep or self.stimulus_gap_s <= limit:
            return None
        return (f"the master's periodic SYNC / set-point sending paused {self.stimulus_gap_s * 1e3:.1f} ms (more "
                f"than {limit * 1e3:.1f} ms) during the check: the master or the host missed the stimulus")

    def log_frames(self, cob: int) -> None:
        """Record the frames of ``cob`` in :attr:`frames` too (once, whatever the number of calls)."""
        if cob in self.logged_cobs:
            return
        self.logged_cobs.add(cob)
        if not self._tapped:
            self.net.subscribe(cob, self.frames.on_frame)

    def _sdo(self, op: Callable[[], Any], what: str) -> Any:
        """An expedited SDO exchange with one retry after a timeout, as a field master does: a request or its
        answer lost once (a host that stalled for longer than the timeout, a frame dropped by a loaded
        machine's socket) is not taken for the behaviour under check. Every retry is noted in the check's
        trace and in :attr:`Result.sdo_retries`, and the summary counts them, so a node that drops requests
        is still seen; a second timeout fails the check ("no SDO answer").

        A request that timed out may still be answered, late: that answer then arrives during a later
        exchange, which sees a response of the wrong kind or for another object. Only while such a late
        answer is due (one per timeout) is that exchange sent again once (noted the same way); any other
        wrong answer fails the check."""
        try:
            return op()
        except canopen.SdoCommunicationError as exc:
            text = str(exc)
            if "No SDO response" in text:
                self.late_answers_due += 1
                self.retries.append(what)
                self.note(f"{what}: no answer in {self.sdo_timeout_s:g} s, sent again")
            elif self.late_answers_due and ("Unexpected response" in text or " instead" in text):
                self.late_answers_due -= 1
                self.retries.append(what)
                self.note(f"{what}: a late answer to an earlier request arrived ({text}), sent again")
            else:
                raise
        return op()

    # ------------------------------------------------------------------ trace helpers
    def note(self, text: str) -> None:
        self.trace.append(text)

    def read(self, index: int, sub: int = 0) -> int:
        """SDO upload (raw value per the EDS type); an abort raises ``canopen.SdoAbortedError``."""
        var = self._var(index, sub)
        try:
            value = self._sdo(lambda: var.raw, f"SDO read 0x{index:04X}:{sub}")
        except canopen.SdoAbortedError as exc:
            self.last_abort = (index, sub, exc.code)
            self.note(f"SDO read 0x{index:04X}:{sub} -> abort 0x{exc.code:08X}")
            raise
        self.note(f"SDO read 0x{index:04X}:{sub} -> {value!r}")
        return value

    def _var(self, index: int, sub: int):
        """The master's SDO variable of ``index:sub`` (a plain object's sub 0 is the object itself)."""
        return self.node.sdo[index] if sub == 0 and not self._is_container(index) else self.node.sdo[index][sub]

    def poll(self, index: int, sub: int = 0) -> Any:
        """SDO upload in a polling loop: like :meth:`read` (one retry after a timeout, noted) but without a
        trace line per poll."""
        var = self._var(index, sub)
        try:
            return self._sdo(lambda: var.raw, f"SDO read 0x{index:04X}:{sub}")
        except canopen.SdoAbortedError as exc:
            self.last_abort = (index, sub, exc.code)
            raise

    def write(self, index: int, sub: int, value: Any) -> None:
        var = self._var(index, sub)
        try:
            self._sdo(lambda: setattr(var, "raw", value), f"SDO write 0x{index:04X}:{sub} = {value!r}")
        except canopen.SdoAbortedError as exc:
            self.last_abort = (index, sub, exc.code)
            self.note(f"SDO write 0x{index:04X}:{sub} = {value!r} -> abort 0x{exc.code:08X}")
            raise
        self.note(f"SDO write 0x{index:04X}:{sub} = {value!r} -> ok")

    def raw_read(self, index: int, sub: int) -> bytes:
        """SDO upload of raw bytes (no EDS needed for the entry)."""
        return self.sized_read(index, sub)[0]

    def sized_read(self, index: int, sub: int) -> tuple[bytes, int | None]:
        """SDO upload of raw bytes as the node sent them, and the size it indicated (None: an expedited answer
        without a size, CiA 301 allows it): not cut to the EDS' data type, as ``SdoClient.upload`` cuts a longer
        answer."""
        def upload() -> tuple[bytes, int | None]:
            with self.node.sdo.open(index, sub, buffering=0) as fp:
                size = fp.size
                data = fp.read()
            return data, size

        try:
            data, size = self._sdo(upload, f"SDO upload 0x{index:04X}:{sub}")
        except canopen.SdoAbortedError as exc:
            self.note(f"SDO upload 0x{index:04X}:{sub} -> abort 0x{exc.code:08X}")
            raise
        self.note(f"SDO upload 0x{index:04X}:{sub} -> {data.hex(' ')}")
        return data, size

    def raw_write(self, index: int, sub: int, data: bytes) -> None:
        try:
            self._sdo(lambda: self.node.sdo.download(index, sub, data),
                      f"SDO download 0x{index:04X}:{sub} [{data.hex(' ')}]")
        except canopen.SdoAbortedError as exc:
            self.note(f"SDO download 0x{index:04X}:{sub} [{data.hex(' ')}] -> abort 0x{exc.code:08X}")
            raise
        self.note(f"SDO download 0x{index:04X}:{sub} [{data.hex(' ')}] -> ok")

    def raw_sdo(self, request: bytes, timeout: float = 1.0) -> bytes | None:
        """Send a raw SDO request frame (8 bytes) and return the response (or None)."""
        got = self._sdo_exchange(request, timeout, first_only=True)
        self.note(f"SDO raw {request.hex(' ')} -> {got[0].hex(' ') if got else 'no answer'}")
        return got[0] if got else None

    def sdo_answers(self, request: bytes, listen_s: float) -> list[bytes]:
        """Send a raw SDO request frame and return every frame on the node's SDO answer COB-ID in ``listen_s``."""
        got = self._sdo_exchange(request, listen_s, first_only=False)
        self.note(f"SDO raw {request.hex(' ')} -> {len(got)} frame(s) in {listen_s:g} s")
        return got

    def _sdo_exchange(self, request: bytes, wait_s: float, *, first_only: bool) -> list[bytes]:
        """The frames on 0x580 + id after ``request`` went to 0x600 + id: until the first (``first_only``) or
        for ``wait_s``, at most ``wait_s``."""
        got: list[bytes] = []
        ev = threading.Event()

        def on(can_id: int, data: bytearray, ts: float) -> None:
            got.append(bytes(data))
            ev.set()

        cob_tx = 0x580 + self.node_id
        self.net.subscribe(cob_tx, on)
        try:
            self.net.send_message(0x600 + self.node_id, request)
            if first_only:
                ev.wait(wait_s)
            else:
                time.sleep(wait_s)
        finally:
            self.net.unsubscribe(cob_tx, on)  # (only this callback: canopen's own SDO client stays subscribed)
        return list(got)

    def expect_abort(self, code: int | Iterable[int], fn: Callable[[], Any], what: str) -> int:
        codes = {code} if isinstance(code, int) else set(code)
        try:
            fn()
        except canopen.SdoAbortedError as exc:
            if exc.code in codes:
                return exc.code
            raise Fail(f"{what}: abort 0x{exc.code:08X}, expected {' or '.join(f'0x{c:08X}' for c in codes)}") from None
        raise Fail(f"{what}: accepted, expected abort {' or '.join(f'0x{c:08X}' for c in codes)}")

    def _is_container(self, index: int) -> bool:
        obj = self.od.get(index) if index in self.od else None
        return obj is not None and not isinstance(obj, canopen.objectdictionary.Variable)

    def nmt(self, command: int) -> None:
        self._answer_skip.clear()  # (a new NMT state: PDOs may start or stop)
        self._pdos_on = command == 0x01  # only an OPERATIONAL node answers SYNC with PDOs
        self.note(f"NMT 0x{command:02X} -> node {self.node_id}")
        self.net.send_message(0, bytes((command, self.node_id)))

    # ------------------------------------------------------------------ CiA 402 helpers
    def sw(self) -> int:
        return self.read(0x6041)

    def deadline(self, timeout_s: float) -> Callable[[], bool]:
        """A timeout of ``timeout_s`` of the node's time. Returns "expired?", to be called after each look at
        the node.

        Real time: wall time. Lockstep while SYNCs run: ``timeout_s`` / SYNC period SYNCs sent (a loaded master
        or host slows the node's time down with its SYNCs); when those SYNCs take more than
        :data:`LOCKSTEP_WAIT_FACTOR` x ``timeout_s`` (at least :data:`STUCK_MIN_S`) of wall time, the call
        raises :class:`RunError` (the master or the host is stuck, not the node). Lockstep without SYNC (the
        node's state changes on the SDO exchange itself): expired once ``timeout_s`` of wall time has passed
        and :data:`POLLS_AFTER_TIMEOUT` more looks at the node were made since."""
        t0, s0 = time.monotonic(), self.syncs
        need = timeout_s / self.sync_period_s
        stuck_s = max(LOCKSTEP_WAIT_FACTOR * timeout_s, STUCK_MIN_S)
        late_looks = [0]

        def expired() -> bool:
            waited = time.monotonic() - t0
            if not self.lockstep:
                return waited > timeout_s
            sent = self.syncs - s0
            if sent >= need:
                return True
            if sent == 0 and not self.syncs_running:  # no SYNC: the wait is not for motion
                if waited <= timeout_s:
                    return False
                late_looks[0] += 1
                return late_looks[0] > POLLS_AFTER_TIMEOUT
            if waited > stuck_s:
                raise RunError(f"{sent} of {need:.0f} SYNCs ({timeout_s:g} s of node time) sent in {waited:.1f} s "
                               "of wall time: the master or the host is too slow, the node's time stood still")
            return False

        return expired

    def sleep(self, seconds: float) -> None:
        """Let ``seconds`` of the node's time pass (see :meth:`deadline`)."""
        expired = self.deadline(seconds)
        time.sleep(seconds)  # (SYNCs are never sent faster than their period: node time <= wall time)
        while not expired():
            time.sleep(0.002)

    def wait_sw(self, mask: int, value: int, timeout: float = 1.0, what: str = "") -> int:
        expired = self.deadline(timeout)
        sw = self.poll(0x6041)
        while sw & mask != value:
            if expired():
                self.note(f"statusword 0x{sw:04X}, waited for & 0x{mask:04X} == 0x{value:04X}")
                raise Fail(f"{what or 'statusword'}: 0x{sw:04X} after {timeout:g} s, expected "
                           f"(sw & 0x{mask:04X}) == 0x{value:04X}")
            time.sleep(0.005)
            sw = self.poll(0x6041)
        self.note(f"statusword 0x{sw:04X}")
        return sw

    def enable(self) -> None:
        """Fault reset if needed, then shutdown / switch on / enable operation by SDO controlword."""
        sw = self.poll(0x6041)
        if sw & 0x4F == 0x08:
            self.write(0x6040, 0, 0x00)
            self.write(0x6040, 0, 0x80)
            self.wait_sw(0x4F, 0x40, 1.0, "fault reset")
        for cw, mask, expect in ((0x06, 0x6F, 0x21), (0x07, 0x6F, 0x23), (0x0F, 0x6F, 0x27)):
            self.write(0x6040, 0, cw)
            self.wait_sw(mask, expect, 1.0, f"controlword 0x{cw:02X}")

    def disable(self) -> None:
        try:
            self.node.sdo[0x6040].raw = 0x00
        except (canopen.SdoAbortedError, canopen.SdoCommunicationError):
            pass

    def emcy_codes(self, mark: int) -> list[int]:
        return [int.from_bytes(d[0:2], "little") for _, _, d in self.frames.since(mark, self.emcy_cob)]

    def wait_emcy(self, mark: int, code: int | None, timeout: float = 1.0) -> bytes | None:
        f = self.frames.wait(mark, self.emcy_cob,
                             None if code is None else (lambda d: int.from_bytes(d[0:2], "little") == code), timeout)
        return None if f is None else f[2]

    # ------------------------------------------------------------------ SYNC
    def start_sync(self, period_s: float | None = None) -> None:
        """SYNC every ``period_s`` (default :attr:`sync_period_s`) until :meth:`stop_sync`. Lockstep: a SYNC is
        sent only once the node answered the previous one (its TPDO1, when TPDO1 answers SYNC), never faster
        than the period: a loaded master or host slows the node's time down but never makes it skip cycles.
        Real time: the gaps between SYNCs are kept (:meth:`periodic_sent`, :meth:`stimulus_missed`)."""
        if self._sync_task is not None:
            return
        period = period_s or self.sync_period_s
        stop = threading.Event()

        def run() -> None:
            nxt = time.monotonic()
            first = True
            while not stop.is_set():
                # lockstep: waits for the node's answer; real time: the SYNC only
                self.sync_once(answer_cob=0x180 + self.node_id if self.lockstep else None)
                self.periodic_sent(restart=first)
                first = False
                nxt += period
                delay = nxt - time.monotonic()
                if delay > 0:
                    stop.wait(delay)
                else:
                    nxt = time.monotonic()

        thread = threading.Thread(target=run, daemon=True, name="conformance-sync")
        thread.start()
        self._sync_task = _SyncThread(thread, stop)

    def stop_sync(self) -> None:
        if self._sync_task is not None:
            self._sync_task.stop()
            self._sync_task = None

    def sync_once(self, answer_cob: int | None = None) -> None:
        """One SYNC (counted in :attr:`syncs`). Lockstep with ``answer_cob``: then wait (at most
        :data:`ANSWER_WAIT_S`) for that frame, the node's answer, once the node has answered a SYNC with it."""
        mark = self.frames.mark() if answer_cob is not None and self.lockstep and self._pdos_on else None
        self.net.send_message(0x80, b"")
        self.syncs += 1
        if mark is None:
            return
        skip = self._answer_skip.get(answer_cob, 0)
        if skip:  # the node did not answer with this frame lately: not waited for, asked again now and then
            self._answer_skip[answer_cob] = skip - 1
            return
        end = time.monotonic() + ANSWER_WAIT_S
        while self.frames.wait(mark, answer_cob, None, 0.01) is None:
            if not self._pdos_on:  # an NMT command meanwhile: no answer to wait for
                return
            if time.monotonic() > end:
                self._answer_skip[answer_cob] = UNANSWERED_SKIP
                return

    # ------------------------------------------------------------------ units
    def mm(self, x_mm: float) -> int:
        return int(round(x_mm * self.units_per_mm))


def boot(ctx: Context, *, timeout: float = 3.0) -> None:
    """Reset node and wait for the boot-up; heartbeat 50 ms so the master sees the NMT state."""
    ctx.stop_sync()
    mark = ctx.frames.mark()
    ctx.nmt(0x81)
    if ctx.frames.wait(mark, ctx.hb_cob, lambda d: d[:1] == b"\x00", timeout) is None:
        raise Fail("no boot-up frame after NMT Reset Node")
    time.sleep(0.05)


#: SDO exchanges in a row without a valid answer (timeouts, malformed frames) after which a run stops: a working
#: node on a loaded host leaves one or two unanswered between valid ones; this many means it has stopped answering
MAX_UNANSWERED_SDO = 20


#: transfers the node began (answered the initiate) and then left without an answer, after which a run stops
#: (one is retried: a lost frame; the same again is a server that stops in the middle of its transfers)
MAX_STALLED_SDO = 2


class RunStopped(Exception):  # noqa: N818 - the name says what happened
    """The run cannot go on: the node's SDO server is broken (a transfer that never ends, or
    :data:`MAX_UNANSWERED_SDO` exchanges left unanswered), or the node no longer answers after a check failed. An
    error of the run, not a result of a check; the results so far are in :attr:`results`."""

    def __init__(self, message: str, results: list[Result]):
        super().__init__(message)
        self.results = results


def _run_stopped(ctx: Context, chk: Check, results: list[Result]) -> RunStopped | None:
    client = ctx.sdo_client
    if client.overrun:
        why = client.overrun
    elif client.stalled >= MAX_STALLED_SDO:
        why = (f"{client.stalled} SDO transfers begun by the node and left unfinished (no answer within "
               f"{ctx.sdo_timeout_s:g} s; the last: {client.last_failure}): the node's SDO server does not finish "
               "its transfers")
    elif client.unanswered_in_row >= MAX_UNANSWERED_SDO:
        why = (f"{client.unanswered_in_row} SDO exchanges in a row without a valid answer within "
               f"{ctx.sdo_timeout_s:g} s (the last: "
               f"{client.last_failure}): the node's SDO server has stopped working")
    else:
        return None
    return RunStopped(f"node {ctx.node_id}: {why}; the run stopped in {chk.id} after {len(results)} check(s)",
                      results)


def _fault_state(ctx: Context) -> str:
    """After a failed check: ``"; after the check the node shows FAULT (...)"`` when its statusword tells a fault
    (FAULT or FAULT REACTION ACTIVE, with 0x603F where the EDS lists it), so that a message about a move that did
    not start is read with the fault that stopped it; "" otherwise or when the node does not answer."""
    try:
        sw = int(ctx.poll(0x6041))
    except Exception:  # noqa: BLE001 - a hint only: the failure stands as it is
        return ""
    state = {0x08: "FAULT", 0x0F: "FAULT REACTION ACTIVE"}.get(sw & 0x4F)
    if state is None:
        return ""
    code = ""
    if 0x603F in ctx.od:
        try:
            code = f", error code 0x603F = 0x{int(ctx.poll(0x603F)):04X}"
        except Exception:  # noqa: BLE001
            code = ""
    return f"; after the check the node shows {state} (statusword 0x{sw:04X}{code})"


def run_checks(ctx: Context, checks: list[Check], *, progress: Callable[[Result], None] | None = None) -> list[Result]:
    """Run ``checks`` in order; a check's exception other than Fail/Skip is a failure naming it. A node whose
    SDO server is broken ends the run with :class:`RunStopped` (bounded by the SDO timeout: one transfer lasts
    at most ``master.TRANSFER_TIMEOUTS`` timeouts, :data:`MAX_STALLED_SDO` transfers left unfinished or
    :data:`MAX_UNANSWERED_SDO` timeouts in a row end the run)."""
    results: list[Result] = []
    for chk in checks:
        stopped = _run_stopped(ctx, chk, results)  # (also after the clean-up of the check before)
        if stopped is not None:
            raise stopped
        ctx.trace = []
        ctx.retries = []
        ctx.last_abort = None
        ctx.stimulus_gap_s = 0.0
        aside0 = len(ctx.sdo_client.set_aside)
        t0 = time.monotonic()
        failure_type = ""
        try:
            got = chk.fn(ctx)
            status, detail = "pass", got or "as expected"
        except SdoTransferOverrun:
            status, detail = "fail", "the node's SDO server does not finish its transfers"
        except Fail as exc:
            status, detail, failure_type = "fail", str(exc), "behaviour"
        except Skip as exc:
            status, detail = "skipped", str(exc)
        except RunError as exc:
            status, detail, failure_type = "error", str(exc), "run"
        except (KeyError, canopen.SdoAbortedError) as exc:
            index = missing_object(exc, ctx)
            how = "the EDS lists no" if isinstance(exc, KeyError) else "the node has no (SDO abort " \
                f"0x{exc.code:08X})"
            if index == -1:
                status, detail = "skipped", f"the EDS lists no {str(exc).strip(chr(39))} (a sub-index this check " \
                    "needs; optional)"
            elif index is not None and index not in MANDATORY_OBJECTS:
                status, detail = "skipped", f"{how} object 0x{index:04X}, which this check needs (optional)"
            elif index is not None:
                status, detail, failure_type = "fail", f"{how} object 0x{index:04X}, mandatory", "missing-object"
            elif isinstance(exc, canopen.SdoAbortedError):
                status, detail = "fail", f"unexpected SDO abort 0x{exc.code:08X} ({exc})"
                failure_type = "sdo-abort"
            else:
                status, detail, failure_type = "fail", f"{type(exc).__name__}: {exc}", "error"
        except canopen.SdoCommunicationError as exc:
            status, detail, failure_type = "fail", f"no SDO answer: {exc}", "no-answer"
        except Exception as exc:  # noqa: BLE001 - a check must never stop the run
            status, detail, failure_type = "fail", f"{type(exc).__name__}: {exc}", "error"
        finally:
            ctx.stop_sync()
        stopped = _run_stopped(ctx, chk, results)
        if stopped is not None:
            raise stopped
        aside = ctx.sdo_client.set_aside[aside0:]
        if aside:
            ctx.note(f"{len(aside)} SDO frame(s) answering no pending request set aside: " + "; ".join(aside[:5]))
        missed = ctx.stimulus_missed() if status == "fail" else None
        if missed is not None:  # real time: not the node's failure when the master did not send its stimulus
            ctx.note(f"failure not judged: {detail}")
            status, detail, failure_type = "error", missed, "run"
        elif status == "fail" and failure_type == "behaviour":
            detail += _fault_state(ctx)
        res = Result(chk.id, chk.family, chk.clause, status, detail, list(ctx.trace[-40:]),
                     time.monotonic() - t0, list(ctx.retries), failure_type)
        results.append(res)
        ctx.frames.trim()
        if progress is not None:
            progress(res)
        if status in ("fail", "error"):
            try:  # leave the node in a known state for the next check
                ctx.disable()
                boot(ctx)
            except Exception:  # noqa: BLE001
                pass
            gone = _node_gone(ctx)
            if gone is not None:
                raise RunStopped(f"node {ctx.node_id}: {gone}; the run stopped after {chk.id} failed "
                                 f"({len(results)} check(s) run)", results)
    return results


def _node_gone(ctx: Context) -> str | None:
    """After a failed check: whether the node still answers an SDO read of 0x1000 (with the run's SDO timeout
    and retries); a node that has gone (its process ended, unplugged) would fail every later check as if it
    behaved wrongly, so its absence ends the run instead. None while it answers (an abort is an answer too)."""
    try:
        ctx.read(0x1000)
    except canopen.SdoAbortedError:
        return None
    except (canopen.SdoCommunicationError, SdoTransferOverrun) as exc:
        return f"does not answer any more (SDO read 0x1000: {exc})"
    return None


def line(res: Result) -> str:
    trace = " | ".join(res.trace[-3:])
    return f"{res.id:<14} {res.status.upper():<7} {res.detail}" + (f"  [{trace}]" if trace else "")


def summary(results: list[Result]) -> dict[str, int]:
    """Checks per status, and the SDO requests sent again after a timeout (``sdo_retries``)."""
    out = {"pass": 0, "fail": 0, "skipped": 0, "error": 0, "sdo_retries": 0}
    for r in results:
        out[r.status] += 1
        out["sdo_retries"] += len(r.sdo_retries)
    return out


def write_json(path: Path, results: list[Result], meta: dict) -> None:
    path.write_text(json.dumps({"meta": meta, "summary": summary(results),
                                "checks": [asdict(r) for r in results]}, indent=2))


#: pacing probe: heartbeat period asked for [ms], SYNCs sent first, then the wall time without SYNC [s] and the
#: heartbeats in it that show a node keeping its own time (20 ms: ~15 expected of a node in real time, half of
#: them enough)
PACING_PROBE_HEARTBEAT_MS = 20
PACING_PROBE_SYNCS = 5
PACING_PROBE_QUIET_S = 0.3
PACING_PROBE_OWN_TIME = 8


#: how long the master listens for further answers to its one SDO request of :func:`duplicate_node_problem` [s]
DUPLICATE_LISTEN_S = 0.3


def duplicate_node_problem(ctx: Context) -> str | None:
    """Two nodes with the node-ID on the bus both answer every SDO request: the checks would judge whichever
    answer comes first. Asked before the checks: one SDO read of 0x1018:0 (mandatory; no check before reads it,
    so a late answer to an earlier request is not counted), every answer on 0x580 + id that carries 0x1018:0
    (an abort too) counted for :data:`DUPLICATE_LISTEN_S`. Returns what is wrong when more than one came."""
    mux = b"\x18\x10\x00"
    answers = [a for a in ctx.sdo_answers(b"\x40" + mux + b"\x00\x00\x00\x00", DUPLICATE_LISTEN_S)
               if a[1:4] == mux]
    cob = 0x580 + ctx.node_id
    if len(answers) <= 1:
        return None
    return (f"{len(answers)} answers on COB-ID 0x{cob:03X} to one SDO request: more than one node on this bus has "
            f"node-ID {ctx.node_id}; give each node a node-ID of its own")


def pacing_problem(ctx: Context) -> str | None:
    """Whether the node's clock is the one the pacing judges timings on. Asked before the checks: after a boot and
    a few SYNCs, with the heartbeat at :data:`PACING_PROBE_HEARTBEAT_MS` and no SYNC for
    :data:`PACING_PROBE_QUIET_S`, a lockstep node sends no heartbeat (its clock waits for the next SYNC); one that
    sends :data:`PACING_PROBE_OWN_TIME` or more runs on its own clock.

    - Lockstep pacing judges every timing in node time (SYNC counts): a node that keeps its own time would fail
      the timed checks (``301-HB-1``, ``301-PDO-7``) for the master's mistake.
    - Real-time pacing judges on the wall clock: a node that sends no heartbeat at all without SYNC waits for
      SYNC, and would fail every check that waits without sending SYNC (the heartbeat, SYNC loss).

    Returns what to do then, else None."""
    try:
        boot(ctx)
        ctx.write(0x1017, 0, PACING_PROBE_HEARTBEAT_MS)
        for _ in range(PACING_PROBE_SYNCS):
            ctx.sync_once()
            time.sleep(0.002)
        ctx.read(0x1000)  # (answered after the SYNCs: what the node sent before them has arrived by now)
        mark = ctx.frames.mark()
        time.sleep(PACING_PROBE_QUIET_S)
        n = len(ctx.frames.since(mark, ctx.hb_cob))
        boot(ctx)
    except (Fail, KeyError, canopen.SdoAbortedError, canopen.SdoCommunicationError, SdoTransferOverrun):
        return None  # (a node that does not boot or answer, an EDS without 0x1017: the checks report that)
    if ctx.lockstep and n >= PACING_PROBE_OWN_TIME:
        return (f"node {ctx.node_id} keeps its own time ({n} heartbeats of {PACING_PROBE_HEARTBEAT_MS} ms in "
                f"{PACING_PROBE_QUIET_S:g} s without SYNC), but --pacing lockstep judges timings in SYNCs: run with "
                "--pacing realtime, or serve the node with --lockstep")
    if not ctx.lockstep and n == 0:
        return (f"node {ctx.node_id} waits for SYNC (no heartbeat of {PACING_PROBE_HEARTBEAT_MS} ms in "
                f"{PACING_PROBE_QUIET_S:g} s without SYNC: served with --lockstep), but --pacing realtime judges "
                "timings on the wall clock: run with --pacing lockstep, or serve the node without --lockstep")
    return None


def identity(ctx: Context) -> dict[str, str]:
    """The node's identity for a report: device type 0x1000, identity 0x1018:1..4, names 0x1008 / 0x100A (those
    it answers)."""
    out: dict[str, str] = {"node_id": str(ctx.node_id)}
    for key, index, sub in (("device_type", 0x1000, 0), ("vendor_id", 0x1018, 1), ("product_code", 0x1018, 2),
                            ("revision", 0x1018, 3), ("serial", 0x1018, 4)):
        try:
            out[key] = f"0x{int.from_bytes(ctx.node.sdo.upload(index, sub)[:4], 'little'):08X}"
        except Exception:  # noqa: BLE001 - an identity entry the node lacks is left out
            pass
    for key, index in (("device_name", 0x1008), ("software_version", 0x100A)):
        try:
            out[key] = ctx.node.sdo.upload(index, 0).decode("latin-1").rstrip("\x00")
        except Exception:  # noqa: BLE001
            pass
    return out


def write_junit(path: Path, results: list[Result], name: str = "virtualaxis.conformance",
                properties: dict[str, Any] | None = None) -> None:
    """One testcase per check: a failure with its ``type`` and message, a skip with its reason, and in
    ``system-out`` the clause, the outcome and every exchange and measured value the check recorded;
    ``properties``: the node's identity and the run's pacing."""
    s = summary(results)
    suite = ET.Element("testsuite", name=name, tests=str(len(results)), failures=str(s["fail"]),
                       skipped=str(s["skipped"]), errors=str(s["error"]),
                       time=f"{sum(r.duration_s for r in results):.3f}")
    if properties:
        props = ET.SubElement(suite, "properties")
        for key, value in properties.items():
            ET.SubElement(props, "property", name=str(key), value=str(value))
    for r in results:
        case = ET.SubElement(suite, "testcase", classname=f"{name}.{r.family}", name=r.id, time=f"{r.duration_s:.3f}")
        if r.status == "fail":
            ET.SubElement(case, "failure", message=r.detail, type=r.failure_type or "behaviour").text = (
                "\n".join(r.trace))
        elif r.status == "skipped":
            ET.SubElement(case, "skipped", message=r.detail)
        elif r.status == "error":
            ET.SubElement(case, "error", message=r.detail, type="run").text = "\n".join(r.trace)
        out = ET.SubElement(case, "system-out")
        retried = f"\nSDO sent again: {', '.join(r.sdo_retries)}" if r.sdo_retries else ""
        out.text = f"{r.clause}\n{r.status}: {r.detail}{retried}\n" + "\n".join(r.trace)
    ET.indent(suite)
    ET.ElementTree(suite).write(path, encoding="utf-8", xml_declaration=True)
