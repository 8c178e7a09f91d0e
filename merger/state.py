"""The merger's state file: everything a merger needs to resume where it stopped
(:meth:`~fleetmap.merger.engine.Merger.save_state`, ``fleetmap merger --state``).

One msgpack map of version :data:`STATE_VERSION`: the submaps as received, in the order they
entered the graph, the integrations (the robots' links come back with their submaps), the robots,
the pair queue and what decided it, the submaps received and not yet taken in, the last step's
messages. A file of another version, or one that does not parse, is refused as bad input.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import msgpack
import numpy as np
from fleetmap.merger.graph import Edge
from fleetmap.merger.outputs import Outgoing, Robot
from fleetmap.shared.core.geometry import Transform2D
from fleetmap.shared.core.integration import Window
from fleetmap.shared.errors import BadInput
from fleetmap.shared.io.messages import BadMessage, LocalMap, decode

STATE_VERSION = 2
"""The format of the state file a merger saves; a file of another is refused."""


@dataclass
class MergerState:
    seq: int
    stamp: float
    submaps: list[LocalMap]
    """In the order they entered the graph."""
    edges: list[Edge]
    """The integrations (not the links: they come back with their submaps)."""
    robots: dict[str, Robot]
    queue: dict[tuple[str, str], Transform2D | None]
    pending: list[LocalMap]
    scheduled: dict[str, int]
    finals: int
    far_tries: dict[str, int]
    last_out: list[Outgoing]
    behind: bool = False
    """Whether the last step left pairs queued (:attr:`~fleetmap.merger.schedule.PairSchedule.behind`)."""
    windows: dict[tuple[str, str], Window] = field(default_factory=dict)
    """Where queued pose-free pairs search (:attr:`~fleetmap.merger.schedule.PairSchedule.windows`)."""


def write_state(path: str | Path, state: MergerState) -> None:
    """Write a state file to a temporary file and rename it, so a merger killed while saving
    leaves the previous state whole."""
    packed = {
        "v": STATE_VERSION,
        "seq": state.seq,
        "stamp": state.stamp,
        "submaps": [m.to_msgpack() for m in state.submaps],
        "edges": [_edge_to_dict(e) for e in state.edges],
        "robots": {name: _robot_to_dict(r) for name, r in state.robots.items()},
        "queue": [[a, b, None if t is None else [t.x, t.y, t.theta]] for (a, b), t in state.queue.items()],
        "pending": [m.to_msgpack() for m in state.pending],
        "scheduled": state.scheduled,
        "finals": state.finals,
        "far_tries": state.far_tries,
        "behind": state.behind,
        "windows": [
            [a, b, w.centre.x, w.centre.y, w.centre.theta, w.radius, w.rotation] for (a, b), w in state.windows.items()
        ],
        "last_out": [[o.key, o.payload] for o in state.last_out],
    }
    p = Path(path)
    tmp = p.with_name(p.name + ".tmp")
    try:
        with open(tmp, "wb") as fh:
            fh.write(msgpack.packb(packed, use_bin_type=True))
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, p)
    except OSError:
        tmp.unlink(missing_ok=True)  # a half-written state would only take the space a retry needs
        raise


def read_state(path: str | Path) -> MergerState:
    """A state file :func:`write_state` wrote; :class:`BadInput` naming the file if it is not one."""
    source = str(path)
    try:
        state = msgpack.unpackb(Path(path).read_bytes(), raw=False)
        if not isinstance(state, dict) or state.get("v") != STATE_VERSION:
            raise BadInput(source, f"not a fleetmap merger state file (version {STATE_VERSION})")
        submaps = []
        for payload in state["submaps"]:
            m = decode(bytes(payload))
            if not isinstance(m, LocalMap):
                raise ValueError(f"a saved submap is a {m.SCHEMA}")
            submaps.append(m)
        edges = [_edge_from_dict(e) for e in state["edges"]]
        robots = {name: _robot_from_dict(r) for name, r in state["robots"].items()}
        queue: dict[tuple[str, str], Transform2D | None] = {}
        for a, b, t in state.get("queue", []):
            queue[(str(a), str(b))] = None if t is None else Transform2D(*t)
        pending = [decode(bytes(payload)) for payload in state.get("pending", [])]
        if not all(isinstance(m, LocalMap) for m in pending):
            raise ValueError("a saved pending submap is not a LocalMap")
        return MergerState(
            seq=int(state["seq"]),
            stamp=float(state["stamp"]),
            submaps=submaps,
            edges=edges,
            robots=robots,
            queue=queue,
            pending=[m for m in pending if isinstance(m, LocalMap)],
            scheduled={str(k): int(v) for k, v in state.get("scheduled", {}).items()},
            finals=int(state.get("finals", 0)),
            far_tries={str(k): int(v) for k, v in state.get("far_tries", {}).items()},
            last_out=[Outgoing(str(key), bytes(payload)) for key, payload in state.get("last_out", [])],
            behind=bool(state.get("behind", False)),
            windows={
                (str(a), str(b)): Window(Transform2D(float(x), float(y), float(t)), float(r), float(q))
                for a, b, x, y, t, r, q in state.get("windows", [])
            },
        )
    except (
        OSError,
        ValueError,
        KeyError,
        TypeError,
        IndexError,
        AttributeError,
        msgpack.UnpackException,
        BadMessage,
    ) as exc:  # any shape of file: the merger's own of another version, or not its at all
        raise BadInput(source, f"cannot load the merger state (not one a merger saved): {exc}"[:300]) from None


def _edge_to_dict(e: Edge) -> dict[str, Any]:
    return {
        "a": e.a,
        "b": e.b,
        "t": [e.transform.x, e.transform.y, e.transform.theta],
        "value": e.value,
        "valid": e.valid,
        "runner_up": e.runner_up,
        "seconds": e.seconds,
        "versions": list(e.versions),
        "violation": e.violation,
        "solid_violation": e.solid_violation,
        "information": None if e.information is None else list(e.information),
        "rivals": [[t.x, t.y, t.theta] for t in e.rivals],
    }


def _edge_from_dict(e: dict[str, Any]) -> Edge:
    return Edge(
        e["a"],
        e["b"],
        Transform2D(*e["t"]),
        float(e["value"]),
        bool(e["valid"]),
        float(e["runner_up"]),
        float(e["seconds"]),
        (int(e["versions"][0]), int(e["versions"][1])),
        float(e.get("violation", 0.0)),
        None if e.get("solid_violation") is None else float(e["solid_violation"]),
        _information(e.get("information")),
        rivals=tuple(Transform2D(*t) for t in e.get("rivals", [])),
    )


def _robot_to_dict(r: Robot) -> dict[str, Any]:
    return {
        "epoch": r.epoch,
        "stamp": r.stamp,
        "at": None if r.at is None else [r.at[0], r.at[1].x, r.at[1].y, r.at[1].theta],
        "relocalized": sorted(r.relocalized),
    }


def _robot_from_dict(r: dict[str, Any]) -> Robot:
    at = r.get("at")
    return Robot(
        epoch=int(r["epoch"]),
        stamp=float(r["stamp"]),
        at=None if at is None else (str(at[0]), Transform2D(float(at[1]), float(at[2]), float(at[3]))),
        relocalized={int(x) for x in r["relocalized"]},
    )


def _information(value: object) -> tuple[float, ...] | None:
    """An edge's saved :attr:`~fleetmap.merger.graph.Edge.information` (None: not saved)."""
    if value is None:
        return None
    if not isinstance(value, list) or len(value) != 9:
        raise ValueError(f"an edge's information must be a list of 9 numbers, got {value!r}")
    h = np.array([float(v) for v in value]).reshape(3, 3)
    scale = float(np.abs(h).max()) if np.isfinite(h).all() else math.inf
    if not math.isfinite(scale) or not np.allclose(h, h.T, rtol=1e-9, atol=1e-12 * scale):
        raise ValueError(f"an edge's information must be a finite symmetric matrix, got {value!r}")
    if np.linalg.eigvalsh(h).min() < -1e-9 * scale:
        raise ValueError(f"an edge's information must be positive semidefinite, got {value!r}")
    return tuple(h.ravel().tolist())
