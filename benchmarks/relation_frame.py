"""Where a relations file's frame sits on the laser, measured from the log's own scans (no map).

Kümmerle et al.'s relations give the pose at t2 in the frame of the pose at t1, in the frame their
mapper used: the laser's on aces and mit-csail, a frame a few centimetres off it on fr079 (the data
README: "fr079 shows a small offset of about 4 cm"). ``fleetmap map`` writes laser poses (the
contract), so a relation rotated by theta is off by about 2 |offset| sin(theta / 2) for any map,
however right: 6 cm at 90 degrees on fr079, most of the 0.10 m budget.

The offset is measured here without any map: each relation rotated more than 30 degrees (where an
offset shows) is registered on the raw returns of its two scans (point-to-line ICP, the tracker's
``register``, started at the relation), which gives the relation in the laser's frame, L; the
offset O is the (x, y) that best turns those into the relations, O^-1 L O = R (Huber loss). It is a
property of the ground truth, not of fleetmap: the same two numbers for every map of the log.

    python benchmarks/relation_frame.py            # the three logs
"""

from __future__ import annotations

import argparse
import math
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from fleetmap.shared.config import TrackingParams
from fleetmap.shared.core.geometry import Transform2D
from fleetmap.shared.core.rangescan import RangeScan
from fleetmap.shared.core.tracking import ReferenceMap, ScanSamples, register
from fleetmap.shared.io.sources import CarmenSource
from scipy.optimize import least_squares
from scipy.spatial import cKDTree

sys.path.insert(0, str(Path(__file__).resolve().parent))
from tracking import LOGS, data_folder

MIN_ROTATION = math.radians(30.0)
SAMPLE = 150
MAX_RANGE = 20.0
NEIGHBOURS = 7


@dataclass(frozen=True)
class Frame:
    """The relations' frame on the laser, and how well it explains the registrations."""

    offset: Transform2D
    pairs: int
    median_before: float
    median_after: float


def raw_samples(scan: RangeScan) -> ScanSamples:
    """A scan's returns with normals from their neighbours (points on no clear line dropped)."""
    r = np.asarray(scan.ranges, dtype=float)
    angles = scan.angle_min + np.arange(len(r)) * scan.angle_increment
    ok = np.isfinite(r) & (r > 0) & (r < min(scan.range_max, MAX_RANGE))
    points = np.column_stack([r[ok] * np.cos(angles[ok]), r[ok] * np.sin(angles[ok])])
    _, near = cKDTree(points).query(points, k=min(NEIGHBOURS, len(points)))
    local = points[near] - points[near].mean(axis=1, keepdims=True)
    values, vectors = np.linalg.eigh(np.einsum("nki,nkj->nij", local, local))
    normals = vectors[:, :, 0]
    normals[np.einsum("ij,ij->i", normals, points) > 0] *= -1  # towards the laser
    spread = np.linalg.norm(points[near] - points[:, None, :], axis=2).max(axis=1)
    good = (values[:, 0] < 0.2 * values[:, 1]) & (spread < 0.5)
    return ScanSamples(points[good], normals[good], np.full(int(good.sum()), 0.05), None)


def measure(log: Path, relations: Path, range_max: float, seed: int = 0) -> Frame:
    """The relations' frame measured on ``log`` (see the module's docstring)."""
    scans = {round(s.scan.stamp * 1e4): s.scan for s in CarmenSource(log, range_max=range_max)}
    rel = np.loadtxt(relations, ndmin=2)
    rel = rel[np.abs(rel[:, 7]) > MIN_ROTATION]
    rel = rel[np.random.default_rng(seed).permutation(len(rel))[:SAMPLE]]
    params = TrackingParams()
    prior = np.diag([1 / 0.3**2, 1 / 0.3**2, 1 / math.radians(5) ** 2])
    laser, truth = [], []
    for t1, t2, x, y, _z, _roll, _pitch, yaw in rel:
        a, b = scans.get(round(t1 * 1e4)), scans.get(round(t2 * 1e4))
        if a is None or b is None:
            continue
        r = Transform2D(x, y, yaw)
        reference = ReferenceMap(0.02)
        reference.insert(raw_samples(a))
        fit = register(raw_samples(b), reference, r, r, prior, params)
        if fit.converged:
            laser.append(fit.pose)
            truth.append(r)

    def residuals(o: np.ndarray) -> list[float]:
        off = Transform2D(float(o[0]), float(o[1]), 0.0)
        out: list[float] = []
        for lt, rt in zip(laser, truth, strict=True):
            e = rt.inverse().compose(off.inverse().compose(lt).compose(off))
            out += [e.x, e.y]
        return out

    if len(laser) < 10:
        return Frame(Transform2D.identity(), len(laser), math.nan, math.nan)
    fit = least_squares(residuals, [0.0, 0.0], loss="huber", f_scale=0.03)
    before = np.asarray(residuals(np.zeros(2))).reshape(-1, 2)
    after = np.asarray(residuals(fit.x)).reshape(-1, 2)
    return Frame(
        Transform2D(float(fit.x[0]), float(fit.x[1]), 0.0),
        len(laser),
        float(np.median(np.hypot(*before.T))),
        float(np.median(np.hypot(*after.T))),
    )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.parse_args(argv)
    data = data_folder()
    for name, (path, range_max) in LOGS.items():
        f = measure(data / path, data / "relations" / f"{name}.relations", range_max)
        print(
            f"{name}: relations' frame at x {f.offset.x:+.3f} m, y {f.offset.y:+.3f} m on the laser "
            f"({f.pairs} pairs; median misfit {f.median_before:.3f} -> {f.median_after:.3f} m)"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
