"""Writing traces in the measured-trace format (``docs/reference/trace-format.md``): SI units, one column per signal.

The file name chooses the container:

- ``*.npz`` -- NumPy archive (uncompressed), one float64 array per column plus ``__columns__`` (the column
  order). Bit-exact; the fastest to write and read. Rows are buffered in memory until ``close()``
  (8 bytes x columns x rows: 200 s at 1 kHz with 10 columns is 16 MB).
- anything else (``*.csv``) -- CSV with a header row, the same columns and number format as before
  (``%.10g``: ten significant digits). Rows are formatted by a compiled (numba) formatter into one byte
  block per chunk and streamed, so memory does not grow with duration. With ``threaded=True`` the
  formatting and writing run in a thread of their own, beside the caller's next simulation chunk (both the
  formatter and the plant kernel release the GIL): a run's wall time is then about the larger of the two
  instead of their sum. At most two blocks wait in that thread's queue.

Precision of the CSV: each value is written with ten significant digits, i.e. the relative error of a
value read back is at most 5.0e-10 (half a unit in the tenth digit). The digits are those of Python's
``'%.10g' % x`` except when the exact decimal expansion lies within about 1e-6 units of a rounding tie
in the tenth digit, where the last digit may differ by one (the error bound stays 5.0001e-10).
``nan``/``inf``/``-inf`` are written as ``%g`` writes them. For bit-exact traces use ``.npz``.
"""

from __future__ import annotations

import math
import queue
import stat
import threading
import zipfile
from collections.abc import Iterable
from pathlib import Path
from typing import BinaryIO

import numpy as np
from numba import njit

from virtualaxis import jitcache  # noqa: F401  (numba cache failures are not fatal)

#: relative precision of a CSV value read back (ten significant digits, see the module docstring)
CSV_RELATIVE_PRECISION = 5.0001e-10
#: key of the column-order array in an NPZ trace
NPZ_COLUMNS_KEY = "__columns__"
_SIG = 10  # significant digits, as '%.10g'
_MAX_FIELD = 18  # '-1.234567891e-308' (17) + ',' or '\n'


_POW10 = np.array([10.0**k for k in range(23)])


@njit(cache=True, inline="always")
def _pow10(k: int) -> float:
    """10**k as a float, exact for 0 <= k <= 22 (table), ``10.0**k`` otherwise."""
    if 0 <= k <= 22:
        return _POW10[k]
    return 10.0**k


@njit(cache=True, inline="always")
def _scaled_mantissa(ax: float, e: int) -> float:
    """round(ax * 10**(SIG-1-e)) computed with one correctly rounded multiply or divide where possible."""
    k = _SIG - 1 - e
    if k >= 0:
        if k > 300:  # subnormal range: scale in two steps to avoid overflow of 10**k
            return np.rint(ax * _pow10(300) * _pow10(k - 300))
        return np.rint(ax * _pow10(k))
    return np.rint(ax / _pow10(-k))


_PAIRS = np.frombuffer("".join(f"{i:02d}" for i in range(100)).encode("ascii"), dtype=np.uint8).copy()


@njit(cache=True, inline="always")
def _put_int(buf: np.ndarray, pos: int, m: int, ndig: int) -> int:
    """Write the non-negative integer ``m`` zero-padded to ``ndig`` digits (two digits per division)."""
    i = pos + ndig
    while i - pos >= 2:
        q = m // 100
        r = m - q * 100
        buf[i - 1] = _PAIRS[2 * r + 1]
        buf[i - 2] = _PAIRS[2 * r]
        m = q
        i -= 2
    if i > pos:
        buf[pos] = 48 + m % 10
    return pos + ndig


@njit(cache=True, inline="always")
def _put_digits_point(buf: np.ndarray, pos: int, m: int, ndig: int, before: int) -> int:
    """Write the ``ndig``-digit integer ``m`` with a decimal point after its first ``before`` digits."""
    after = ndig - before
    p10 = np.int64(1)
    for _ in range(after):
        p10 *= 10
    hi = m // p10
    _put_int(buf, pos, hi, before)
    buf[pos + before] = 46
    return _put_int(buf, pos + before + 1, m - hi * p10, after)


@njit(cache=True, inline="always")
def _format_g10(x: float, buf: np.ndarray, pos: int) -> int:
    """Append ``'%.10g' % x`` (see the module docstring for the tie caveat) to ``buf`` at ``pos``."""
    if x != x:
        buf[pos] = 110  # n
        buf[pos + 1] = 97  # a
        buf[pos + 2] = 110  # n
        return pos + 3
    if math.copysign(1.0, x) < 0.0:
        buf[pos] = 45  # '-'
        pos += 1
    ax = abs(x)
    if ax == math.inf:
        buf[pos] = 105  # i
        buf[pos + 1] = 110  # n
        buf[pos + 2] = 102  # f
        return pos + 3
    if ax == 0.0:
        buf[pos] = 48
        return pos + 1
    e = int(math.floor(math.log10(ax)))
    m = _scaled_mantissa(ax, e)
    lo = _pow10(_SIG - 1)
    hi = _pow10(_SIG)
    if m >= hi:
        e += 1
        m = _scaled_mantissa(ax, e)
    elif m < lo:
        e -= 1
        m = _scaled_mantissa(ax, e)
        if m >= hi:  # log10 was right after all and the value rounds up to the next decade
            e += 1
            m = _scaled_mantissa(ax, e)
    mi = np.int64(m)
    nd = _SIG  # significant digits left after stripping trailing zeros
    while nd > 1 and mi % 10 == 0:
        mi //= 10
        nd -= 1
    if -4 <= e < _SIG:
        if e >= 0:
            if nd <= e + 1:  # integer: the digits then zeros
                pos = _put_int(buf, pos, mi, nd)
                for _ in range(e + 1 - nd):
                    buf[pos] = 48
                    pos += 1
                return pos
            return _put_digits_point(buf, pos, mi, nd, e + 1)
        buf[pos] = 48
        buf[pos + 1] = 46
        pos += 2
        for _ in range(-e - 1):
            buf[pos] = 48
            pos += 1
        return _put_int(buf, pos, mi, nd)
    if nd > 1:
        pos = _put_digits_point(buf, pos, mi, nd, 1)
    else:
        pos = _put_int(buf, pos, mi, 1)
    buf[pos] = 101  # 'e'
    pos += 1
    if e < 0:
        buf[pos] = 45
        e = -e
    else:
        buf[pos] = 43  # '+'
    pos += 1
    return _put_int(buf, pos, e, 3 if e >= 100 else 2)


@njit(cache=True, nogil=True)
def _format_block(block: np.ndarray, buf: np.ndarray) -> int:
    """Format a (rows, cols) float64 block as CSV lines into ``buf``; return the number of bytes written."""
    pos = 0
    n, c = block.shape
    for i in range(n):
        for j in range(c):
            if j:
                buf[pos] = 44  # ','
                pos += 1
            pos = _format_g10(block[i, j], buf, pos)
        buf[pos] = 10  # '\n'
        pos += 1
    return pos


def format_csv_rows(block: np.ndarray) -> bytes:
    """CSV text (bytes, ``\\n`` line ends) of a 2-D float block, ten significant digits per value."""
    b = np.ascontiguousarray(block, dtype=np.float64)
    if b.ndim != 2:
        raise ValueError(f"format_csv_rows needs a 2-D block, got shape {b.shape}")
    buf = np.empty(b.shape[0] * (b.shape[1] * _MAX_FIELD + 1), dtype=np.uint8)
    n = _format_block(b, buf)
    return buf[:n].tobytes()


def prepare_csv_formatter() -> None:
    """Compile (or load from numba's cache) the CSV formatter in the calling thread. A threaded
    :class:`TraceWriter` calls it before it starts its thread, so that thread only runs compiled code: a first
    compilation there (LLVM, under numba's process-wide compiler lock) would leave ``close`` waiting on it for
    as long as the compilation takes on a busy host, with nothing to show for it."""
    format_csv_rows(np.zeros((1, 1)))


def trace_format_for(path: str | Path) -> str:
    """``'npz'`` or ``'csv'``, chosen by the file name's suffix (``.parquet`` is refused: no pyarrow)."""
    suffix = Path(path).suffix.lower()
    if suffix == ".npz":
        return "npz"
    if suffix in (".parquet", ".pq"):
        from virtualaxis.config.errors import InputError

        raise InputError(str(path), "Parquet traces are not supported (pyarrow is not a dependency); use .npz or .csv")
    return "csv"


class TraceWriter:
    """Streams trace blocks to ``path`` (CSV or NPZ by suffix, see the module docstring).

    ``columns``: signal names; ``t`` (s) always comes first. ``write(data)`` takes a dict of equal-length
    arrays (SI units) holding at least these columns. ``threaded``: CSV blocks are formatted and written by
    a thread of the writer (see the module docstring); an error there (a full disk) is raised by the next
    ``write`` or by ``close``. The formatter is compiled in the constructing thread (:func:`prepare_csv_formatter`).
    """

    def __init__(self, path: str | Path, columns: list[str], *, threaded: bool = False):
        self.path = Path(path)
        self.format = trace_format_for(self.path)
        self.columns = ["t"] + [c for c in columns if c != "t"]
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.rows = 0
        self._fh: BinaryIO | None = None
        self._blocks: list[np.ndarray] = []
        self._queue: queue.Queue | None = None
        self._thread: threading.Thread | None = None
        self._error: BaseException | None = None
        self._reported = False
        if self.format == "csv":
            self._fh = self.path.open("wb")
            self._fh.write((",".join(self.columns) + "\n").encode("ascii"))
            if threaded:
                prepare_csv_formatter()
                self._queue = queue.Queue(maxsize=2)
                self._thread = threading.Thread(target=self._drain, name="trace-writer", daemon=True)
                self._thread.start()

    def _drain(self) -> None:
        """The writer thread: format and write each queued block until the ``None`` that ``close`` sends; after
        an error, the blocks still coming are taken and dropped (the error is raised in the caller)."""
        q = self._queue
        while True:
            block = q.get()
            if block is None:
                return
            if self._error is None:
                try:
                    self._fh.write(format_csv_rows(block))
                except BaseException as exc:  # noqa: BLE001 - handed to the caller's thread
                    self._error = exc

    def _raise_pending(self, unless_reported: bool = False) -> None:
        """The writer thread's error, again at every ``write`` once it happened (nothing after it is written);
        ``close`` raises it only if no ``write`` has."""
        if self._error is not None and not (unless_reported and self._reported):
            self._reported = True
            raise OSError(f"{self.path}: writing the trace failed: {self._error}") from self._error

    def write(self, data: dict[str, np.ndarray]) -> None:
        missing = [c for c in self.columns if c not in data]
        if missing:
            raise KeyError(f"{self.path}: trace block lacks column(s) {', '.join(missing)}")
        block = np.empty((len(np.asarray(data["t"])), len(self.columns)), dtype=np.float64)
        for j, c in enumerate(self.columns):
            block[:, j] = data[c]
        if self._queue is not None:
            self._raise_pending()
            self._queue.put(block)  # (a fresh array: the caller may reuse its own)
        elif self._fh is not None:
            self._fh.write(format_csv_rows(block))
        else:
            self._blocks.append(block)
        self.rows += len(block)

    def close(self) -> None:
        if self._thread is not None:
            self._queue.put(None)
            self._thread.join()
            self._thread = self._queue = None
        if self._fh is not None:
            fh, self._fh = self._fh, None
            try:
                fh.close()  # (flushes the last bytes: may fail too)
            except OSError as exc:
                if self._error is None:  # after a reported failure the file is known to be bad already
                    self._error = exc
            self._raise_pending(unless_reported=True)
            return
        if self.format == "npz":
            allr = np.concatenate(self._blocks) if self._blocks else np.zeros((0, len(self.columns)))
            arrays = {c: np.ascontiguousarray(allr[:, j]) for j, c in enumerate(self.columns)}
            with self.path.open("wb") as fh:
                np.savez(fh, **{NPZ_COLUMNS_KEY: np.array(self.columns)}, **arrays)
            self._blocks = []
            self.format = "closed"

    def __enter__(self) -> TraceWriter:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
            return
        try:  # already failing: the file is closed, the first error is the one raised
            self.close()
        except Exception:  # noqa: BLE001
            pass


def write_trace_csv(path: str | Path, data: dict[str, np.ndarray], columns: list[str] | None = None) -> Path:
    """Write one whole trace (CSV, or NPZ when ``path`` ends in ``.npz``)."""
    cols = columns or [c for c in data if c != "t"]
    with TraceWriter(path, cols) as w:
        w.write(data)
    return Path(path)


#: members of an NPZ trace at most (a trace has a few dozen columns)
NPZ_MAX_MEMBERS = 1024
#: bytes of one NPZ member's .npy header at most (NumPy's own default limit)
NPZ_MAX_HEADER_BYTES = 10_000


def _npy_header(zf, info, where: str, column: str) -> tuple[tuple[int, ...], np.dtype, int]:
    """Shape, dtype and header length of one ``.npy`` member, read from its header only (nothing is
    decompressed beyond the header): what the member would take in memory is known before it is read."""
    from virtualaxis.config.errors import InputError

    fmt = np.lib.format
    try:
        with zf.open(info) as fh:
            version = fmt.read_magic(fh)
            if version == (1, 0):
                shape, _, dtype = fmt.read_array_header_1_0(fh, max_header_size=NPZ_MAX_HEADER_BYTES)
            elif version in ((2, 0), (3, 0)):
                shape, _, dtype = fmt.read_array_header_2_0(fh, max_header_size=NPZ_MAX_HEADER_BYTES)
            else:
                raise ValueError(f"unknown .npy format version {version}")
            header_len = fh.tell()
    except (ValueError, OSError, EOFError, zipfile.BadZipFile, NotImplementedError, RuntimeError) as exc:
        raise InputError(where, f"not a readable .npy array ({' '.join(str(exc).split())})", None, column) from None
    return tuple(int(n) for n in shape), dtype, header_len


def read_trace_npz(path: str | Path, *, max_rows: int | None = None,
                   columns: Iterable[str] | None = None) -> tuple[list[str], np.ndarray]:
    """Header and ``(rows, cols)`` float data of an NPZ trace written by :class:`TraceWriter`.

    Every size is checked before anything is decompressed: the zip directory (members, their declared
    sizes), then each member's ``.npy`` header (shape and dtype: numbers only, one dimension, at most
    ``max_rows`` values), and the declared size must match what the header announces; only then are the
    arrays read (only those in ``columns`` when given: the data's columns are then the header's names that
    are in ``columns``, in the header's order; the header lists all). A small file that would
    decompress to gigabytes is refused by its figures, unread.

    Raises :class:`~virtualaxis.config.errors.InputError` (a ``ValueError``) naming the file and column.
    """
    from virtualaxis.config.errors import InputError

    p = Path(path)
    sp = str(p)
    try:
        st = p.stat()
        if stat.S_ISDIR(st.st_mode):
            raise InputError(sp, "is a folder, not a trace file")
        if not stat.S_ISREG(st.st_mode):
            raise InputError(sp, "not a regular file (a device, pipe or socket); give a trace file")
        with p.open("rb") as fh:
            magic = fh.read(6)
        if magic == b"\x93NUMPY":
            raise InputError(sp, "not an NPZ archive (a single .npy array)")
        zf = zipfile.ZipFile(p)
    except FileNotFoundError:
        raise InputError(sp, "file not found") from None
    except (zipfile.BadZipFile, EOFError, ValueError) as exc:
        if isinstance(exc, InputError):
            raise
        raise InputError(sp, "not an NPZ archive (not a zip file): a trace named .npz must be written by "
                             "virtualaxis simulate or numpy.savez") from None
    except OSError as exc:
        raise InputError(sp, f"cannot read ({exc.strerror or exc})") from None
    with zf:
        infos = zf.infolist()
        if len(infos) > NPZ_MAX_MEMBERS:
            raise InputError(sp, f"{len(infos)} members; an NPZ trace has at most {NPZ_MAX_MEMBERS} columns")
        members = {}
        for info in infos:
            name = info.filename[:-4] if info.filename.endswith(".npy") else info.filename
            if name in members:
                raise InputError(sp, "the archive holds this member twice", None, name)
            members[name] = info
        if NPZ_COLUMNS_KEY in members:
            info = members[NPZ_COLUMNS_KEY]
            shape, dtype, hlen = _npy_header(zf, info, sp, NPZ_COLUMNS_KEY)
            n = int(np.prod(shape)) if shape else 1
            if dtype.kind != "U" or len(shape) != 1 or n > NPZ_MAX_MEMBERS or dtype.itemsize > 4 * 256:
                raise InputError(sp, f"{NPZ_COLUMNS_KEY} must be a list of at most {NPZ_MAX_MEMBERS} column names "
                                     f"(got {dtype} of shape {shape})", None, NPZ_COLUMNS_KEY)
            header = [str(c) for c in _read_member(zf, info, sp, NPZ_COLUMNS_KEY)]
        else:
            header = list(members)
        wanted = set(header) if columns is None else set(columns)
        plan = []
        rows = None
        for c in header:
            if c not in members:
                raise InputError(sp, f"listed in {NPZ_COLUMNS_KEY} but no such array", None, c)
            info = members[c]
            shape, dtype, hlen = _npy_header(zf, info, sp, c)
            if dtype.kind not in "biuf" or dtype.hasobject or dtype.fields:
                raise InputError(sp, f"not numeric (dtype {dtype})", None, c)
            if len([d for d in shape if d != 1]) > 1:
                raise InputError(sp, f"an array of shape {shape}; a trace column has one dimension", None, c)
            n = int(np.prod(shape)) if shape else 1
            if max_rows is not None and n > max_rows:
                raise InputError(sp, f"{n:,} samples; at most {max_rows:,} samples per trace are read (bounded "
                                     "memory and fit time): cut the trace into segments or decimate it", None, c)
            if info.file_size != hlen + n * dtype.itemsize:
                raise InputError(sp, f"the archive declares {info.file_size:,} bytes for this member, its .npy "
                                     f"header announces {hlen + n * dtype.itemsize:,}: a damaged archive", None, c)
            if rows is not None and n != rows:
                raise InputError(sp, f"has {n} values, column {header[0]} has {rows}", None, c)
            rows = n
            if c in wanted:
                plan.append((c, info))
        if not header:
            raise InputError(sp, "no columns")
        cols = [np.asarray(_read_member(zf, info, sp, c), dtype=float).ravel() for c, info in plan]
    data = np.column_stack(cols) if cols else np.empty((rows or 0, 0))
    return header, data


def _read_member(zf, info, where: str, column: str) -> np.ndarray:
    """One member's array, after :func:`_npy_header` has checked its size."""
    from virtualaxis.config.errors import InputError

    try:
        with zf.open(info) as fh:
            return np.lib.format.read_array(fh, allow_pickle=False, max_header_size=NPZ_MAX_HEADER_BYTES)
    except (ValueError, OSError, EOFError, zipfile.BadZipFile, RuntimeError) as exc:
        raise InputError(where, f"not a readable .npy array ({' '.join(str(exc).split())})", None, column) from None


def read_trace_csv(path: str | Path) -> dict[str, np.ndarray]:
    """Plain reader for traces this package wrote, CSV or NPZ (the diagnosis has its own validating reader)."""
    if trace_format_for(path) == "npz":
        header, data = read_trace_npz(path)
        return {h: data[:, i] for i, h in enumerate(header)}
    arr = np.genfromtxt(path, delimiter=",", names=True)
    return {name: np.asarray(arr[name], dtype=float) for name in arr.dtype.names}
