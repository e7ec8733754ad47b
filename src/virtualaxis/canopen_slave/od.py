"""The object dictionary the slave serves, loaded from the EDS with the `canopen` package's importer.

`canopen` parses the EDS (sections, $NODEID, data types, defaults, integer limits); this module turns every
sub-entry into a mutable :class:`Entry` holding the live value, its struct packer, size and limits, so that
the SDO server and the PDO engine never go back to the `canopen` objects in the hot path.
"""

from __future__ import annotations

import copy
import functools
import struct
from configparser import RawConfigParser
from dataclasses import dataclass, field
from pathlib import Path

from canopen.objectdictionary import ODArray, ODRecord, ODVariable, import_od
from canopen.objectdictionary import datatypes as dt

from virtualaxis.config.errors import InputError
from virtualaxis.eds_text import declared_limits

# struct formats of the fixed-size types we map into PDOs or serve by SDO
_STRUCT_FORMATS: dict[int, str] = {
    dt.BOOLEAN: "?", dt.INTEGER8: "b", dt.INTEGER16: "h", dt.INTEGER32: "i", dt.INTEGER64: "q",
    dt.UNSIGNED8: "B", dt.UNSIGNED16: "H", dt.UNSIGNED32: "I", dt.UNSIGNED64: "Q",
    dt.REAL32: "f", dt.REAL64: "d",
}
_TYPE_RANGES: dict[int, tuple[int, int]] = {
    dt.INTEGER8: (-(1 << 7), (1 << 7) - 1), dt.INTEGER16: (-(1 << 15), (1 << 15) - 1),
    dt.INTEGER32: (-(1 << 31), (1 << 31) - 1), dt.INTEGER64: (-(1 << 63), (1 << 63) - 1),
    dt.UNSIGNED8: (0, 0xFF), dt.UNSIGNED16: (0, 0xFFFF), dt.UNSIGNED32: (0, 0xFFFFFFFF),
    dt.UNSIGNED64: (0, (1 << 64) - 1), dt.BOOLEAN: (0, 1),
}
STRING_TYPES = (dt.VISIBLE_STRING, dt.OCTET_STRING, dt.UNICODE_STRING, dt.DOMAIN)


@dataclass(eq=False)
class Entry:
    """One (index, sub-index) of the dictionary with its live value."""

    index: int
    sub: int
    name: str
    data_type: int
    access: str                  # "ro", "wo", "rw", "rwr", "rww", "const"
    pdo_mappable: bool
    default: object
    low: float | int | None
    high: float | int | None
    fmt: str | None              # struct format character (fixed-size types) or None (strings, domain)
    size: int | None             # bytes (fixed-size types) or None
    value: object = None
    #: TPDOs that map this entry (filled by the PDO engine; a change marks them for event transmission)
    tpdos: list = field(default_factory=list)

    @property
    def readable(self) -> bool:
        return self.access != "wo"

    @property
    def writable(self) -> bool:
        return self.access in ("rw", "wo", "rwr", "rww")

    def encode(self, value) -> bytes:
        """Value -> bytes as sent on the bus (little endian)."""
        if self.fmt is not None:
            if self.fmt in "fd":
                return struct.pack("<" + self.fmt, float(value))
            return struct.pack("<" + self.fmt, int(value))
        if isinstance(value, (bytes, bytearray)):
            return bytes(value)
        if self.data_type == dt.UNICODE_STRING:
            return str(value).encode("utf_16_le")
        return str(value).encode("ascii", errors="replace")

    def decode(self, data: bytes):
        """Bytes -> value (the caller has checked the length of fixed-size types)."""
        if self.fmt is not None:
            return struct.unpack("<" + self.fmt, data)[0]
        if self.data_type == dt.VISIBLE_STRING:
            return data.decode("ascii", errors="replace").rstrip("\x00")
        if self.data_type == dt.UNICODE_STRING:
            return data.decode("utf_16_le", errors="replace").rstrip("\x00")
        return bytes(data)


@dataclass(eq=False)
class ObjectInfo:
    """One index: a VAR (only sub 0), an ARRAY or a RECORD."""

    index: int
    name: str
    kind: str                    # "VAR", "ARRAY", "RECORD"
    subs: dict[int, Entry]


_OBJECT_TYPES = {0x2: "DOMAIN", 0x5: "DEFTYPE", 0x6: "DEFSTRUCT", 0x7: "VAR", 0x8: "ARRAY", 0x9: "RECORD"}
_ACCESS_TYPES = ("ro", "wo", "rw", "rwr", "rww", "const")
_KNOWN_TYPES = frozenset(_STRUCT_FORMATS) | frozenset(STRING_TYPES) | frozenset(
    getattr(dt, name) for name in ("INTEGER24", "INTEGER40", "INTEGER48", "INTEGER56", "UNSIGNED24", "UNSIGNED40",
                                   "UNSIGNED48", "UNSIGNED56", "TIME_OF_DAY", "TIME_DIFFERENCE") if hasattr(dt, name))


def _object_key(section: str) -> tuple[int, int | None] | None:
    """(index, sub or None) of an object dictionary section name (``1018``, ``1018sub2``), None otherwise."""
    name = section.lower()
    hexdigits = "0123456789abcdef"
    if len(name) == 4 and all(c in hexdigits for c in name):
        return int(name, 16), None
    if len(name) > 7 and name[4:7] == "sub" and all(c in hexdigits for c in name[:4] + name[7:]):
        return int(name[:4], 16), int(name[7:], 16)
    return None


def _int_value(text: str) -> int:
    """An EDS integer: decimal, 0x hex, octal 0..., with an optional ``$NODEID+`` term (as 0)."""
    t = text.strip().upper().replace("$NODEID", "0")
    total = 0
    for term in t.split("+"):
        term = term.strip()
        if not term:
            raise ValueError(text)
        total += int(term, 16) if term.startswith("0X") else int(term, 10)
    return total


def _file_key(path: Path) -> tuple[str, str, int, int] | None:
    """The identity of a file's version (the path as given, the resolved path, modification time, size) for the
    caches below: an EDS is checked and parsed once per process and version of the file, not once per axis
    (parsing took ~95 % of building a served axis). None if the file cannot be stat'ed."""
    try:
        st = path.stat()
    except OSError:
        return None
    return str(path), str(path.resolve()), st.st_mtime_ns, st.st_size


def validate_eds(eds_path: str | Path) -> None:
    """Check the object sections of an EDS before `canopen` imports it: every ``ObjectType``, ``DataType``,
    ``AccessType``, ``PDOMapping``, ``SubNumber``, ``DefaultValue``, ``LowLimit`` and ``HighLimit`` is parsed and
    checked; a bad one raises :class:`InputError` naming the file, the ``[section]`` and the key with the value
    found and what was expected (e.g. ``eds/x.eds: [6040] DataType = '0x9999': unknown CANopen data type``).
    A version of a file found good is not checked again in this process."""
    path = Path(eds_path)
    if path.suffix.lower() not in (".eds", ".dcf", ".epf"):  # canopen picks its importer by the suffix
        raise InputError(str(path), f"not an EDS file (suffix {path.suffix or 'none'!r}; expected .eds, .dcf or .epf)")
    key = _file_key(path)
    if key is None:
        _check_sections(path)
    else:
        _checked(*key)


@functools.lru_cache(maxsize=16)
def _checked(path: str, _resolved: str, _mtime_ns: int, _size: int) -> None:
    """:func:`_check_sections` once per version of a file (a file that fails is checked again: nothing cached)."""
    _check_sections(Path(path))


def _check_sections(path: Path) -> None:
    parser = RawConfigParser(inline_comment_prefixes=(";",), strict=True)
    parser.optionxform = str
    try:
        with open(path, encoding="utf-8") as fh:
            parser.read_file(fh)
    except UnicodeDecodeError as exc:
        raise InputError(str(path), f"not UTF-8 text ({exc.reason} at byte {exc.start})") from None
    except Exception as exc:  # noqa: BLE001 - configparser errors name the line; keep them on one line
        raise InputError(str(path), " ".join(str(exc).split())) from None

    def bad(section: str, key: str, value: str, expected: str) -> InputError:
        return InputError(str(path), f"[{section}] {key} = {value!r}: {expected}")

    for section in parser.sections():
        if _object_key(section) is None:
            continue
        get = parser[section].get
        object_type = 0x7
        if (text := get("ObjectType")) is not None:
            try:
                object_type = int(text, 0) if text.strip() else 0x7
            except ValueError:
                raise bad(section, "ObjectType", text, "expected an integer (0x7 VAR, 0x8 ARRAY, 0x9 RECORD)") from None
            if object_type not in _OBJECT_TYPES:
                raise bad(section, "ObjectType", text, "expected 0x2, 0x5, 0x6, 0x7 (VAR), 0x8 (ARRAY) or 0x9 (RECORD)")
        if (text := get("SubNumber")) is not None and text.strip():
            try:
                if not 0 <= int(text, 0) <= 255:
                    raise ValueError
            except ValueError:
                raise bad(section, "SubNumber", text, "expected an integer 0..255") from None
        if object_type != 0x7:
            continue
        text = get("DataType")
        if text is None:
            raise InputError(str(path), f"[{section}] DataType missing: a VAR needs a data type")
        try:
            data_type = int(text, 0)
        except ValueError:
            raise bad(section, "DataType", text,
                      "expected an integer data type index (e.g. 0x0007 UNSIGNED32)") from None
        if data_type not in _KNOWN_TYPES:
            raise bad(section, "DataType", text, "unknown CANopen data type (expected a CiA 301 basic type, "
                      "e.g. 0x0001..0x0009, 0x000F, 0x0010..0x001B)")
        access = get("AccessType")
        if access is not None and access.strip().lower() not in _ACCESS_TYPES:
            raise bad(section, "AccessType", access, "expected one of " + ", ".join(_ACCESS_TYPES))
        if (text := get("PDOMapping")) is not None and text.strip() not in ("", "0", "1"):
            raise bad(section, "PDOMapping", text, "expected 0 or 1")
        numeric = data_type in _STRUCT_FORMATS
        is_float = data_type in (dt.REAL32, dt.REAL64)
        for key in ("DefaultValue", "LowLimit", "HighLimit"):
            text = get(key)
            if text is None or not text.strip() or not numeric:
                continue
            try:
                value = float(text) if is_float else _int_value(text)
            except ValueError:
                kind = "a number" if is_float else "an integer (decimal, 0x hex, optionally $NODEID+...)"
                raise bad(section, key, text, f"expected {kind}") from None
            rng = _TYPE_RANGES.get(data_type)
            if rng is not None and "$NODEID" not in text.upper() and not rng[0] <= value <= rng[1]:
                raise bad(section, key, text, f"outside the range of the data type ({rng[0]}..{rng[1]})")


#: objects this slave's CiA 301 stack reads whatever its configuration (index, sub, what it is): without one
#: the slave cannot start (0x1005, 0x1006, 0x1007, 0x1017, the PDO parameters) or every frame fails (0x1001,
#: 0x1014, 0x1015); 0x1000 and 0x1018 are mandatory in CiA 301
STACK_OBJECTS: tuple[tuple[int, int, str], ...] = (
    (0x1000, 0, "device type"), (0x1001, 0, "error register"), (0x1005, 0, "COB-ID SYNC"),
    (0x1006, 0, "communication cycle period"), (0x1007, 0, "synchronous window length"),
    (0x1014, 0, "COB-ID EMCY"), (0x1015, 0, "inhibit time EMCY"), (0x1017, 0, "producer heartbeat time"),
    (0x1018, 0, "identity object"), (0x1018, 1, "vendor-ID"),
    *((0x1400 + n, s, f"RPDO{n + 1} communication parameter") for n in range(4) for s in (0, 1, 2)),
    *((0x1600 + n, 0, f"RPDO{n + 1} mapping parameter") for n in range(4)),
    *((0x1800 + n, s, f"TPDO{n + 1} communication parameter") for n in range(4) for s in (0, 1, 2)),
    *((0x1A00 + n, 0, f"TPDO{n + 1} mapping parameter") for n in range(4)),
)


def check_served_eds(eds_path: str | Path, needs: tuple[tuple[int, int, str], ...] = ()) -> None:
    """Before serving from an EDS: :func:`validate_eds`, then the EDS must have a ``[DeviceInfo]`` section
    (mandatory in CiA 306), the objects of :data:`STACK_OBJECTS`, every object its default PDO mappings map,
    and ``needs`` (the application's objects: index, sub, name). Raises :class:`InputError` naming the file and
    what is missing (a missing object stopped the slave with a KeyError, or was served silently: an RPDO mapping
    a missing 0x6040 Controlword)."""
    import logging

    path = Path(eds_path)
    validate_eds(path)
    parser = RawConfigParser(inline_comment_prefixes=(";",), strict=False)
    parser.optionxform = str
    with open(path, encoding="utf-8") as fh:
        parser.read_file(fh)
    if not parser.sections():
        raise InputError(str(path), "no sections: not an EDS (an empty file?)")
    if not parser.has_section("DeviceInfo"):
        raise InputError(str(path), "no [DeviceInfo] section: not a complete EDS (mandatory in CiA 306)")
    canopen_log = logging.getLogger("canopen")
    level = canopen_log.level
    canopen_log.setLevel(logging.ERROR)  # (its warnings about the file are ours to report, once)
    try:
        store = ObjectStore(path, 1)
    finally:
        canopen_log.setLevel(level)
    names = {(i, s): n for i, s, n in (*STACK_OBJECTS, *needs)}
    missing: dict[tuple[int, int], str] = {}
    for index, sub, what in (*STACK_OBJECTS, *needs):
        if (index, sub) not in store:
            missing.setdefault((index, sub), what)
    mapped_by: dict[tuple[int, int], list[str]] = {}
    for base, kind in ((0x1600, "RPDO"), (0x1A00, "TPDO")):
        for n in range(4):
            if (base + n, 0) not in store:
                continue
            count = store.value(base + n, 0)
            for sub in range(1, count + 1 if isinstance(count, int) else 1):
                if (base + n, sub) not in store:
                    missing.setdefault((base + n, sub), f"{kind}{n + 1} mapping entry; sub-index 0 says {count}")
                    continue
                mapping = store.value(base + n, sub)
                if not isinstance(mapping, int) or not mapping:
                    continue
                key = (mapping >> 16, (mapping >> 8) & 0xFF)
                if key[0] >= 0x1000 and key not in store:
                    missing.setdefault(key, names.get(key, "an object"))
                    mapped_by.setdefault(key, []).append(f"{kind}{n + 1}")
    if missing:
        grouped: dict[tuple[int, str], list[int]] = {}
        for (index, sub), what in sorted(missing.items()):
            if (index, sub) in mapped_by:
                what += f"; mapped by {', '.join(mapped_by[(index, sub)])}"
            grouped.setdefault((index, what), []).append(sub)
        items = [f"0x{i:04X}:{'/'.join(f'{s:02X}' for s in subs)} ({what})" for (i, what), subs in grouped.items()]
        more = f" and {len(items) - 8} more" if len(items) > 8 else ""
        raise InputError(str(path), f"lacks object(s) the served drive needs: {', '.join(items[:8])}{more}")


def _parse_float_limits(eds_path: Path) -> dict[tuple[int, int], tuple[float | None, float | None]]:
    """canopen only parses integer limits; REAL32/REAL64 LowLimit/HighLimit are read here."""
    limits: dict[tuple[int, int], tuple[float | None, float | None]] = {}
    for key, (low, high, data_type) in declared_limits(eds_path).items():
        try:
            if data_type is None or int(data_type, 0) not in (dt.REAL32, dt.REAL64):
                continue
            limits[key] = (float(low) if low is not None else None, float(high) if high is not None else None)
        except ValueError as exc:
            raise InputError(str(eds_path), f"[{key[0]:04X}sub{key[1]:X}] bad LowLimit/HighLimit: {exc}") from None
    return limits


@functools.lru_cache(maxsize=16)
def _loaded_objects(path: str, _resolved: str, _mtime_ns: int, _size: int):
    """:func:`_load_objects` once per version of a file (the result is a template: never handed out)."""
    return _load_objects(Path(path))


def _load_objects(eds_path: Path) -> tuple[dict[int, ObjectInfo], frozenset[tuple[int, int]]]:
    """The objects of an EDS (checked by :func:`validate_eds`, imported by `canopen`) with the defaults of node-ID
    0, and the entries whose default is relative to the node-ID (``$NODEID+n``: the node's default is n + its
    node-ID, as `canopen` computes it)."""
    validate_eds(eds_path)
    try:
        od = import_od(str(eds_path), 0)
        float_limits = _parse_float_limits(eds_path)
    except InputError:
        raise
    except Exception as exc:  # configparser / canopen errors -> one clear line
        raise InputError(str(eds_path), f"cannot load EDS: {exc}") from None
    objects: dict[int, ObjectInfo] = {}
    relative: set[tuple[int, int]] = set()
    for index in sorted(od.indices if hasattr(od, "indices") else od):
        obj = od[index]
        if isinstance(obj, ODVariable):
            kind, variables = "VAR", [obj]
        else:
            kind = "ARRAY" if isinstance(obj, ODArray) else "RECORD"
            assert isinstance(obj, (ODArray, ODRecord))
            variables = [obj[s] for s in sorted(obj.subindices)]
        subs: dict[int, Entry] = {}
        for var in variables:
            entry = _entry_from(var, float_limits)
            subs[entry.sub] = entry
            if getattr(var, "relative", False) and isinstance(entry.default, int):
                relative.add((entry.index, entry.sub))
        objects[index] = ObjectInfo(index=index, name=obj.name, kind=kind, subs=subs)
    return objects, frozenset(relative)


def _entry_from(var: ODVariable, float_limits) -> Entry:
    fmt = _STRUCT_FORMATS.get(var.data_type)
    default = var.default
    if default is None:
        default = "" if var.data_type in (dt.VISIBLE_STRING, dt.UNICODE_STRING) else (
            b"" if fmt is None else 0)
    low, high = var.min, var.max
    if (var.index, var.subindex) in float_limits:
        low, high = float_limits[(var.index, var.subindex)]
    return Entry(index=var.index, sub=var.subindex, name=var.name, data_type=var.data_type,
                 access=(var.access_type or "rw").lower(), pdo_mappable=bool(var.pdo_mappable),
                 default=default, low=low, high=high, fmt=fmt,
                 size=struct.calcsize("<" + fmt) if fmt else None, value=default)


class ObjectStore:
    """All entries of the EDS, keyed by (index, sub) and by index."""

    def __init__(self, eds_path: str | Path, node_id: int):
        self.eds_path = Path(eds_path)
        if not self.eds_path.is_file():
            raise InputError(str(self.eds_path), "EDS file not found")
        key = _file_key(self.eds_path)
        objects, relative = _load_objects(self.eds_path) if key is None else _loaded_objects(*key)
        # this store's own entries (their values are live; the template's are never handed out), with the
        # defaults given as $NODEID+n for this node
        self.objects: dict[int, ObjectInfo] = {}
        self.entries: dict[tuple[int, int], Entry] = {}
        for index, info in objects.items():
            subs = {sub: copy.copy(e) for sub, e in info.subs.items()}
            for e in subs.values():
                e.tpdos = []
                if (e.index, e.sub) in relative:
                    e.default = e.value = e.default + node_id
                self.entries[(e.index, e.sub)] = e
            self.objects[index] = ObjectInfo(index=index, name=info.name, kind=info.kind, subs=subs)

    def __contains__(self, key: tuple[int, int]) -> bool:
        return key in self.entries

    def entry(self, index: int, sub: int = 0) -> Entry:
        return self.entries[(index, sub)]

    def value(self, index: int, sub: int = 0):
        return self.entries[(index, sub)].value

    def reset(self, lo: int, hi: int, keep: frozenset[int] = frozenset()) -> None:
        """Set every entry with lo <= index <= hi (except `keep`) back to its EDS default."""
        for (index, _sub), entry in self.entries.items():
            if lo <= index <= hi and index not in keep:
                entry.value = entry.default


def type_range(data_type: int) -> tuple[int, int] | None:
    """(min, max) representable by an integer data type, None for other types."""
    return _TYPE_RANGES.get(data_type)
