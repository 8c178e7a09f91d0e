"""The wire form of a message's values: what msgpack packs for each field.

Arrays travel as one ``bin`` of little-endian numbers (int64, float32 for laser readings, float64
otherwise), transforms as maps ``{"x", "y", "theta"}``, parts as maps of their fields. A global
map's component keeps its wire form once made: a merger publishes again, at every step, the
components no step changed.
"""

from __future__ import annotations

import weakref
from collections.abc import Mapping
from dataclasses import fields, is_dataclass
from typing import Any

import numpy as np
from fleetmap.shared.core.geometry import Transform2D
from fleetmap.shared.io.message_parts import Component

_COMPONENT_WIRE: weakref.WeakKeyDictionary[Component, dict[str, Any]] = weakref.WeakKeyDictionary()
"""Each global-map component's wire form, made once: a merger publishes the components no step
changed again at every step."""


def to_wire(value: Any) -> Any:
    if isinstance(value, Component):
        held = _COMPONENT_WIRE.get(value)
        if held is None:
            held = _COMPONENT_WIRE[value] = {f.name: to_wire(getattr(value, f.name)) for f in fields(value)}
        return held
    if isinstance(value, np.ndarray):
        if value.dtype.kind in "iu":
            return np.ascontiguousarray(value, dtype="<i8").tobytes()
        return np.ascontiguousarray(value, dtype="<f4" if value.dtype == np.float32 else "<f8").tobytes()
    if isinstance(value, Transform2D):
        return {"x": value.x, "y": value.y, "theta": value.theta}
    if is_dataclass(value) and not isinstance(value, type):
        return {f.name: to_wire(getattr(value, f.name)) for f in fields(value)}
    if isinstance(value, Mapping):
        return {k: to_wire(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [to_wire(v) for v in value]
    return value
