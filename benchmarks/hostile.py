"""Benchmark: a live fleet under attack (run on demand, not in CI).

Each attack runs against real processes on loopback: a session of the department scenario
(``fleetmap run``'s :class:`~fleetmap.runner.Session`: router, recorder, merger and three agents),
with an attacker's own zenoh session on the same router that starts its attack once the merger is
up, before the robots start, and keeps it up until they are done. Per attack it prints:

- whether the merger and the recorder were still running when the robots were done,
- the real robots placed (of 3),
- the aligned map error (mean, m) and its difference from the attack-free baseline,
- the merge latency median (s, arrival of a local map version at the recorder to the step that
  took it in),
- the peak resident memory (VmHWM) of each kind of process, against the baseline's,
- what the attack left: the recording's size, and what the merger counted (from its log).

With ``--secure`` the fleet logs in (``fleetmap secure``) and the attacker is robot r2, logged in
as itself: the attacks an authenticated robot can make.

    python benchmarks/hostile.py                          # every attack
    python benchmarks/hostile.py --attacks token,bombs
    python benchmarks/hostile.py --secure --attacks bombs,made-up-keys
    python benchmarks/hostile.py --write-results
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import re
import signal
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import msgpack
import numpy as np
from fleetmap.scenarios import load_scenario
from fleetmap.shared.config import FleetmapConfig
from fleetmap.shared.core.geometry import Transform2D
from fleetmap.shared.io.keys import FleetKeys
from fleetmap.shared.io.messages import EpochLink, LocalMap, Scan, SubmapLink
from fleetmap.shared.io.recording_reader import RecordingReader
from fleetmap.shared.io.zenoh_bus import ZenohBus
from fleetmap.shared.io.zenoh_config import ZenohOptions
from results import markdown_table, write_result

from fleetmap.report import merge_latencies
from fleetmap.runner import Session, SessionError

Attack = Callable[["HostileSession", ZenohBus, FleetKeys, threading.Event], None]
"""What an attacker does on its zenoh session (the bus), until the event is set; it may start and
stop the session's processes."""

BOMB = {"x": [[[]] * 800_000] * 20}
"""The issue's decoding bomb: 16 MB of empty msgpack arrays (1.1-1.4 GB in every subscriber)."""


def _packed(schema: str, v: int, **fields: Any) -> bytes:
    packed: bytes = msgpack.packb({"schema": schema, "v": v, **fields})
    return packed


def token(session: HostileSession, bus: ZenohBus, keys: FleetKeys, stop: threading.Event) -> None:
    """A liveliness token under alive/ that names no robot (the merger exited 2 and crash-looped)."""
    held = bus.declare_liveliness(f"{keys.prefix}/alive/BAD")
    stop.wait()
    held.close()


def bombs(session: HostileSession, bus: ZenohBus, keys: FleetKeys, stop: threading.Event) -> None:
    """Six 16 MB payloads of empty arrays on a robot's events key, three under a field no message
    has and three under one it has (``segments`` of a LocalMap)."""
    for i in range(6):
        fields = BOMB if i % 2 == 0 else {"segments": BOMB["x"]}
        bus.publish(keys.robot_events("r2"), _packed("fleetmap.LocalMap", 2, **fields))
        bus.flush()
    stop.wait()


def made_up_keys(session: HostileSession, bus: ZenohBus, keys: FleetKeys, stop: threading.Event) -> None:
    """12 x 8 MB (random: no compression helps) under keys a robot makes up under its own prefix
    (each key had the recorder's 64 MB burst)."""
    for k in range(12):
        bus.publish(f"{keys.prefix}/robots/r2/k{k}", os.urandom(8_000_000))
        bus.flush()
    stop.wait()


def fake_robots(session: HostileSession, bus: ZenohBus, keys: FleetKeys, stop: threading.Event) -> None:
    """Valid local maps of 1000 robots that hold no liveliness token, before the real ones start
    (they filled the 256-robot limit: every message of the real robots was refused)."""
    walls = np.array([[0.0, 0.0, 4.0, 0.0], [4.0, 0.0, 4.0, 3.0], [4.0, 3.0, 0.0, 3.0]])
    for i in range(1000):
        bus.publish(keys.localmap(f"f{i}"), LocalMap(f"f{i}", 0, 0, 1.0, walls + i % 7, 3, final=True).to_msgpack())
    bus.flush()
    stop.wait()


def future_stamp(session: HostileSession, bus: ZenohBus, keys: FleetKeys, stop: threading.Event) -> None:
    """One placed scan of r1 stamped 9.2e9 s (under the format's limit), once r1 is placed: r1 got
    no pose for the rest of the session."""
    stop.wait(3.0)
    scan = Scan("r1", 0, 10**6, 9.2e9, np.zeros((0, 4)), submap=0, pose=Transform2D())
    bus.publish(keys.scan("r1"), scan.to_msgpack())
    bus.flush()
    stop.wait()


def flood(session: HostileSession, bus: ZenohBus, keys: FleetKeys, stop: threading.Event) -> None:
    """A robot r9 holding its token floods its own key with 500 final epochs (each linked to the
    one before, as a real agent's kidnaps are): 2,000 such epochs queued 6,031 pairs ahead of the
    real robots' and left them unmerged a minute after they finished."""
    held = bus.declare_liveliness(keys.alive("r9"))
    walls = np.array([[0.0, 0.0, 4.0, 0.0], [4.0, 0.0, 4.0, 3.0], [4.0, 3.0, 0.0, 3.0]])
    for e in range(500):
        link = EpochLink(e - 1, "lost") if e else None
        m = LocalMap("r9", e, 0, 1.0, walls * (1 + e % 5), 3, final=True, previous_epoch_link=link)
        bus.publish(keys.localmap("r9"), m.to_msgpack())
    bus.flush()
    stop.wait()
    held.close()


LINK_COVARIANCE = (0.01, 0.0, 0.0, 0.0, 0.01, 0.0, 0.0, 0.0, 0.001)
"""A submap link's covariance as a robot's tracking might give it (m^2, rad^2)."""


def large_submaps(session: HostileSession, bus: ZenohBus, keys: FleetKeys, stop: threading.Event) -> None:
    """A robot r9 holding its token sends six final submaps of 5,000 segments each (the most the
    merger takes), strewn over 40 m by 40 m, one epoch's chain: each is integrated with the real
    robots' submaps most like it (one integration of two such maps took 12.6 s; six raised the real
    robots' merge latency median from 0.05 s to 11.3 s)."""
    held = bus.declare_liveliness(keys.alive("r9"))
    rng = np.random.default_rng(9)
    for n in range(6):
        start = rng.uniform(-20.0, 20.0, (5000, 2))
        heading, length = rng.uniform(0.0, 2 * np.pi, 5000), rng.uniform(0.2, 3.0, 5000)
        walls = np.column_stack([start, start + length[:, None] * np.column_stack([np.cos(heading), np.sin(heading)])])
        link = SubmapLink(n - 1, Transform2D(5.0, 0.0, 0.0), LINK_COVARIANCE) if n else None
        m = LocalMap("r9", 0, 0, time.time(), walls, 50, final=True, submap=n, link=link)
        bus.publish(keys.localmap("r9"), m.to_msgpack())
    bus.flush()
    stop.wait()
    held.close()


def _second_r2(session: HostileSession, kill_first: bool, stop: threading.Event) -> None:
    """Another ``fleetmap agent --robot r2`` on the same path, 3 s into the session; the first one
    SIGKILLed before (a reboot) or left running (two live r2)."""
    if stop.wait(3.0):
        return
    if kill_first:
        for child in session.children:
            if child.name == "agent-r2":
                child.signal(signal.SIGKILL)
    out = session.out_dir
    session._child(
        "agent-r2-again",
        "agent",
        "--robot",
        "r2",
        "--scenario",
        str(out / "scenario.toml"),
        "--speed",
        str(session.speed),
        "--config",
        str(out / "config.toml"),
        *session._zenoh("r2"),
    )
    stop.wait()


def reboot(session: HostileSession, bus: ZenohBus, keys: FleetKeys, stop: threading.Event) -> None:
    """r2 SIGKILLed 3 s in and started again under its id (its new r2/0/0 replaced a final submap)."""
    _second_r2(session, True, stop)


def twin(session: HostileSession, bus: ZenohBus, keys: FleetKeys, stop: threading.Event) -> None:
    """A second live r2, 3 s in (the map split into two components)."""
    _second_r2(session, False, stop)


ATTACKS: dict[str, Attack] = {
    "token": token,
    "bombs": bombs,
    "made-up-keys": made_up_keys,
    "fake-robots": fake_robots,
    "future-stamp": future_stamp,
    "reboot": reboot,
    "twin": twin,
    "flood": flood,
    "large-submaps": large_submaps,
}


class MemorySampler(threading.Thread):
    """The peak resident memory (VmHWM, MB) of each kind of the session's processes, read from /proc
    every quarter second (a process's peak is kept by the kernel: the last reading before it ends)."""

    def __init__(self, session: Session) -> None:
        super().__init__(daemon=True)
        self.session = session
        self.stop = threading.Event()
        self.peak: dict[str, float] = {}

    def run(self) -> None:
        while not self.stop.wait(0.25):
            for child in list(self.session.children):
                if child.popen is None or child.popen.poll() is not None:
                    continue
                try:
                    status = Path(f"/proc/{child.popen.pid}/status").read_text()
                except OSError:
                    continue
                found = re.search(r"VmHWM:\s+(\d+) kB", status)
                if found:
                    role = child.name.split("-", 1)[0]
                    self.peak[role] = max(self.peak.get(role, 0.0), int(found.group(1)) / 1024)


@dataclasses.dataclass
class HostileSession(Session):
    """A session whose attacker starts once the merger is up, before the robots, and stops when
    they are done; it notes whether the services were still running then."""

    attack: Attack | None = None
    alive: dict[str, bool] = dataclasses.field(default_factory=dict)
    sampler: MemorySampler | None = None

    def _play(self, scenario_file, config_file, merger_args, merger, feeds=None):  # type: ignore[no-untyped-def]
        self.sampler = MemorySampler(self)
        self.sampler.start()
        stop = threading.Event()
        attacker = None
        if self.attack is not None:
            flags = self._zenoh("r2")
            if self.secure:
                options = ZenohOptions(config_file=flags[1], fleet=self.fleet)
            else:
                options = ZenohOptions(mode="client", connect=(flags[1],), fleet=self.fleet)
            bus = ZenohBus.open(options)
            attacker = threading.Thread(target=self.attack, args=(self, bus, options.keys, stop), daemon=True)
            attacker.start()
        try:
            merger = super()._play(scenario_file, config_file, merger_args, merger, feeds)
        finally:
            self.alive = {c.name: c.running for c in self.children if c.name in ("merger", "recorder")}
            stop.set()
            if attacker is not None:
                attacker.join(30)
                bus.close()
        return merger


def run_one(name: str, attack: Attack | None, speed: float, secure: bool, out: Path) -> dict[str, Any]:
    scenario = dataclasses.replace(load_scenario("department"), events=())
    session = HostileSession(
        scenario, out, FleetmapConfig(), speed=speed, fleet="hostile", progress=False, secure=secure, attack=attack
    )
    row: dict[str, Any] = {"attack": name}
    start = time.monotonic()
    try:
        report = session.run()
        row.update(
            placed=report["robots_placed"],
            error=report["map_error_aligned_mean_m"],
            latency=report.get("merge_latency_median_s"),
            recording_mb=(out / "session.mcap").stat().st_size / 1e6,
            r1_poses=_poses_of(out / "session.mcap", FleetKeys("hostile").pose("r1")),
            real_latency=_real_latency(out / "session.mcap", {r.id for r in scenario.robots}),
        )
    except SessionError as exc:
        row["failed"] = str(exc)[:200]
    finally:
        if session.sampler is not None:
            session.sampler.stop.set()
    row["seconds"] = time.monotonic() - start
    row["alive"] = session.alive
    row["peak_mb"] = dict(session.sampler.peak) if session.sampler else {}
    merger_log = out / "logs" / "merger.log"
    row["merger_said"] = _counted(merger_log.read_text(errors="replace")) if merger_log.exists() else ""
    recorder_log = out / "logs" / "recorder.log"
    said = recorder_log.read_text(errors="replace") if recorder_log.exists() else ""
    row["throttled"] = said.count("faster than --max-key-rate")
    return row


def _real_latency(recording: Path, robots: set[str]) -> float | None:
    """The merge latency median of the scenario's own robots' local maps (s)."""
    keys = FleetKeys("hostile")
    topics = [keys.localmap(r) for r in robots] + [keys.steps]
    with RecordingReader(recording) as reader:
        latencies = merge_latencies((m.payload, m.log_time) for m in reader.messages(topics=topics, warn=False))
    return float(np.median(latencies)) if latencies else None


def _poses_of(recording: Path, key: str) -> int:
    with RecordingReader(recording) as reader:
        return sum(1 for m in reader.messages(topics=[key], warn=False))


def _counted(log: str) -> str:
    """The merger's own words on what it dropped, refused or ignored (first of each kind)."""
    said = []
    patterns = (r"ignored the liveliness token", r"dropped a malformed", r"refused [^:\n]*", r"dropped a \S+")
    for pattern in (*patterns, r"stopped at the work budget"):
        found = re.search(pattern, log)
        if found:
            said.append(found.group(0))
    return "; ".join(dict.fromkeys(said))


def _fmt(value: float | None, digits: int = 3) -> str:
    return "-" if value is None else f"{value:.{digits}f}"


def _peak(row: dict[str, Any], base: dict[str, Any], role: str) -> str:
    mb, baseline = row["peak_mb"].get(role, 0.0), base["peak_mb"].get(role, 0.0)
    return f"{mb:.0f} ({mb / baseline:.1f}x)" if baseline else f"{mb:.0f}"


def table(rows: list[dict[str, Any]]) -> str:
    base = rows[0]
    header = ["attack", "merger, recorder alive", "robots placed", "map error (m)", "vs baseline (m)"]
    header += ["latency r1-r3 (s)", "session (s)"]
    header += ["peak MB merger / recorder / agent", "recording (MB)", "recorder throttled", "r1 poses"]
    header += ["the merger said"]
    lines = []
    for row in rows:
        alive = ", ".join("yes" if row["alive"].get(s) else "NO" for s in ("merger", "recorder"))
        if "failed" in row:
            lines.append(
                [row["attack"], alive, "-", "-", "-", "-", f"{row['seconds']:.0f}", "-", "-", "-", "-", row["failed"]]
            )
            continue
        delta = None if row["error"] is None or base.get("error") is None else row["error"] - base["error"]
        peak = " / ".join(_peak(row, base, role) for role in ("merger", "recorder", "agent"))
        lines.append(
            [
                row["attack"],
                alive,
                f"{row['placed']}/3",
                _fmt(row["error"]),
                _fmt(delta, 4) if row is not base else "baseline",
                _fmt(row["real_latency"], 2),
                f"{row['seconds']:.0f}",
                peak,
                f"{row['recording_mb']:.1f}",
                str(row["throttled"]),
                str(row["r1_poses"]),
                row["merger_said"] or "-",
            ]
        )
    return markdown_table(header, lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--attacks", default=",".join(ATTACKS), help=f"comma-separated, of {', '.join(ATTACKS)}")
    parser.add_argument("--speed", type=float, default=4.0, help="scenario seconds per wall second (default 4)")
    parser.add_argument("--secure", action="store_true", help="a logged-in fleet; the attacker is robot r2")
    parser.add_argument("--write-results", action="store_true", help="write its result into benchmarks/results/")
    parser.add_argument("--out", help="keep each session's folder (logs, recording) here")
    args = parser.parse_args()
    names = [a.strip() for a in args.attacks.split(",") if a.strip()]
    unknown = [n for n in names if n not in ATTACKS]
    if unknown:
        raise SystemExit(f"--attacks: unknown {', '.join(unknown)} (known: {', '.join(ATTACKS)})")
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for name in ["baseline", *names]:
            row = run_one(name, ATTACKS.get(name), args.speed, args.secure, Path(args.out or tmp) / name)
            print(f"{name}: {row}", flush=True)
            rows.append(row)
    text = table(rows)
    print(text)
    if args.write_results:
        fleet = "secured fleet (the attacker logged in as robot r2)" if args.secure else "open fleet"
        body = (
            f"The department scenario (3 robots, speed {args.speed:g}) on loopback, an {fleet}; each attack starts "
            "once the merger is up, before the robots, and lasts until they are done. Latency: median, over the "
            "real robots' local map versions, from arrival to the merger step that took it in; session: until the "
            "merger integrated every pair (the runner's wait). Peak: VmHWM of each kind of process, and its ratio to "
            "the baseline's. Map error: aligned mean against the true walls.\n\n" + text
        )
        section = "hostile-secure" if args.secure else "hostile"
        title = "A fleet under attack" + (", secured" if args.secure else "") + " (`benchmarks/hostile.py`)"
        write_result(section, title, body, config=FleetmapConfig())


if __name__ == "__main__":
    main()
