"""Laser log readers: CARMEN logs and the ranges JSONL of the contracts, read into
:class:`~fleetmap.shared.core.rangescan.RangeScan` (a name, line or record that is wrong is
named in the error)."""

from __future__ import annotations

import gzip
import json
import logging
import math
from collections.abc import Iterator
from dataclasses import dataclass, replace
from itertools import pairwise
from pathlib import Path
from typing import IO, Any

import numpy as np
from fleetmap.shared.core.geometry import Array, Transform2D
from fleetmap.shared.core.rangescan import RangeScan
from fleetmap.shared.errors import BadInput

log = logging.getLogger(__name__)

REVERSE_NOISE = 0.001
"""An odometry step shorter than this (m) says nothing of which way the robot moved."""


def half_circle_angles(n: int) -> tuple[float, float]:
    """angle_min and angle_increment of an n-beam FLASER/RLASER line.

    FLASER lines do not say their field of view. The beams cover the half circle from -90 degrees,
    first beam to the right: an odd count (181, 361) spans -90..+90 with both ends included (1 or
    0.5 degree steps); an even count (180, 360) cannot include both ends at a laser's step, and
    takes 180/n degree steps from -90, as GMapping, which corrected ``../shared/data/corrected``,
    reads such logs: spread over both ends, the scans turn too far against the corrected poses
    (docs/decisions/006-real-lasers-extraction-and-refusal.md).
    """
    if n % 2 == 0:
        return -math.pi / 2.0, math.pi / n
    return -math.pi / 2.0, math.pi / max(n - 1, 1)


def _open_text(path: Path) -> IO[str]:
    if path.suffix == ".gz":
        return gzip.open(path, "rt", encoding="utf-8", errors="replace")
    return path.open("r", encoding="utf-8", errors="replace")


def _floats(tokens: list[str], source: str) -> Array:
    try:
        return np.array([float(t) for t in tokens], dtype=np.float64)
    except ValueError:
        raise BadInput(source, "expected numbers") from None


FLASER_TAIL = (7, 9)
"""Fields after a FLASER/RLASER line's ranges: x y theta odom_x odom_y odom_theta ipc_timestamp,
then ipc_hostname logger_timestamp in logs written since 2002 (every log of ../shared/data)."""
ROBOTLASER_TAIL = (12, 14)
"""Fields after a ROBOTLASER1 line's remissions: laser pose, robot pose, tv, rv, the two safety
distances, turn axis, timestamp, then hostname and logger timestamp."""


def parse_carmen_line(line: str, source: str, range_max: float) -> RangeScan | None:
    """One CARMEN log line as a scan, or None for lines that carry no laser data. A line that is
    cut, or whose fields do not add up to what it declares (181 ranges declared, 300 written),
    raises :class:`BadInput` naming ``source`` (the caller's ``path:line``)."""
    tokens = line.split()
    if not tokens:
        return None
    kind = tokens[0]
    try:
        if kind in ("FLASER", "RLASER"):
            n = int(tokens[1])
            ranges = _floats(tokens[2 : 2 + n], source)
            rest = tokens[2 + n :]
            _check_tail(kind, n, len(ranges), len(rest), FLASER_TAIL, source)
            pose = _floats(rest[0:6], source)
            stamp = float(rest[6])
            angle_min, inc = half_circle_angles(n)
            return RangeScan(
                stamp, angle_min, inc, range_max, ranges, (pose[0], pose[1], pose[2]), (pose[3], pose[4], pose[5])
            )
        if kind in ("ROBOTLASER1", "ROBOTLASER2"):
            start, _fov, res, max_range = _floats(tokens[2:6], source)
            n = int(tokens[8])
            ranges = _floats(tokens[9 : 9 + n], source)
            n_rem = int(tokens[9 + n])
            rest = tokens[10 + n + n_rem :]
            _check_tail(kind, n, len(ranges), len(rest), ROBOTLASER_TAIL, source)
            pose = _floats(rest[0:3], source)
            stamp = float(rest[11])
            xyz = (pose[0], pose[1], pose[2])
            return RangeScan(stamp, start, res, min(max_range, range_max), ranges, xyz, xyz)
    except (IndexError, ValueError):
        raise BadInput(source, f"malformed {kind} line") from None
    return None


def _check_tail(kind: str, declared: int, read: int, tail: int, expected: tuple[int, int], source: str) -> None:
    """Whether a laser line holds what it declares: its ranges, then ``expected`` fields."""
    if declared < 1:
        raise BadInput(source, f"{kind} line declares {declared} ranges")
    if read < declared or tail < expected[0]:
        raise BadInput(source, f"{kind} line is cut short ({declared} ranges declared)")
    if tail > expected[1]:
        raise BadInput(
            source, f"{kind} line declares {declared} ranges but holds {declared + tail - expected[1]} numbers or more"
        )


def read_carmen(path: str | Path, range_max: float = math.inf) -> Iterator[RangeScan]:
    """Scans of a CARMEN log (plain or .gz): FLASER, RLASER and ROBOTLASER1 lines, in file order.

    ``range_max`` marks the no-return reading of FLASER/RLASER lines (which do not carry it):
    readings at or beyond it are no return.
    """
    for _, scan in read_carmen_lines(path, range_max):
        yield scan


def read_carmen_lines(path: str | Path, range_max: float = math.inf) -> Iterator[tuple[int, RangeScan]]:
    """:func:`read_carmen` with each scan's line number. A laser line that is cut or does not add
    up (:func:`parse_carmen_line`) is skipped with one warning naming its line (a logger that
    crashed leaves a cut last line); a log whose laser lines are all bad is an error."""
    p = _carmen_file(path)
    good = bad = 0
    first_bad: BadInput | None = None
    with _open_text(p) as fh:
        try:
            for lineno, line in enumerate(fh, 1):
                if not line.startswith(("FLASER", "RLASER", "ROBOTLASER")):
                    continue
                try:
                    scan = parse_carmen_line(line, f"{path}:{lineno}", range_max)
                except BadInput as exc:
                    bad += 1
                    first_bad = first_bad or exc
                    _warn_once(p, lineno, f"{exc}: line skipped")
                    continue
                if scan is not None:
                    good += 1
                    yield lineno, scan
        except (OSError, EOFError) as exc:
            raise BadInput(str(path), f"cannot read (corrupt or truncated file?): {exc}") from None
    if not good and first_bad is not None:
        raise BadInput(str(path), f"none of its {bad} laser lines can be read (the first: {first_bad})")
    if not good:
        raise BadInput(str(path), "no FLASER, RLASER or ROBOTLASER1 lines: not a CARMEN laser log")


_warned: set[tuple[str, float, int]] = set()


def _warn_once(path: Path, lineno: int, message: str) -> None:
    """Warn of a bad line once, however often the log is read (a source reads it more than once)."""
    try:
        key = (str(path.resolve()), path.stat().st_mtime, lineno)
    except OSError:
        key = (str(path), 0.0, lineno)
    if key not in _warned:
        _warned.add(key)
        log.warning("%s", message)


@dataclass(frozen=True)
class OdometryReading:
    """One ODOM line of a CARMEN log: the robot's odometry pose and when it was read."""

    line: int
    stamp: float
    pose: tuple[float, float, float]
    moved: bool = True
    """Whether the wheels' motion from this reading on is known (:func:`_unanchored`: not after a
    corrected log's anchor that no wheel reading follows before the next scan)."""


def read_carmen_odometry(path: str | Path) -> list[OdometryReading]:
    """The ODOM lines of a CARMEN log, in file order (``ODOM x y theta tv rv accel ipc_timestamp
    ...``); a line that does not parse is skipped (a log may end in a cut line). Where the poses
    integrate the speed without its sign (:func:`_signed_odometry`), they are integrated again with it."""
    p = _carmen_file(path)
    out: list[OdometryReading] = []
    speeds: list[float] = []
    lasers: list[tuple[int, tuple[float, float, float]]] = []
    with _open_text(p) as fh:
        try:
            for lineno, line in enumerate(fh, 1):
                if line.startswith("FLASER "):
                    laser = _flaser_pose(line)
                    if laser is not None:
                        lasers.append((lineno, laser))
                    continue
                if not line.startswith("ODOM "):
                    continue
                tokens = line.split()
                try:
                    x, y, theta = float(tokens[1]), float(tokens[2]), float(tokens[3])
                    speed, stamp = float(tokens[4]), float(tokens[7])
                except (IndexError, ValueError):
                    continue
                out.append(OdometryReading(lineno, stamp, (x, y, theta)))
                speeds.append(speed)
        except (OSError, EOFError) as exc:
            raise BadInput(str(path), f"cannot read (corrupt or truncated file?): {exc}") from None
    return _signed_odometry(_unanchored(out, lasers, p), speeds, p)


def _flaser_pose(line: str) -> tuple[float, float, float] | None:
    """The laser pose (``x y theta`` after the ranges) of an FLASER line, or None if it does not parse."""
    tokens = line.split()
    try:
        n = int(tokens[1])
        return float(tokens[2 + n]), float(tokens[3 + n]), float(tokens[4 + n])
    except (IndexError, ValueError):
        return None


def _unanchored(
    readings: list[OdometryReading], lasers: list[tuple[int, tuple[float, float, float]]], path: Path
) -> list[OdometryReading]:
    """The readings chained again where the log's odometry starts over at every laser line's pose.

    A SLAM's corrected log (GMapping's, as in ``corrected/``) writes each laser line at its
    corrected pose and the odometry reading right after it at that same pose: the odometry is
    anchored again at every scan, and only its increments between one laser line and the next are
    the wheels' own. Read as one track, scan to scan it mixes the correction between two scans into
    the wheels' motion (csail-corrected: turns off by 10-40 degrees a scan). Where the first reading
    after every laser line lies exactly at its pose, each such jump is taken out (the reading
    continues from the one before it: the two are read at the same moment) and the wheels'
    increments are chained into one track; any other log is left as it is. A stretch with no
    wheel reading between its anchor and the next scan says nothing of how far the robot went:
    its anchor is marked not ``moved``, and whoever reads odometry there gets none (orebro-corrected:
    220 of its 237 stretches)."""
    if len(lasers) < 2 or len(readings) < 2:
        return readings
    lines = [r.line for r in readings]
    anchors: set[int] = set()
    for line, pose in lasers:
        i = int(np.searchsorted(lines, line))
        if i == len(readings):
            continue
        if not all(math.isclose(a, b, abs_tol=1e-9) for a, b in zip(readings[i].pose, pose, strict=True)):
            return readings
        anchors.add(i)
    if len(anchors) < 2:
        return readings
    _warn_once(
        path,
        0,
        f"{path}: the odometry starts over at every laser line's pose (a corrected log's); its increments"
        " between scans are chained into one track",
    )
    laser_lines = [line for line, _ in lasers]
    out: list[OdometryReading] = []
    offset = Transform2D.identity()  # the current stretch's raw frame in the chained track's
    for i in range(len(readings)):
        raw = Transform2D(*readings[i].pose)
        if i in anchors and out:
            offset = Transform2D(*out[-1].pose).compose(raw.inverse())
        chained = offset.compose(raw)
        # an anchor the next scan's line follows with no reading between: nothing moved it
        empty = False
        if i in anchors:
            after = int(np.searchsorted(laser_lines, readings[i].line))
            empty = i + 1 == len(readings) or (after < len(laser_lines) and readings[i + 1].line > laser_lines[after])
        out.append(replace(readings[i], pose=(chained.x, chained.y, chained.theta), moved=not empty))
    return out


def _signed_odometry(readings: list[OdometryReading], speeds: list[float], path: Path) -> list[OdometryReading]:
    """The readings, integrated again with the sign of their speed where the log's poses ignore it.

    Some logs' odometry adds up the wheels' speed without its sign: reversing, the robot's ``tv``
    is negative while its pose moves forward (fr079: all 406 steps taken at a negative speed). A
    tracker started from such a pose looks for the scan where the robot did not go, and along a
    corridor the walls cannot say otherwise. When most steps taken at a negative speed move
    forward, each of those steps is turned back (its translation negated, its turn kept) and the
    poses are summed again; a log whose odometry reverses as it should is left as it is."""
    steps = [Transform2D(*a.pose).inverse().compose(Transform2D(*b.pose)) for a, b in pairwise(readings)]
    moving = [i for i, step in enumerate(steps) if speeds[i] < 0 and math.hypot(step.x, step.y) > REVERSE_NOISE]
    forward = {i for i in moving if steps[i].x > 0}
    if 2 * len(forward) <= len(moving):  # also when nothing reverses
        return readings
    _warn_once(
        path,
        0,
        f"{path}: the odometry moves forward while its speed says the robot reverses ({len(forward)} of "
        f"{len(moving)} steps): its poses add up the speed without its sign; integrated again with it",
    )
    out = readings[:1]
    pose = Transform2D(*readings[0].pose)
    for i, (reading, step) in enumerate(zip(readings[1:], steps, strict=True)):
        pose = pose.compose(Transform2D(-step.x, -step.y, step.theta) if i in forward else step)
        out.append(replace(reading, pose=(pose.x, pose.y, pose.theta)))
    return out


def _carmen_file(path: str | Path) -> Path:
    p = Path(path)
    if not p.exists():
        raise BadInput(str(path), "no such file")
    if p.is_dir():
        raise BadInput(str(path), "is a directory, not a CARMEN log")
    return p


def scan_from_dict(data: Any, source: str) -> RangeScan:
    """A RangeScan from one decoded ranges-JSONL object; errors name ``source`` and the field."""
    if not isinstance(data, dict):
        raise BadInput(source, f"a range scan must be a JSON object, got {type(data).__name__}")
    values: dict[str, float] = {}
    for key in ("angle_min", "angle_increment", "range_max"):
        v = data.get(key)
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise BadInput(source, f"field '{key}' must be a finite number, got {v!r}")
        values[key] = float(v)
    if values["angle_increment"] == 0:
        raise BadInput(source, "field 'angle_increment' must not be zero")
    stamp = data.get("stamp", 0.0)
    if isinstance(stamp, bool) or not isinstance(stamp, (int, float)) or not math.isfinite(stamp):
        raise BadInput(source, f"field 'stamp' must be a finite number, got {stamp!r}")
    ranges = data.get("ranges")
    if not isinstance(ranges, list):
        raise BadInput(source, f"field 'ranges' must be a list of numbers, got {type(ranges).__name__}")
    out = np.empty(len(ranges))
    for i, r in enumerate(ranges):
        if r is None:
            out[i] = math.nan  # JSON has no NaN: null is a no-return beam
        elif isinstance(r, bool) or not isinstance(r, (int, float)):
            raise BadInput(source, f"field 'ranges'[{i}] must be a number, got {r!r}")
        else:
            out[i] = float(r)
    return RangeScan(float(stamp), values["angle_min"], values["angle_increment"], values["range_max"], out)


def read_ranges_jsonl(path: str | Path) -> Iterator[RangeScan]:
    """Scans of a ranges JSONL file (one scan per line, blank lines skipped)."""
    p = Path(path)
    if not p.exists():
        raise BadInput(str(path), "no such file")
    with _open_text(p) as fh:
        for lineno, line in enumerate(fh, 1):
            if not line.strip():
                continue
            source = f"{path}:{lineno}"
            try:
                data = json.loads(line)
            except json.JSONDecodeError as exc:
                raise BadInput(source, f"malformed JSON: {exc.msg}") from None
            yield scan_from_dict(data, source)
