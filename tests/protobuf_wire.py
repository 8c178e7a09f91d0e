"""A small protobuf decoder driven by a schema's FileDescriptorSet, for checking Foxglove channels.

An MCAP protobuf schema carries a serialized ``google.protobuf.FileDescriptorSet``; decoding a
message with it (and with nothing else: no generated code, no protobuf package) proves that the
recording is readable by anyone who follows the schema, as Foxglove does. Messages decode to
dicts keyed by field name; repeated fields are lists; absent fields are absent.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from typing import Any

# FieldDescriptorProto.Type
DOUBLE, FLOAT, INT64, UINT64, INT32, FIXED64, FIXED32, BOOL, STRING = 1, 2, 3, 4, 5, 6, 7, 8, 9
MESSAGE, BYTES, UINT32, ENUM, SFIXED32, SFIXED64, SINT32, SINT64 = 11, 12, 13, 14, 15, 16, 17, 18
REPEATED = 3
VARINT_TYPES = {INT64, UINT64, INT32, BOOL, UINT32, ENUM, SINT32, SINT64}


def _varint(data: bytes, i: int) -> tuple[int, int]:
    value = shift = 0
    while True:
        byte = data[i]
        i += 1
        value |= (byte & 0x7F) << shift
        shift += 7
        if not byte & 0x80:
            return value, i


def _fields(data: bytes) -> list[tuple[int, int, Any]]:
    """(field number, wire type, raw value) of every field of one message."""
    out = []
    i = 0
    while i < len(data):
        key, i = _varint(data, i)
        number, wire = key >> 3, key & 7
        if wire == 0:
            value, i = _varint(data, i)
        elif wire == 1:
            value, i = data[i : i + 8], i + 8
        elif wire == 2:
            size, i = _varint(data, i)
            value, i = data[i : i + size], i + size
        elif wire == 5:
            value, i = data[i : i + 4], i + 4
        else:
            raise ValueError(f"unsupported wire type {wire}")
        out.append((number, wire, value))
    return out


@dataclass(frozen=True)
class Field:
    name: str
    number: int
    repeated: bool
    type: int
    type_name: str


def _scalar(kind: int, wire: int, raw: Any) -> Any:
    if kind == DOUBLE:
        return struct.unpack("<d", raw)[0]
    if kind == FLOAT:
        return struct.unpack("<f", raw)[0]
    if kind in (FIXED64, SFIXED64):
        return struct.unpack("<q" if kind == SFIXED64 else "<Q", raw)[0]
    if kind in (FIXED32, SFIXED32):
        return struct.unpack("<i" if kind == SFIXED32 else "<I", raw)[0]
    if kind == BOOL:
        return bool(raw)
    if kind in (SINT32, SINT64):
        return (raw >> 1) ^ -(raw & 1)
    if kind in (INT32, INT64) and raw >= 2**63:
        return raw - 2**64
    if kind == STRING:
        return raw.decode("utf-8")
    return raw


def _unpack_packed(kind: int, raw: bytes) -> list[Any]:
    if kind in VARINT_TYPES:
        values, i = [], 0
        while i < len(raw):
            value, i = _varint(raw, i)
            values.append(_scalar(kind, 0, value))
        return values
    size = 8 if kind in (DOUBLE, FIXED64, SFIXED64) else 4
    return [_scalar(kind, 1, raw[j : j + size]) for j in range(0, len(raw), size)]


class Schema:
    """The message types of a FileDescriptorSet, by full name (``foxglove.SceneUpdate``)."""

    def __init__(self, file_descriptor_set: bytes) -> None:
        self.messages: dict[str, dict[int, Field]] = {}
        for number, _, file_bytes in _fields(file_descriptor_set):
            if number != 1:
                continue
            file_fields = _fields(file_bytes)
            package = next((v.decode() for n, _, v in file_fields if n == 2), "")
            for n, _, message_bytes in file_fields:
                if n == 4:
                    self._add_message(package, message_bytes)

    def _add_message(self, scope: str, data: bytes) -> None:
        parts = _fields(data)
        name = next(v.decode() for n, _, v in parts if n == 1)
        full = f"{scope}.{name}" if scope else name
        table: dict[int, Field] = {}
        for n, _, value in parts:
            if n == 2:
                f = {k: v for k, _, v in _fields(value)}
                table[f[3]] = Field(f[1].decode(), f[3], f.get(4) == REPEATED, f[5], f.get(6, b"").decode().lstrip("."))
            elif n == 3:
                self._add_message(full, value)
        self.messages[full] = table

    def decode(self, type_name: str, data: bytes) -> dict[str, Any]:
        table = self.messages[type_name]
        out: dict[str, Any] = {}
        for number, wire, raw in _fields(data):
            if number not in table:
                raise ValueError(f"{type_name} has no field {number}")
            f = table[number]
            if f.type == MESSAGE:
                values = [self.decode(f.type_name, raw)]
            elif f.repeated and wire == 2 and f.type not in (STRING, BYTES):
                values = _unpack_packed(f.type, raw)
            else:
                values = [_scalar(f.type, wire, raw)]
            if f.repeated:
                out.setdefault(f.name, []).extend(values)
            else:
                out[f.name] = values[0]
        return out
