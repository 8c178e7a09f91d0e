"""``fleetmap replay``: a recorded session fed through a fresh merger, offline.

The merger is deterministic given the same local maps in the same order, and the live merger
published, step by step, which local map versions it integrated (``MergerStep``). A full replay
follows those steps with the recorded local maps, so it rebuilds exactly the live global map, even
where the recorder heard two robots in the other order. Where the merger restarted (a
``merger_start`` event after its first step), the replay's merger restarts too, at the same step: from its own state
file when the live one resumed from its state (its steps go on numbering), empty when it started
afresh (they start again at 1). A partial replay (``--from``/``--to``,
``--robots``) feeds the selected local maps in recording order instead. A recording cut short by a
crash is read up to its last complete chunk, with a warning saying how much was read.
"""

from __future__ import annotations

import functools
import logging
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from fleetmap.merger.engine import Merger
from fleetmap.report import SessionLog, make_truth, write_outputs
from fleetmap.scenarios import Scenario
from fleetmap.scenarios.loader import read_scenario
from fleetmap.shared.config import FleetmapConfig
from fleetmap.shared.config_files import apply_overrides
from fleetmap.shared.errors import BadInput
from fleetmap.shared.io.keys import FleetKeys
from fleetmap.shared.io.messages import BadMessage, FleetEvent, GlobalMap, LocalMap, MergerStep, Scan, decode
from fleetmap.shared.io.outputs import output_folder
from fleetmap.shared.io.recording_reader import RecordedMessage, RecordingReader

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ReplayOptions:
    speed: float = 0.0
    """0: as fast as possible; otherwise the recording's own pace times this factor."""
    start: float | None = None
    """Seconds from the start of the recording (partial replay)."""
    stop: float | None = None
    robots: frozenset[str] | None = None
    config: FleetmapConfig | None = None
    """Overrides the configuration stored in the recording."""


@dataclass
class ReplayResult:
    report: dict[str, Any]
    exact: bool
    """Whether the replay followed the live merger's steps."""
    warning: str | None = None
    live: GlobalMap | None = None
    replayed: GlobalMap | None = None
    steps: int = 0
    inputs: list[str] = field(default_factory=list)


def same_global_map(a: GlobalMap | None, b: GlobalMap | None) -> bool:
    """Identical components: anchors, members, poses and segments, number for number."""
    if a is None or b is None or len(a.components) != len(b.components):
        return a is None and b is None
    for ca, cb in zip(a.components, b.components, strict=True):
        if ca.anchor != cb.anchor or tuple(ca.members) != tuple(cb.members):
            return False
        if any(ca.poses[k] != cb.poses[k] for k in ca.members):
            return False
        if not np.array_equal(np.asarray(ca.segments), np.asarray(cb.segments)):
            return False
    return True


def _metadata_config(meta: dict[str, dict[str, str]]) -> FleetmapConfig:
    text = meta.get("fleetmap.config", {}).get("toml")
    if not text:
        return FleetmapConfig()
    import tomllib

    return apply_overrides(FleetmapConfig(), tomllib.loads(text), "the recording's config")


def _metadata_scenario(meta: dict[str, dict[str, str]]) -> Scenario | None:
    text = meta.get("fleetmap.scenario", {}).get("toml")
    if not text:
        return None
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "scenario.toml"
        path.write_text(text, encoding="utf-8")
        return read_scenario(path)


def replay(
    path: str | Path,
    out_dir: str | Path,
    options: ReplayOptions | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> ReplayResult:
    opts = options or ReplayOptions()
    source = str(path)
    meta, recorded, warning = _read(path)
    fleet = meta.get("fleetmap.session", {}).get("fleet", "default")
    keys = FleetKeys(fleet)
    config = opts.config or _metadata_config(meta)
    scenario = _metadata_scenario(meta)
    merger = Merger(keys, config)
    session = SessionLog()
    chosen = _Selection(opts, recorded[0].log_time if recorded else 0)
    decoded = _decoded(recorded, keys, session)
    if not decoded:
        why = f" ({warning.removeprefix(source + ': ')})" if warning else ""
        raise BadInput(source, f"holds no fleetmap message of fleet {fleet!r}{why}")
    if warning:
        log.warning("%s", warning)
    if opts.robots is not None:
        _check_robots(opts.robots, decoded, source)
    output_folder(out_dir, "--out")
    steps, live, compared, restarts = _steps_and_live_maps(decoded)
    exact = bool(steps) and not chosen.partial
    _add_robot_side(session, decoded, chosen)
    take = functools.partial(_take, session)
    inputs: list[str] = []
    at_live: GlobalMap | None = None
    pace = _Pacer(opts.speed)
    stepped = 0
    if exact:
        merger, at_live, stepped = _follow_steps(
            merger, steps, restarts, decoded, compared, pace, take, inputs, progress
        )
    else:
        maps = [
            (m, msg) for m, msg in decoded if isinstance(msg, LocalMap) and chosen.wanted(msg) and chosen.selected(m)
        ]
        _feed_in_order(merger, maps, pace, take, inputs, progress)
    report = write_outputs(session, make_truth(scenario), out_dir, f"fleetmap replay: {Path(path).name}")
    stepped = stepped or merger.stats.steps
    result = ReplayResult(report, exact, warning, live, merger.global_map, stepped, inputs)
    report["replay"] = {
        "exact": exact,
        "steps": stepped,
        "merger_restarts": len(restarts) if exact else 0,
        "local_maps_fed": len(inputs),
        # against the map of the step that published the live one: a recording cut by a crash may
        # hold maps no recorded step took, which the replay goes on to integrate after it
        "matches_live": same_global_map(compared, at_live or merger.global_map) if exact else None,
        "warning": warning,
    }
    from fleetmap.runner import _write_json

    _write_json(Path(out_dir) / "report.json", report)
    return result


def _read(path: str | Path) -> tuple[dict[str, dict[str, str]], list[RecordedMessage], str | None]:
    """A recording's metadata, its raw messages and the warning of a file cut short (or None)."""
    if not Path(path).exists():
        raise BadInput(str(path), "no such file")
    with RecordingReader(path) as reader:
        meta = reader.metadata()
        recorded = list(reader.messages(warn=False))
        warning = reader.report.warning
    return meta, recorded, warning


@dataclass(frozen=True)
class _Selection:
    """What of a recording a replay takes: the time window and the robots its options name."""

    opts: ReplayOptions
    t_first: int
    """The first message's log time (ns): the window's seconds count from it."""

    @property
    def partial(self) -> bool:
        return self.opts.start is not None or self.opts.stop is not None or self.opts.robots is not None

    def selected(self, m: RecordedMessage) -> bool:
        t = (m.log_time - self.t_first) / 1e9
        return (self.opts.start is None or t >= self.opts.start) and (self.opts.stop is None or t <= self.opts.stop)

    def wanted(self, msg: Any) -> bool:
        robot = getattr(msg, "robot", None)
        return self.opts.robots is None or robot is None or robot in self.opts.robots


def _add_robot_side(session: SessionLog, decoded: list[tuple[RecordedMessage, Any]], chosen: _Selection) -> None:
    """The robots' side of the session (scans, epochs, local maps) into the report, as recorded."""
    for m, msg in decoded:
        robot_side = isinstance(msg, (Scan, LocalMap)) or (isinstance(msg, FleetEvent) and msg.kind == "epoch")
        if robot_side and chosen.wanted(msg) and (not chosen.partial or chosen.selected(m)):
            session.add(msg)


def _take(session: SessionLog, outgoing: list[Any]) -> None:
    """The replayed merger's outputs into the report."""
    for o in outgoing:
        try:
            session.add(decode(o.payload))
        except BadMessage:  # our own messages: cannot happen, but never fatal
            session.malformed += 1


def _decoded(
    recorded: list[RecordedMessage], keys: FleetKeys, session: SessionLog
) -> list[tuple[RecordedMessage, Any]]:
    """The recorded messages of the fleet, decoded (those that do not decode counted in ``session``)."""
    decoded: list[tuple[RecordedMessage, Any]] = []
    for m in recorded:
        if not m.topic.startswith(keys.prefix + "/"):
            continue
        try:
            decoded.append((m, decode(m.payload)))
        except BadMessage:
            session.malformed += 1
    return decoded


def _check_robots(robots: frozenset[str], decoded: list[tuple[RecordedMessage, Any]], source: str) -> None:
    """``--robots``: every robot named is one the recording holds."""
    present = {r for _, msg in decoded if (r := getattr(msg, "robot", None)) is not None}
    if missing := sorted(robots - present):
        listed = ", ".join(sorted(present)) or "none"
        raise BadInput("--robots", f"no robot {', '.join(missing)} in {source} (its robots: {listed})")


def _steps_and_live_maps(
    decoded: list[tuple[RecordedMessage, Any]],
) -> tuple[list[MergerStep], GlobalMap | None, GlobalMap | None, dict[int, bool]]:
    """The merger's steps as recorded, its last global map, the last one whose step the recording
    holds (the live map a replay is compared with: a recorder killed between a step's global map
    and its MergerStep kept the map, not the step), and the merger's restarts: before which step
    (index), and whether it resumed from its state (the step numbers go on) or not."""
    # A merger restored from its state publishes its last step again (Merger.where_it_stands):
    # the same bytes, fed once.
    steps: list[MergerStep] = []
    fed: set[bytes] = set()
    # A restarted merger says merger_start, publishes where it stands (a step the killed one had
    # saved but maybe not published: that one's, not the new one's), then asks for the robots'
    # maps (republish_request): its own steps begin after that.
    restarts: dict[int, bool] = {}
    starting = restarted = False
    for m, msg in decoded:
        if isinstance(msg, FleetEvent) and msg.robot is None and steps:
            if msg.kind == "merger_start":
                starting = True
            elif msg.kind == "republish_request" and starting:
                starting, restarted = False, True
        if isinstance(msg, MergerStep):
            if restarted:
                restarts[len(steps)] = resumed = msg.seq > steps[-1].seq
                restarted = False
                if not resumed:
                    fed.clear()  # an empty merger's steps may repeat the first one's, byte for byte
            if m.payload not in fed:
                fed.add(m.payload)
                steps.append(msg)
    live = next((msg for _, msg in reversed(decoded) if isinstance(msg, GlobalMap)), None)
    stepped = {step.seq for step in steps}
    compared = next((msg for _, msg in reversed(decoded) if isinstance(msg, GlobalMap) and msg.seq in stepped), None)
    return steps, live, compared, restarts


def _restart(merger: Merger, resumed: bool) -> Merger:
    """The merger a live one restarted as: a new one loaded from ``merger``'s state file (written
    and read as the live one did), or an empty one."""
    fresh = Merger(merger.keys, merger.config)
    if resumed:
        with tempfile.TemporaryDirectory() as tmp:
            state = Path(tmp) / "merger.state"
            merger.save_state(state)
            fresh.load_state(state)
    return fresh


def _follow_steps(
    merger: Merger,
    steps: list[MergerStep],
    restarts: dict[int, bool],
    decoded: list[tuple[RecordedMessage, Any]],
    compared: GlobalMap | None,
    pace: _Pacer,
    take: Callable[[list[Any]], None],
    inputs: list[str],
    progress: Callable[[int, int], None] | None,
) -> tuple[Merger, GlobalMap | None, int]:
    """Feed the merger the local map versions each recorded step took and step it as far as that
    step integrated (``take`` hears what it publishes, ``inputs`` the versions fed); then on, for a
    recording that ends before the live merger caught up; restarted where the live one was
    (``restarts``, :func:`_restart`). The merger at the end, the global map after the step that
    published ``compared`` (None if none did), and the steps taken."""
    at_live: GlobalMap | None = None
    stepped = 0
    by_version = {(msg.submap_key, msg.version): (m, msg) for m, msg in decoded if isinstance(msg, LocalMap)}
    for n, step in enumerate(steps):
        if n in restarts:
            stepped += merger.stats.steps
            merger = _restart(merger, restarts[n])
        for key, version in zip(step.maps, step.versions, strict=True):
            if key.count("/") == 1:  # a version-1 map key (no submap): an epoch's map is its submap 0
                key = f"{key}/0"
            found = by_version.get((key, version))
            if found is None:
                log.warning("local map %s version %d is not in the recording", key, version)
                continue
            pace.wait(found[0].log_time)
            merger.take(found[1])
            inputs.append(f"{key}@{version}")
        take(merger.step(limit=step.integrations))
        if compared is not None and step.seq == compared.seq:
            at_live = merger.global_map  # the step that published the live map compared with
        if progress:
            progress(n + 1, len(steps))
    while merger.has_work:  # a recording that ends before the live merger caught up
        take(merger.step())
    return merger, at_live, stepped + merger.stats.steps


def _feed_in_order(
    merger: Merger,
    maps: list[tuple[RecordedMessage, LocalMap]],
    pace: _Pacer,
    take: Callable[[list[Any]], None],
    inputs: list[str],
    progress: Callable[[int, int], None] | None,
) -> None:
    """A partial replay: each selected local map version in recording order, a step after each."""
    for n, (m, msg) in enumerate(maps):
        pace.wait(m.log_time)
        merger.take(msg)
        inputs.append(f"{msg.submap_key}@{msg.version}")
        take(merger.step())
        if progress:
            progress(n + 1, len(maps))


class _Pacer:
    """Sleeps so that recorded times pass at ``speed`` times their pace (0: no sleeping)."""

    def __init__(self, speed: float) -> None:
        self.speed = speed
        self.first: int | None = None
        self.started = time.monotonic()

    def wait(self, log_time: int) -> None:
        if self.speed <= 0:
            return
        if self.first is None:
            self.first, self.started = log_time, time.monotonic()
            return
        due = self.started + (log_time - self.first) / 1e9 / self.speed
        delay = due - time.monotonic()
        if delay > 0:
            time.sleep(delay)
