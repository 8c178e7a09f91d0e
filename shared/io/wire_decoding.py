"""Decoding a payload's msgpack within bounds: what a payload costs to decode grows with its size,
not with what it packs.

Every item's header is checked against the limits before it is allocated, and what is decoded is
counted as it is built (:class:`_DecodeBudget`), so a payload costs at most a fixed multiple of its
size whatever it packs (docs/decisions/013-input-that-looks-legitimate.md). Fields the payload's
message does not have are skipped without being decoded. Which fields a message has is the
caller's to say (:data:`FieldsOf`): the messages are in :mod:`fleetmap.shared.io.messages`.
"""

from __future__ import annotations

import sys
from collections.abc import Callable, Mapping, Set
from typing import Any

import msgpack
from fleetmap.shared.io.wire_fields import MAX_MAPS, MAX_SEGMENTS, BadMessage

MAX_PAYLOAD_BYTES = 16 * 1024 * 1024
"""Payloads larger than this are refused before they are unpacked: the largest message fleetmap
sends, a global map of ``MAX_SEGMENTS`` packed segments, is 6.4 MB, while a payload of small
integers unpacks into Python objects tens of times its size, in every subscriber
(docs/decisions/003-a-fleet-that-lets-in-only-its-own.md)."""

FieldsOf = Callable[[Mapping[str, Any]], tuple[Set[str], Set[str]]]
"""``fields_of(raw)``: given a payload's ``schema`` and ``v``, the names of its message's fields and
those of them whose value is a msgpack map or array; BadMessage for a message not read here."""

_CONTAINER_HEADERS = frozenset([*range(0x80, 0xA0), 0xDC, 0xDD, 0xDE, 0xDF])
"""The first byte of a msgpack map or array (fixmap, fixarray, array 16/32, map 16/32)."""


_LIMITS: dict[str, Any] = {
    # each checked against its header before anything is allocated
    "max_array_len": 4 * MAX_SEGMENTS,
    "max_map_len": MAX_MAPS + 64,
    "max_str_len": 64 * 1024,
    "max_bin_len": MAX_PAYLOAD_BYTES,
    "max_ext_len": 0,
}
MAX_FIELDS = 64
"""The most fields one message's top-level map may have (fleetmap's messages have at most 16)."""
DECODED_BYTES_PER_BYTE = 16
"""The decoding budget: what a payload decodes into (its containers and their items, as Python
objects) may take this many bytes per payload byte, plus :data:`DECODED_SLACK`. Messages as
fleetmap sends them carry their bulk in bins, about one byte per byte; a transform, the densest
part, takes 11 (38 bytes on the wire, 410 as a dict); a payload of empty lists would take 64."""
DECODED_SLACK = 1024 * 1024
"""... plus this much, for small messages of many little fields."""
_MOST_PER_BYTE = 64
"""The most one payload byte can decode into (an empty list: 56 bytes, and its slot in its
container), so a payload of at most ``DECODED_SLACK / (_MOST_PER_BYTE - DECODED_BYTES_PER_BYTE)``
bytes is within its budget whatever it holds and is decoded without counting."""


class _OverBudget(Exception):
    pass


class _DecodeBudget:
    """Counts what msgpack decodes, container by container as each is built, and stops decoding
    past the payload's budget: memory grows with the payload's size, not with how many items it
    packs (a 16 MB payload of empty lists would otherwise take a gigabyte)."""

    def __init__(self, size: int) -> None:
        self.left = DECODED_BYTES_PER_BYTE * size + DECODED_SLACK

    def _charge(self, size: int) -> None:
        self.left -= size
        if self.left < 0:
            raise _OverBudget

    def on_list(self, items: list[Any]) -> list[Any]:
        self._charge(sys.getsizeof(items) + sum(map(sys.getsizeof, items)))
        return items

    def on_map(self, entries: dict[str, Any]) -> dict[str, Any]:
        keys = sum(map(sys.getsizeof, entries.keys()))
        self._charge(sys.getsizeof(entries) + keys + sum(map(sys.getsizeof, entries.values())))
        return entries

    def unpacker(self, data: bytes | bytearray | memoryview) -> msgpack.Unpacker:
        unpacker = msgpack.Unpacker(
            None,
            raw=False,
            strict_map_key=True,
            list_hook=self.on_list,
            object_hook=self.on_map,
            max_buffer_size=max(len(data), 1),
            **_LIMITS,
        )
        unpacker.feed(data)
        return unpacker


def _top_level(data: bytes | bytearray | memoryview, budget: _DecodeBudget, fields_of: FieldsOf) -> dict[str, Any]:
    """The payload's map of fields, in two passes: the first decodes ``schema`` and ``v`` only,
    the second its message's fields; any other field is skipped over without being decoded (a
    newer sender's field, or a decoding bomb under a name no message has), and a map or array
    where its message has a single value or packed bytes is refused from its first byte."""
    raw: dict[str, Any] = {}
    passes: tuple[Set[str] | None, ...] = (frozenset({"schema", "v"}), None)
    containers: Set[str] = frozenset()
    for names in passes:
        unpacker = budget.unpacker(data)
        try:
            entries = unpacker.read_map_header()
        except msgpack.OutOfData:
            raise BadMessage("message", None, "not msgpack: no data") from None
        except ValueError:  # not a map: decode it (within the budget) to say what it is
            whole = budget.unpacker(data).unpack()
            raise BadMessage("message", None, f"expected a msgpack map, got {type(whole).__name__}") from None
        if entries > MAX_FIELDS:
            raise BadMessage("message", None, f"{entries} fields is more than {MAX_FIELDS}")
        if names is None:
            names, containers = fields_of(raw)
        for _ in range(entries):
            name = unpacker.unpack()
            if not isinstance(name, str):
                raise BadMessage("message", None, f"not msgpack of named fields: a name is a {type(name).__name__}")
            if name not in names:
                unpacker.skip()
                continue
            if name not in containers and name not in ("schema", "v") and data[unpacker.tell()] in _CONTAINER_HEADERS:
                raise BadMessage(raw["schema"], name, "expected one value or packed bytes, got a msgpack map or array")
            raw[name] = unpacker.unpack()
        try:
            unpacker.skip()
        except msgpack.OutOfData:
            continue
        raise BadMessage("message", None, "not msgpack: extra data after the message")
    return raw


def unpack_bounded(data: bytes | bytearray | memoryview, fields_of: FieldsOf) -> dict[str, Any]:
    """The msgpack map of a payload, decoded within bounds: a small payload at once (whatever it
    holds, it is within its budget), a larger one field by field (:func:`_top_level`), keeping only
    the fields ``fields_of`` names. BadMessage says what is wrong with a payload that is too large,
    not msgpack, not a map, or that decodes into more than its budget."""
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise BadMessage("message", None, f"expected bytes, got {type(data).__name__}")
    if len(data) > MAX_PAYLOAD_BYTES:
        raise BadMessage("message", None, f"{len(data)} bytes is more than {MAX_PAYLOAD_BYTES}")
    try:
        if len(data) * (_MOST_PER_BYTE - DECODED_BYTES_PER_BYTE) <= DECODED_SLACK:
            raw = msgpack.unpackb(data, raw=False, strict_map_key=True, **_LIMITS)
            if not isinstance(raw, dict):
                raise BadMessage("message", None, f"expected a msgpack map, got {type(raw).__name__}")
        else:
            raw = _top_level(data, _DecodeBudget(len(data)), fields_of)
    except _OverBudget:
        raise BadMessage(
            "message", None, f"{len(data)} bytes decode into more than {DECODED_BYTES_PER_BYTE} times their size"
        ) from None
    except (msgpack.UnpackException, ValueError) as exc:
        raise BadMessage("message", None, f"not msgpack: {exc}"[:200]) from None
    return raw
