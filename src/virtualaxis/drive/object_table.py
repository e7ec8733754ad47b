"""The drive's object table: the values of its CiA 402 and manufacturer objects (:data:`.objects.OBJECTS`),
the manufacturer aliases, the set of objects changed since a mirror last took them, the checks every write path
shares (existence, access, data type, value ranges) and the per-cycle actual values (:attr:`ObjectTable.outputs`).

The table knows nothing of the drive's state: the rules that depend on it (a mode that 0x6502 does not list, a
position factor written in operation, ...) are :meth:`virtualaxis.drive.Drive.check_object_write`'s.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

from virtualaxis.drive.objects import DTYPE_RANGES, SPECS, ObjectSpec

Key = tuple[int, int]

# SDO abort codes of the table's checks
ABORT_READ_ONLY = 0x06010002
ABORT_VALUE_INVALID = 0x06090030
ABORT_VALUE_TOO_HIGH = 0x06090031
ABORT_VALUE_TOO_LOW = 0x06090032
ABORT_NO_OBJECT = 0x06020000


class ObjectAccessError(Exception):
    """A refused object access; ``code`` is the SDO abort code a CANopen master sees."""

    def __init__(self, code: int, message: str):
        super().__init__(message)
        self.code = code


class ObjectTable:
    """Values of the drive's objects, keyed (index, sub); ``aliases`` maps a second name to the object it
    stands for (both keys hold the value). ``output_keys``: the actual values :meth:`publish` writes every cycle
    (no alias among them)."""

    def __init__(self, aliases: dict[Key, Key], output_keys: tuple[Key, ...],
                 value_ranges: dict[Key, tuple[float, float]], range_reasons: dict[Key, str],
                 plain_int_keys: frozenset[Key]):
        if set(output_keys) & set(aliases.values()):
            raise ValueError("an output object has an alias")
        self.aliases = dict(aliases)
        self.aliases_back = {v: k for k, v in aliases.items()}
        self.output_keys = output_keys
        #: (min, max) of the objects with a narrower range than their data type (option codes, EDS limits,
        #: the axis' loop-gain bounds); ``range_reasons`` says why, appended to a refusal
        self.value_ranges = value_ranges
        self.range_reasons = range_reasons
        #: key (and alias) -> (min, max) of the integer objects whose check is the range alone (``plain_int_keys``)
        self.plain_int_ranges = self._plain_int_ranges(plain_int_keys)
        self.values: dict[Key, int | float] = {}
        self._changed: set[Key] = set()
        #: the actual values of the last :meth:`publish` in the order of ``output_keys`` (read only; a new tuple
        #: whenever a value changed: compare by identity to see whether anything did)
        self.outputs: tuple = (None,) * len(output_keys)
        #: where :meth:`publish` copies the changed outputs too (see :meth:`mirror_outputs`)
        self._mirror: tuple[tuple, tuple[bool, ...]] | None = None

    def _plain_int_ranges(self, keys: frozenset[Key]) -> dict[Key, tuple[int, int]]:
        out = {}
        for key in keys:
            spec = SPECS[key]
            lo, hi = DTYPE_RANGES[spec.dtype]
            lo2, hi2 = self.value_ranges.get(key, (lo, hi))
            out[key] = (max(lo, lo2), min(hi, hi2))
        for alias, target in self.aliases.items():
            if target in out:
                out[alias] = out[target]
        return out

    # ------------------------------------------------------------------ values
    def reset(self, values: dict[Key, int | float]) -> dict[Key, int | float]:
        """Every object to ``values`` (aliases copied from their objects), all marked changed, no outputs
        published; returns the value dict (the same object for the table's life)."""
        v = self.values
        v.clear()
        v.update(values)
        for alias, target in self.aliases.items():
            v[alias] = v[target]
        self._changed = set(v)
        self.outputs = (None,) * len(self.output_keys)
        return v

    def key(self, index: int, sub: int) -> Key:
        """The object ``(index, sub)`` stands for (itself unless an alias)."""
        key = (index, sub)
        return self.aliases.get(key, key)

    def read(self, index: int, sub: int = 0) -> int | float:
        key = self.key(index, sub)
        try:
            return self.values[key]
        except KeyError:
            raise ObjectAccessError(ABORT_NO_OBJECT, f"0x{index:04X}:{sub} is not a drive object") from None

    def store(self, key: Key, value: int | float) -> None:
        """Set an object (and its alias) without any reaction; marked changed if the value differs."""
        values = self.values
        if values.get(key) != value:
            values[key] = value
            self._changed.add(key)
            alias = self.aliases_back.get(key)
            if alias is not None:
                values[alias] = value
                self._changed.add(alias)

    def store_all(self, values: dict[Key, int | float]) -> None:
        """:meth:`store` of every item."""
        for key, value in values.items():
            self.store(key, value)

    def changed(self) -> bool:
        """Whether an object changed since :meth:`take_changed` (the outputs of a cycle not counted)."""
        return bool(self._changed)

    def take_changed(self) -> list[tuple[Key, int | float]]:
        """The objects changed since the last call: ((index, sub), value), values as of now."""
        if not self._changed:
            return []
        values = self.values
        out = [(k, values[k]) for k in self._changed]
        self._changed = set()
        return out

    # ------------------------------------------------------------------ per-cycle outputs
    def mirror_outputs(self, entries: Sequence[Any], real: Sequence[bool]) -> None:
        """From now on :meth:`publish` copies each output that changed into ``entries[i].value`` too (``None``:
        not mirrored), as ``float`` where ``real[i]``, and marks every TPDO in ``entries[i].tpdos`` that maps it
        (``.dirty = True``) when the entry's value changed: the CANopen dictionary gets a cycle's actual values in
        the one pass that stores them (a slave's entries; see :mod:`virtualaxis.drive.canopen_app`)."""
        if len(entries) != len(self.output_keys) or len(real) != len(self.output_keys):
            raise ValueError("one mirror entry and one real flag per output")
        self._mirror = (tuple(entries), tuple(bool(r) for r in real))
        current, self.outputs = self.outputs, (None,) * len(self.output_keys)
        self.publish(current)  # (the values already published go in now; nothing when none were)

    def publish(self, values: tuple) -> None:
        """The actual values of one cycle (``output_keys`` order): the changed ones into the objects (and the
        mirror's entries). Not marked in the changed set: a reader compares :attr:`outputs` by identity."""
        last = self.outputs
        if values == last:
            return
        objects = self.values
        mirror = self._mirror
        if mirror is None:
            for key, value, old in zip(self.output_keys, values, last, strict=True):
                if value != old:
                    objects[key] = value
        else:
            for key, value, old, entry, real in zip(self.output_keys, values, last, mirror[0], mirror[1],
                                                    strict=True):
                if value != old:
                    objects[key] = value
                    if entry is not None:
                        if real:
                            value = float(value)
                        if entry.value != value:
                            entry.value = value
                            for tpdo in entry.tpdos:
                                tpdo.dirty = True
        self.outputs = values

    # ------------------------------------------------------------------ write checks
    def check_write(self, index: int, sub: int, value) -> ObjectSpec | None:
        """The checks of every write path: the object exists and is writable, ``value`` is a finite number
        (an integer for an integer type) within its data type and value range. Raises
        :class:`ObjectAccessError` with the SDO abort code; returns ``None`` for an integer object whose only
        rule is its range (nothing more to check), else the object's spec (the caller's own rules follow)."""
        plain = self.plain_int_ranges.get((index, sub))
        if plain is not None and type(value) is int and plain[0] <= value <= plain[1]:
            return None
        key = self.key(index, sub)
        spec = SPECS.get(key)
        if spec is None or key not in self.values:
            raise ObjectAccessError(ABORT_NO_OBJECT, f"0x{index:04X}:{sub} is not a drive object")
        if spec.access == "ro":
            raise ObjectAccessError(ABORT_READ_ONLY, f"0x{index:04X}:{sub} {spec.name} is read-only")
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise ObjectAccessError(ABORT_VALUE_INVALID, f"0x{index:04X}:{sub} needs a number")
        if spec.dtype != "f32" and value != int(value):
            raise ObjectAccessError(ABORT_VALUE_INVALID, f"0x{index:04X}:{sub} needs an integer")
        lo, hi = DTYPE_RANGES[spec.dtype]
        if value > hi:
            raise ObjectAccessError(ABORT_VALUE_TOO_HIGH, f"0x{index:04X}:{sub} {spec.name}: {value} > {hi}")
        if value < lo:
            raise ObjectAccessError(ABORT_VALUE_TOO_LOW, f"0x{index:04X}:{sub} {spec.name}: {value} < {lo}")
        bounds = self.value_ranges.get(key)
        if bounds is not None:
            lo2, hi2 = bounds
            if value > hi2:
                raise ObjectAccessError(ABORT_VALUE_TOO_HIGH, f"0x{index:04X}:{sub} {spec.name}: {value} > {hi2}"
                                        + self.range_reasons.get(key, ""))
            if value < lo2:
                raise ObjectAccessError(ABORT_VALUE_TOO_LOW, f"0x{index:04X}:{sub} {spec.name}: {value} < {lo2}")
        return spec
