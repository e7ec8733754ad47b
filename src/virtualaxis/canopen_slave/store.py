"""Store / restore parameters (0x1010 / 0x1011) to a JSON file.

Writing the signature "save" (0x65766173) to 0x1010:n stores the group's writable parameters; writing
"load" (0x64616F6C) to 0x1011:n deletes them from the file, so the EDS defaults apply after the next
reset (CiA 301 7.5.2.13/14). The stored values are the power-on values: they are applied at start and at
every NMT reset (communication group at reset communication, all at reset node).
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

from virtualaxis.canopen_slave import errors as ab
from virtualaxis.canopen_slave.errors import SdoAbort
from virtualaxis.canopen_slave.od import ObjectStore
from virtualaxis.config.errors import InputError

SAVE_SIGNATURE = 0x65766173     # "save" little endian
LOAD_SIGNATURE = 0x64616F6C     # "load"
FORMAT = "virtualaxis canopen parameter store 1"

#: sub-index of 0x1010/0x1011 -> index range of its parameter group
GROUPS: dict[int, tuple[int, int]] = {1: (0x1000, 0x9FFF), 2: (0x1000, 0x1FFF), 3: (0x6000, 0x9FFF),
                                      4: (0x2000, 0x5FFF)}
#: writable objects that are process data or commands, never stored
VOLATILE = frozenset({0x1003, 0x1010, 0x1011, 0x6040, 0x607A, 0x60FF, 0x6071, 0x60B1, 0x60B2, 0x60B8, 0x60C1,
                      0x2010, 0x2011, 0x2014, 0x2100, 0x2101, 0x2102})


def _key(index: int, sub: int) -> str:
    return f"{index:04X}sub{sub:X}"


class ParameterStore:
    def __init__(self, path: str | Path | None, od: ObjectStore):
        self.path = Path(path) if path is not None else None
        self.od = od
        self.values: dict[tuple[int, int], object] = {}
        if self.path is not None and self.path.exists():
            self._load()

    def _load(self) -> None:
        assert self.path is not None
        where = str(self.path)
        try:
            doc = json.loads(self.path.read_text(encoding="utf-8"))
        except (OSError, ValueError) as exc:
            raise InputError(where, f"cannot read parameter store: {exc}") from None
        if not isinstance(doc, dict) or doc.get("format") != FORMAT or \
                not isinstance(doc.get("values"), dict):
            raise InputError(where, f'not a parameter store file (expected "format": "{FORMAT}")')
        for key, value in doc["values"].items():
            try:
                index, sub = int(key[:4], 16), int(key[7:], 16)
            except ValueError:
                raise InputError(where, f"bad key {key!r} (expected e.g. 1017sub0)") from None
            entry = self.od.entries.get((index, sub))
            if entry is None or not entry.writable:
                raise InputError(where, f"{key}: no writable object 0x{index:04X}:{sub} in "
                                        f"{self.od.eds_path.name}")
            numeric = isinstance(value, (int, float)) and not isinstance(value, bool)
            finite = numeric and not (isinstance(value, float) and not math.isfinite(value))
            if entry.fmt is not None and not finite:
                raise InputError(where, f"{key}: expected a number, got {value!r}")
            if numeric and ((entry.low is not None and value < entry.low) or
                            (entry.high is not None and value > entry.high)):
                raise InputError(where, f"{key}: {value} outside [{entry.low}, {entry.high}]")
            if entry.fmt is not None and entry.fmt not in "fd":
                value = int(value)
            self.values[(index, sub)] = value

    @property
    def available(self) -> bool:
        return self.path is not None

    def apply(self, lo: int, hi: int) -> None:
        """Overlay the stored values of indices lo..hi onto the dictionary."""
        for (index, sub), value in self.values.items():
            if lo <= index <= hi:
                self.od.entries[(index, sub)].value = value

    def command(self, index: int, sub: int, value: int) -> None:
        """Handle a write to 0x1010:sub (save) or 0x1011:sub (restore); raises SdoAbort."""
        signature = SAVE_SIGNATURE if index == 0x1010 else LOAD_SIGNATURE
        if value != signature or self.path is None or sub not in GROUPS:
            raise SdoAbort(ab.CANNOT_STORE, "wrong signature" if value != signature else "no store file")
        lo, hi = GROUPS[sub]
        if index == 0x1010:
            for (i, s), entry in self.od.entries.items():
                if lo <= i <= hi and entry.writable and i not in VOLATILE:
                    self.values[(i, s)] = entry.value
        else:
            self.values = {k: v for k, v in self.values.items() if not lo <= k[0] <= hi}
        self._write()

    def _write(self) -> None:
        assert self.path is not None
        values = {}
        for (index, sub), value in sorted(self.values.items()):
            values[_key(index, sub)] = value.hex() if isinstance(value, (bytes, bytearray)) else value
        doc = {"format": FORMAT, "eds": self.od.eds_path.name, "values": values}
        tmp = self.path.with_name(self.path.name + ".tmp")
        try:
            tmp.write_text(json.dumps(doc, indent=1) + "\n", encoding="utf-8")
            os.replace(tmp, self.path)
        except OSError as exc:
            raise SdoAbort(ab.HARDWARE_ERROR, f"cannot write {self.path}: {exc}") from None
