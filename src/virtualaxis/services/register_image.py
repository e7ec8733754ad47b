"""The published register image: every readable register of every unit in shared memory.

``serve`` (the writer, :class:`ImagePublisher`) evaluates the register map of each axis at a fixed period
(default :data:`DEFAULT_PERIOD_S`) into one image per unit — the words a read returns, already scaled,
saturated and split into high/low words as the map defines (:mod:`virtualaxis.services.modbus_map`). The
Modbus server process (the reader, :class:`ImageReader`) answers FC03/04 reads from that image without
talking to ``serve``: a read costs the drive's process nothing.

Layout of the shared memory block (native byte order, one slot per unit in the order given):
``slot = [seq u64][reads u64][words: IMAGE_WORDS x u16]``. ``seq`` is a sequence lock: the writer makes it odd
before and even after it copies a new image; a reader retries while it is odd or changed during its copy, so
no read ever returns a torn image. ``reads`` counts the reads the server process answered from the slot.
"""

from __future__ import annotations

import struct
import threading
import time
from multiprocessing import shared_memory

from virtualaxis.services.modbus_map import BY_ADDRESS, REGISTERS, AxisLink, View, saturate

DEFAULT_PERIOD_S = 0.010
IMAGE_WORDS = max(BY_ADDRESS) + 1  # PDU addresses 0 .. highest register
_HEADER = struct.Struct("=QQ")
SLOT_BYTES = _HEADER.size + 2 * IMAGE_WORDS + (-(2 * IMAGE_WORDS) % 8)
_PACK_CODE = {"u16": "H", "bits": "H", "i16": "h", "u32": "I", "i32": "i"}


def _image_format() -> str:
    """One struct format for the whole image: each register at its address (big-endian words, high word
    first, as on the wire), pad bytes for the holes."""
    parts = [">"]
    a = 0
    for reg in sorted(REGISTERS, key=lambda r: r.address):
        if reg.address > a:
            parts.append(f"{2 * (reg.address - a)}x")
        parts.append(_PACK_CODE[reg.dtype])
        a = reg.address + reg.words
    if a < IMAGE_WORDS:
        parts.append(f"{2 * (IMAGE_WORDS - a)}x")
    return "".join(parts)


IMAGE = struct.Struct(_image_format())
_ORDERED = tuple(sorted(REGISTERS, key=lambda r: r.address))
_READERS = tuple((r.read, r.dtype) for r in _ORDERED)


def build_image(link: AxisLink) -> bytes:
    """The image of one axis (``IMAGE.size`` bytes, big-endian words): one drive instant for all registers
    (the drive's lock held: no cycle runs between the state and the objects the registers read)."""
    with link.drive.lock:
        view = View(link)
        return IMAGE.pack(*[saturate(read(view), dtype) for read, dtype in _READERS])


class ImagePublisher:
    """Writer side (in ``serve``): owns the shared memory; :meth:`publish` one unit, a thread publishing all
    units every ``period_s``."""

    def __init__(self, links: dict[int, AxisLink], period_s: float = DEFAULT_PERIOD_S, gate=None):
        if period_s <= 0:
            raise ValueError(f"register image period must be > 0 s (got {period_s})")
        self.links = links
        self.units = list(links)
        self.period_s = period_s
        self.gate = gate  # CycleGate: a due publication waits for the gap after the next SYNC's PDOs
        self.shm = shared_memory.SharedMemory(create=True, size=SLOT_BYTES * max(1, len(self.units)))
        self.shm.buf[:] = b"\x00" * self.shm.size
        self._lock = threading.Lock()
        self._cond = threading.Condition()
        self._started = 0  # publications started / completed (all units)
        self._done = 0
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.build_s_total = 0.0
        self.builds = 0

    @property
    def name(self) -> str:
        return self.shm.name

    def publish(self, unit: int) -> None:
        """Evaluate unit ``unit``'s map on its drive now and publish it (sequence-locked). The image is built
        under the publisher's lock: a periodic build started before a write (or a refusal) was recorded must not
        be published after the fresh image the bridge published for it (seen in CI: a refused write's last-error
        registers read 0 right after the refusal)."""
        t0 = time.perf_counter()
        off = SLOT_BYTES * self.units.index(unit)
        buf = self.shm.buf
        with self._lock:
            image = build_image(self.links[unit])
            seq = _HEADER.unpack_from(buf, off)[0]
            struct.pack_into("=Q", buf, off, seq + 1)  # odd: being written
            buf[off + _HEADER.size : off + _HEADER.size + len(image)] = image
            struct.pack_into("=Q", buf, off, seq + 2)
        self.build_s_total += time.perf_counter() - t0
        self.builds += 1

    def publish_all(self) -> None:
        with self._cond:
            self._started += 1
            n = self._started
        for unit in self.units:
            self.publish(unit)
        with self._cond:
            self._done = max(self._done, n)
            self._cond.notify_all()

    def sync(self, timeout_s: float = 5.0) -> None:
        """Wait until a publication that started after this call has completed: from then on a read shows the
        drive's state at least as new as at the call."""
        with self._cond:
            target = self._started + 1
            self._cond.wait_for(lambda: self._done >= target, timeout_s)

    def reads(self, unit: int) -> int:
        """Reads the server process answered from unit ``unit``'s image."""
        return _HEADER.unpack_from(self.shm.buf, SLOT_BYTES * self.units.index(unit))[1]

    def start(self) -> ImagePublisher:
        self.publish_all()
        self._thread = threading.Thread(target=self._run, name="virtualaxis-modbus-image", daemon=True)
        self._thread.start()
        return self

    def _run(self) -> None:
        """Publish every ``period_s``; a late publication is skipped, never caught up in a burst, and after each
        one the thread rests at least as long as the publication took. Without that rest a loaded machine, where
        a build outlasts the period, publishes back to back and starves every other user of the drive's lock
        (the runtime's cycle, the bridge's writes, a reader): the lock is not fair, and the publisher releases
        and re-takes it within one switch interval."""
        next_t = time.monotonic()
        build_s = 0.0
        while not self._stop.is_set():
            next_t += self.period_s
            now = time.monotonic()
            if next_t - now < build_s:  # late, or too soon after a long build
                next_t = now + build_s
            if self._stop.wait(next_t - now):
                return
            if self.gate is not None:
                self.gate.wait_next()
            t0 = time.monotonic()
            try:
                self.publish_all()
            except Exception:  # noqa: BLE001 - a drive mid-reconfiguration: keep the old image
                pass
            build_s = time.monotonic() - t0

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            self._thread = None
        try:
            self.shm.close()
            self.shm.unlink()
        except (FileNotFoundError, BufferError):
            pass


class ImageReader:
    """Reader side (in the Modbus server process): answers reads of the published units."""

    def __init__(self, name: str, units: list[int]):
        import mmap
        import os

        # attach by path, not by SharedMemory(name): in Python < 3.13 that would register the block with a
        # resource tracker of this process, which unlinks it when this process ends
        fd = os.open(f"/dev/shm/{name.lstrip('/')}", os.O_RDWR)
        try:
            self._map = mmap.mmap(fd, 0)
        finally:
            os.close(fd)
        self.buf = memoryview(self._map)
        self.slot = {u: SLOT_BYTES * i for i, u in enumerate(units)}
        self.valid = frozenset(BY_ADDRESS)

    def covers(self, address: int, count: int) -> bool:
        """True when ``address .. address+count-1`` are all map registers (no hole) and 1 <= count <= 125."""
        return 1 <= count <= 125 and all(a in self.valid for a in range(address, address + count))

    def read(self, unit: int, address: int, count: int) -> list[int] | None:
        """The words of a read (None: unit not published); the range must be :meth:`covers`-ed."""
        off = self.slot.get(unit)
        if off is None:
            return None
        buf = self.buf
        start = off + _HEADER.size + 2 * address
        while True:
            s1 = _HEADER.unpack_from(buf, off)[0]
            data = bytes(buf[start : start + 2 * count])
            s2, reads = _HEADER.unpack_from(buf, off)
            if s1 == s2 and not s1 & 1:
                break
            time.sleep(0)
        struct.pack_into("=Q", buf, off + 8, reads + 1)  # only this process writes the counter
        return list(struct.unpack(f">{count}H", data))

    def close(self) -> None:
        self.buf.release()
        self._map.close()
