"""Where does a SYNC -> TPDO latency accrue inside ``serve``? Hop timestamps for benchmarks.

``virtualaxis serve --latency-probe FILE`` wraps the served bus in :class:`ProbeBus`, which records (all
``time.time()`` seconds, CLOCK_REALTIME, comparable with the master's timestamps in another process):

- for every received SYNC (COB-ID 0x080): the **kernel receive timestamp** of the frame in serve's socket
  (SO_TIMESTAMPNS, python-can ``udp_multicast``) and the instant serve's **bus receive thread** got it out
  of the socket (``recv`` returned);
- for every transmitted PDO (COB-IDs 0x180..0x4FF): the instant the **runtime thread** called ``send`` and
  the COB-ID.

so that a benchmark can split each SYNC -> TPDO latency into: delivery to serve's socket, serve's receive
thread (CPU / interpreter lock), serve's runtime thread (wake-up, the SYNC's work), and the way back. Written
at stop as ``.npz`` (``sync_kernel_s``, ``sync_user_s``, ``tx_s``, ``tx_cob``; and every cyclic garbage
collection of the process: ``gc_start_s``, ``gc_gen``, ``gc_s`` its length, which holds every thread).
Costs about a microsecond per frame; off unless asked for.

:func:`name_threads` gives the process' Python threads their names as OS thread names (``/proc/.../comm``,
15 characters), so that per-thread CPU and run-queue figures (``/proc/PID/task/TID/schedstat``, ``top -H``)
can be told apart.
"""

from __future__ import annotations

import gc
import threading
import time
from pathlib import Path

import can

SYNC_COB = 0x080
PDO_TX_COBS = range(0x180, 0x500)


class ProbeBus(can.BusABC):
    """A bus wrapper that timestamps SYNC receptions and PDO transmissions (see the module doc)."""

    def __init__(self, inner: can.BusABC):
        self.inner = inner
        self.channel_info = getattr(inner, "channel_info", "bus")
        super().__init__(channel=None)
        self.sync_kernel_s: list[float] = []
        self.sync_user_s: list[float] = []
        self.tx_s: list[float] = []
        self.tx_cob: list[int] = []
        self.gc_start_s: list[float] = []  # cyclic garbage collections: start [time.time s], generation, length
        self.gc_gen: list[int] = []
        self.gc_s: list[float] = []
        self._gc_t0 = 0.0
        gc.callbacks.append(self._on_gc)

    def _on_gc(self, phase: str, info: dict) -> None:
        if phase == "start":
            self._gc_t0 = time.perf_counter()
            self.gc_start_s.append(time.time())
            self.gc_gen.append(info["generation"])
        else:
            self.gc_s.append(time.perf_counter() - self._gc_t0)

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        cob = msg.arbitration_id
        if cob in PDO_TX_COBS and not msg.is_extended_id:
            self.tx_s.append(time.time())
            self.tx_cob.append(cob)
        self.inner.send(msg, timeout)

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        msg = self.inner.recv(timeout)
        if msg is not None and msg.arbitration_id == SYNC_COB and not msg.is_extended_id:
            self.sync_user_s.append(time.time())
            self.sync_kernel_s.append(msg.timestamp)
        return msg, False

    def fileno(self) -> int:
        return self.inner.fileno()

    def __getattr__(self, name: str):  # stats() etc. of the wrapped bus (e.g. the bit-rate emulation)
        if name == "inner":
            raise AttributeError(name)
        return getattr(self.inner, name)

    def shutdown(self) -> None:
        if self._on_gc in gc.callbacks:
            gc.callbacks.remove(self._on_gc)
        self.inner.shutdown()
        super().shutdown()

    def write(self, path: str | Path) -> None:
        import numpy as np

        with open(path, "wb") as fh:  # (np.savez would append .npz to a name without it)
            np.savez(fh, sync_kernel_s=np.array(self.sync_kernel_s), sync_user_s=np.array(self.sync_user_s),
                     tx_s=np.array(self.tx_s), tx_cob=np.array(self.tx_cob, dtype=np.int32),
                     gc_start_s=np.array(self.gc_start_s), gc_gen=np.array(self.gc_gen, dtype=np.int32),
                     gc_s=np.array(self.gc_s[: len(self.gc_start_s)]))


def name_threads(prefix_strip: str = "virtualaxis-") -> None:
    """Set every running Python thread's OS name (``/proc/self/task/TID/comm``) to its Python name (without
    ``prefix_strip``, cut to 15 characters). Best effort: a thread that cannot be named keeps its name."""
    for t in threading.enumerate():
        tid = getattr(t, "native_id", None)
        if tid is None:
            continue
        name = t.name.removeprefix(prefix_strip)
        if t is threading.main_thread():
            name = "main"
        elif name.startswith("Notifier"):
            name = "can-rx"
        try:
            Path(f"/proc/self/task/{tid}/comm").write_text(name[:15])
        except OSError:
            pass
