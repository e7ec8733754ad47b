"""A Sparkplug B payload decoder and encoder of the tests, independent of the package's: it reads the protobuf wire
format itself (no protobuf library, no generated module) with the field numbers of the Sparkplug 3.0
specification's payload definition (Payload, Metric, PropertySet, PropertyValue)."""

from __future__ import annotations

import struct

# Sparkplug B DataType numbers (specification, "Data Types")
DATATYPES = {1: "Int8", 2: "Int16", 3: "Int32", 4: "Int64", 5: "UInt8", 6: "UInt16", 7: "UInt32", 8: "UInt64",
             9: "Float", 10: "Double", 11: "Boolean", 12: "String", 13: "DateTime", 14: "Text"}


def _varint(buf: bytes, i: int) -> tuple[int, int]:
    shift = result = 0
    while True:
        if i >= len(buf):
            raise ValueError("truncated varint")
        b = buf[i]
        i += 1
        result |= (b & 0x7F) << shift
        if not b & 0x80:
            return result, i
        shift += 7


def fields(buf: bytes) -> list[tuple[int, int, object]]:
    """``[(field number, wire type, raw value)]`` of one message."""
    out = []
    i = 0
    while i < len(buf):
        key, i = _varint(buf, i)
        number, wire = key >> 3, key & 7
        if wire == 0:
            value, i = _varint(buf, i)
        elif wire == 1:
            value, i = buf[i:i + 8], i + 8
        elif wire == 2:
            n, i = _varint(buf, i)
            value, i = buf[i:i + n], i + n
        elif wire == 5:
            value, i = buf[i:i + 4], i + 4
        else:
            raise ValueError(f"wire type {wire}")
        out.append((number, wire, value))
    return out


def _property_set(buf: bytes) -> dict:
    keys, values = [], []
    for number, _, raw in fields(buf):
        if number == 1:
            keys.append(raw.decode())
        elif number == 2:
            v = None
            for n, _, r in fields(raw):
                if n == 3 or n == 4:
                    v = r
                elif n == 6:
                    v = struct.unpack("<d", r)[0]
                elif n == 7:
                    v = bool(r)
                elif n == 8:
                    v = r.decode()
            values.append(v)
    return dict(zip(keys, values, strict=True))


def _metric(buf: bytes) -> dict:
    m: dict = {}
    for number, _, raw in fields(buf):
        if number == 1:
            m["name"] = raw.decode()
        elif number == 2:
            m["alias"] = raw
        elif number == 3:
            m["timestamp"] = raw
        elif number == 4:
            m["datatype"] = raw
        elif number == 7:
            m["is_null"] = bool(raw)
        elif number == 9:
            m["properties"] = _property_set(raw)
        elif number in (10, 11):
            m["value"] = raw  # int_value (uint32) / long_value (uint64): signed types are two's complement
        elif number == 12:
            m["value"] = struct.unpack("<f", raw)[0]
        elif number == 13:
            m["value"] = struct.unpack("<d", raw)[0]
        elif number == 14:
            m["value"] = bool(raw)
        elif number == 15:
            m["value"] = raw.decode()
        elif number == 16:
            m["value"] = bytes(raw)
    return m


def decode(payload: bytes) -> dict:
    """``{"timestamp", "seq", "metrics": [{"name", "alias", "timestamp", "datatype", "value", "properties"}]}``
    (keys present only when the field is)."""
    out: dict = {"metrics": []}
    for number, _, raw in fields(payload):
        if number == 1:
            out["timestamp"] = raw
        elif number == 2:
            out["metrics"].append(_metric(raw))
        elif number == 3:
            out["seq"] = raw
    return out


def _key(number: int, wire: int) -> bytes:
    return _enc_varint(number << 3 | wire)


def _enc_varint(n: int) -> bytes:
    out = bytearray()
    while True:
        b = n & 0x7F
        n >>= 7
        if n:
            out.append(b | 0x80)
        else:
            out.append(b)
            return bytes(out)


def _len(number: int, data: bytes) -> bytes:
    return _key(number, 2) + _enc_varint(len(data)) + data


def encode_command(metrics: list[dict], timestamp_ms: int = 0) -> bytes:
    """An NCMD / DCMD payload: each metric ``{"name" | "alias", "datatype", "value"}`` (Boolean, String, Int)."""
    out = _key(1, 0) + _enc_varint(timestamp_ms)
    for m in metrics:
        body = b""
        if "name" in m:
            body += _len(1, m["name"].encode())
        if "alias" in m:
            body += _key(2, 0) + _enc_varint(m["alias"])
        body += _key(4, 0) + _enc_varint(m["datatype"])
        v = m["value"]
        if isinstance(v, bool):
            body += _key(14, 0) + _enc_varint(int(v))
        elif isinstance(v, str):
            body += _len(15, v.encode())
        elif isinstance(v, int):
            body += _key(10, 0) + _enc_varint(v)
        out += _len(2, body)
    return out
