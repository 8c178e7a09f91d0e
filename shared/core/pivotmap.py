"""A robot's local map by the pivot method online (paper IV-C, Algorithm 6): scans added one at a
time, each integrated with the previous placed one, its transform composed and the scan fused once.

The agent's pivot front end (:mod:`fleetmap.agents.pivot`) grows one builder per epoch; the
paper's offline pivot merge of a known sequence (:func:`fleetmap.merger.sequence.pivot`) runs
the same builder over its maps.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from fleetmap.shared.config import IntegrationParams
from fleetmap.shared.core.fusion import fuse
from fleetmap.shared.core.geometry import Array, Transform2D
from fleetmap.shared.core.integration import Integration, Window, integrate
from fleetmap.shared.core.mapgrid import moved_viewpoints, viewpoints_of, with_viewpoints
from fleetmap.shared.core.refine import refine_transform, refinement_kept
from fleetmap.shared.core.segmap import SegmentMap
from fleetmap.shared.core.simplify import SIMPLIFY_TOLERANCE, simplify
from fleetmap.shared.core.transformation_value import prepare, transformation_value
from fleetmap.shared.core.validity import VALID_MAX_AMBIGUITY
from fleetmap.shared.errors import BadInput

WITNESS_TRANSLATION = 0.30
"""Two integrations agree on a scan's pose when they put it within this (m) ..."""
WITNESS_ROTATION = 0.0524
"""... and this (rad, 3 degrees) of each other: one wrong integration cannot place a scan
(docs/decisions/008-pivot-local-maps.md); a refinement or a polish moves a pose no farther."""
LOCAL_MAP_RADIUS = 20.0
"""A scan that integrates with no previous scan is integrated with the built map within this (m) of
the last placed pose: about a laser's reach (the default ``max_range``)."""
CORNER_TURN = math.pi / 4
"""A step that turned more than this (rad, 45 degrees) took a corner: the motion prior then drives on
straight ahead in the new heading (docs/decisions/008-pivot-local-maps.md)."""
SIMPLIFY_FROM = 200
"""The built map is simplified once it holds more segments than this (and half again each time): a
bound on the cost of integrating with it."""


@dataclass(frozen=True)
class PivotStep:
    """What adding one map to a :class:`PivotMapBuilder` did."""

    pose: Transform2D | None
    """The new map's pose in the built map's frame (None: it did not integrate)."""
    integration: Integration | None
    """INTEGRATE(previous placed map, new map); None for the first map."""


class PivotMapBuilder:
    """The pivot method online (Algorithm 6): add maps one at a time, each integrated with the
    previous placed one, its transform composed with the previous pose, and fused once.

    The built map's frame is the first map's. Beyond Algorithm 6 (fleetmap):

    - **Map fallback** (``use_map``): a map that does not integrate validly with the previous one
      is integrated with the map built so far, near the last placed pose (within
      the :data:`LOCAL_MAP_RADIUS`), which has more context (the previous scan may have been blocked by a
      person, or turned away). A map that integrates with neither is not fused and gets no pose;
      the next map is integrated with the last placed one. (An agent takes failures as the sign of
      a kidnap and starts a new builder: a new epoch.)
    - **Viewpoints**: the built map carries the pose of every placed scan
      (:mod:`fleetmap.shared.core.mapgrid`), so the fallback, and any later integration of the map
      with another, judges transformations by the free space those scans saw: a scan placed one
      door further down a corridor puts walls where the map's scans saw none.
    - **Motion prior** (maps with stamps): where an integration does not validly place the new
      map where the robot's recent motion puts it (:meth:`predict`; after a corner, straight
      ahead in the new heading), because it is ambiguous (a hallway matches one door further as
      well, or turned round) or matches best elsewhere, the integration is done again within
      ``motion_prior_radius`` of that pose, and its match there counts if it is valid there and
      scores at least ``VALID_MAX_AMBIGUITY`` of the best match anywhere. Motion picks between
      near-equal matches; against a clearly better one it needs two valid matches where it says
      (below). Against the motion (farther than ``motion_prior_radius`` from the prediction), a
      map is placed only where two valid integrations agree, and not there if one of them also
      matches validly where the motion says. Where two integrations match validly, and agree,
      where the motion says, the map is placed there even if a better match lies elsewhere: a
      forward-looking laser in racks that repeat sees more of the known map one rack back than
      where the robot drove (the part of its view beyond the map matches nothing yet). Before
      the robot has moved (two placed maps), the motion bound settles an ambiguous integration
      the same way: a rival the robot cannot have reached is no rival.
    - **Motion bounds** (``max_speed``, ``max_acceleration``): a map is never placed where the
      robot cannot have driven since the last placed one, nor, while it moves on in the
      predicted heading, farther from the prediction along its direction of motion than it can
      speed up or brake.
    - **Map refinement** (``pivot_refine``): a placed map's pose is refined by least squares on
      the built map near it (scan-to-map, as SLAM front ends do), so the small errors of
      scan-to-scan integrations do not add up along a hallway; never farther than the witness
      tolerances from the pose its integrations placed it at.
    - **Simplification**: whenever the map has grown by half since, it is simplified
      (:func:`fleetmap.shared.core.simplify.simplify`, ``SIMPLIFY_TOLERANCE``), so it holds one segment
      per stretch of wall rather than one per scan that saw it.
    """

    def __init__(self, params: IntegrationParams | None = None, fuse_pairs: bool = False, use_map: bool = True) -> None:
        self.params = params or IntegrationParams()
        self.fuse_pairs = fuse_pairs
        self.use_map = use_map
        self._map = SegmentMap(np.zeros((0, 4)), ordered=False, oriented=True)
        self._viewpoints: list[Array] = []
        self._simplified_size = 0
        self.poses: list[Transform2D | None] = []
        self.integrations = 0
        self._last: SegmentMap | None = None
        self._last_pose = Transform2D.identity()
        self._before: tuple[SegmentMap, Transform2D] | None = None
        """The placed map before the last one, and its pose (a second witness)."""
        self._stamps: list[float] = []
        """Stamps of the one-before-last and last placed maps, where given (the motion prior)."""

    @property
    def map(self) -> SegmentMap:
        """The map built so far (the first map's frame), carrying the placed maps' viewpoints."""
        return with_viewpoints(self._map, self._all_viewpoints())

    def _all_viewpoints(self) -> Array:
        return np.vstack(self._viewpoints) if self._viewpoints else np.zeros((0, 5))

    def predict(self, stamp: float) -> Transform2D | None:
        """Where constant velocity puts a map taken at ``stamp``: the motion from the one-before-last
        placed map to the last, scaled to the time since the last, continued from the last. None
        until two maps with increasing stamps are placed.

        After a corner (a step turned more than :data:`CORNER_TURN`), the robot drives on straight
        ahead in its new heading, as far as that step took it in the same time (the chord across
        the corner, a little short of the way driven): continuing the
        turn would put it facing back the way it came (a robot that turned 90 degrees in one step
        does not turn another 180 in the next two), and a window there would hold no match, so
        a forward-looking laser's alias one rack back would go unchallenged. (A robot reversing
        round a corner is predicted forward: the sign of a corner step's way is no guide, since
        the robot drives it partly in the old heading and partly in the new.)"""
        if self._before is None or len(self._stamps) < 2:
            return None
        t0, t1 = self._stamps
        if not t1 > t0 or not stamp >= t1:
            return None
        ratio = (stamp - t1) / (t1 - t0)
        step = self._before[1].inverse().compose(self._last_pose)
        if abs(step.theta) > CORNER_TURN:
            return self._last_pose.compose(Transform2D(math.hypot(step.x, step.y) * ratio, 0.0, 0.0))
        return self._last_pose.compose(Transform2D(step.x * ratio, step.y * ratio, step.theta * ratio))

    def add(self, m: SegmentMap, stamp: float | None = None) -> PivotStep:
        """Integrate and fuse one map. With its ``stamp`` (seconds; a robot agent's scans), the
        robot's motion counts: an integration that puts the map farther from the last placed one
        than ``max_speed`` times the time since (plus :data:`WITNESS_TRANSLATION`), or farther along
        the way from the prediction than ``max_acceleration`` allows, does not count (the motion
        bounds), and ambiguous integrations are settled by the motion prior (see the class
        docstring)."""
        p = self.params
        motion = self._motion(stamp)
        if self._last is None:
            self._last = m
            self._stamps = [] if stamp is None else [stamp]
            self._map = SegmentMap(m.segments.copy(), ordered=False, oriented=m.oriented)
            self._viewpoints.append(viewpoints_of(m))
            self.poses.append(Transform2D.identity())
            return PivotStep(Transform2D.identity(), None)
        # Step 4: t_{1,i} = t_{1,i-1} composed with t_{i-1,i}.
        witnesses = [self._witness(self._last, self._last_pose, m, motion)]
        if p.pivot.pivot_witnesses and self._before is not None:
            witnesses.append(self._witness(self._before[0], self._before[1], m, motion))
        placed = (
            self._corroborated(witnesses, motion) if len(witnesses) > 1 else self._if_possible(witnesses[0], motion)
        )
        if placed is None and self.use_map and self._before is not None:
            witnesses.append(self._witness(self._near(self._last_pose), Transform2D.identity(), m, motion))
            placed = (
                self._corroborated(witnesses, motion)
                if p.pivot.pivot_witnesses
                else self._if_possible(witnesses[-1], motion)
            )
        if placed is None:
            self.poses.append(None)
            return PivotStep(None, witnesses[-1].integration)
        pose = placed.pose
        if self.params.pivot.pivot_refine:
            pose = self._refined_on_map(m, pose)
        self._fuse(self._last, m, pose, stamp)
        return PivotStep(pose, placed.integration)

    def add_at(self, m: SegmentMap, pose: Transform2D, stamp: float | None = None) -> None:
        """Fuse one map at a ``pose`` known from elsewhere (steps 5-6 without the integration; a
        benchmark's reference map built from ground-truth poses). The first map's pose must be the
        identity: its frame is the built map's."""
        if self._last is None:
            if max(pose.distance(Transform2D.identity())) > 1e-9:
                raise BadInput("pose", f"the first map's pose is the map's frame, so the identity, got {pose}")
            self.add(m, stamp)
            return
        self._fuse(self._last, m, pose, stamp)

    def _fuse(self, last: SegmentMap, m: SegmentMap, pose: Transform2D, stamp: float | None) -> None:
        """Algorithm 6, steps 5-6: fuse ``m`` placed at ``pose`` and make it the last placed map
        (``last``: the last placed one so far)."""
        if self.fuse_pairs:
            # Fig. 13a: fuse S_{i-1,i} (in S_{i-1}'s frame) placed by t_{1,i-1}.
            pair = fuse(last, m, self._last_pose.inverse().compose(pose), self.params)
            self._map = fuse(self._map, pair, self._last_pose, self.params)
        else:
            # Fig. 13b, steps 5-6: fuse S_i itself, placed by t_{1,i}.
            self._map = fuse(self._map, m, pose, self.params)
        self._viewpoints.append(moved_viewpoints(viewpoints_of(m), pose))
        tol = SIMPLIFY_TOLERANCE
        if tol > 0 and len(self._map) > max(SIMPLIFY_FROM, 1.5 * self._simplified_size):
            self._map = simplify(self._map, tol)
            self._simplified_size = len(self._map)
        self._before = (last, self._last_pose)
        self._last, self._last_pose = m, pose
        self._stamps = [] if stamp is None else [*self._stamps[-1:], stamp]
        self.poses.append(pose)

    def _motion(self, stamp: float | None) -> _Motion:
        """What the robot's motion says of a map taken at ``stamp`` (nothing without stamps)."""
        p = self.params
        if stamp is None or not self._stamps or not stamp > self._stamps[-1]:
            # (Time that does not advance, as in a log whose stamps lost their precision, bounds nothing.)
            return _Motion(self._last_pose, p.motion.motion_prior_rotation)
        dt = stamp - self._stamps[-1]
        max_motion = p.motion.max_speed * dt + WITNESS_TRANSLATION if p.motion.max_speed > 0 else None
        predicted = self.predict(stamp)
        slack = None
        if predicted is not None and p.motion.max_acceleration > 0:
            slack = 0.5 * p.motion.max_acceleration * dt * dt + WITNESS_TRANSLATION
        return _Motion(self._last_pose, p.motion.motion_prior_rotation, max_motion, predicted, slack)

    def _witness(self, base: SegmentMap, pose: Transform2D, m: SegmentMap, motion: _Motion) -> _Witness:
        """INTEGRATE(base, m), ``base`` placed at ``pose``; an ambiguous one settled where it can be
        by the motion prior, or, before the robot has moved, by the motion bound (see the class
        docstring)."""
        r = integrate(base, m, self.params)
        self.integrations += 1
        p = self.params
        predicted, max_motion = motion.predicted, motion.max_motion
        if predicted is not None and p.motion.motion_prior_radius > 0:
            window = Window(
                pose.inverse().compose(predicted), p.motion.motion_prior_radius, p.motion.motion_prior_rotation
            )
        elif predicted is None and max_motion is not None:
            window = Window(pose.inverse().compose(self._last_pose), max_motion, math.pi)
        else:
            return _Witness(pose.compose(r.transform), r)
        inside = window.contains(np.array([t.as_array() for t in (r.transform, *(t for t, _ in r.rivals))]))
        if r.valid and inside[0]:
            return _Witness(pose.compose(r.transform), r, at_prediction=predicted is not None)
        if not inside.any() and predicted is None:
            return _Witness(pose.compose(r.transform), r)  # nothing the robot can have reached matched
        # The window is searched even where neither the best match nor its rivals lie in it: against
        # a map, a forward-looking laser's view matches more wall one rack back than where the
        # robot drove (its view beyond the map matches nothing), so the right placement may rank
        # below the few rivals an integration keeps.
        near = integrate(base, m, p, window=window)
        self.integrations += 1
        near_pose = pose.compose(near.transform)
        if near.valid and near.value - near.violation >= VALID_MAX_AMBIGUITY * (r.value - r.violation):
            return _Witness(near_pose, near, at_prediction=predicted is not None)
        if predicted is None or near.value <= 0:
            return _Witness(pose.compose(r.transform), r)
        return _Witness(pose.compose(r.transform), r, near.valid, near_pose, near)

    def _refined_on_map(self, m: SegmentMap, pose: Transform2D) -> Transform2D:
        """``pose`` refined by least squares on the built map near it, if that raises the value or
        lowers it a little after a small move (:func:`~fleetmap.shared.core.refine.refinement_kept`),
        and never farther than the witness tolerances: a small scan at a corner slides along the
        corridor it turns into, to a pose that scores more and that no integration put it at."""
        near = self._near(pose)
        prep = prepare(near.segments, m.segments, near.oriented and m.oriented, self.params)
        before = transformation_value(prep, pose.as_array(), self.params, refuse=False)
        t = refine_transform(prep, pose, self.params, iterations=12)
        if not _close(t, pose, WITNESS_TRANSLATION, WITNESS_ROTATION):
            return pose  # not a refinement: the integrations that placed it agree within these
        after = transformation_value(prep, t.as_array(), self.params, refuse=False)
        return t if refinement_kept(pose, t, before, after, self.params) else pose

    def _corroborated(self, witnesses: list[_Witness], motion: _Motion) -> _Witness | None:
        """The first possible witness that another one agrees with (within the witness tolerances).

        Where the robot's recent motion (``predicted``) puts the map elsewhere, the agreeing witness
        must be valid too: against the motion, only two valid integrations place a map (a kidnapped
        robot's first view can match one integration well enough, and the other almost). And where
        a witness also matches validly where the motion says, geometry and motion disagree: the map
        is not placed there (in a warehouse whose racks repeat, two scans 2.4 m apart match one rack
        off with confidence, while the scan between them matches where the robot drove). Where the
        motion says, the agreeing witness may be invalid, and may agree by its best match inside
        the motion prior's window. Failing all that, :meth:`_with_motion`."""
        tt, tr = WITNESS_TRANSLATION, WITNESS_ROTATION
        window = None
        if motion.predicted is not None and self.params.motion.motion_prior_radius > 0:
            window = Window(motion.predicted, self.params.motion.motion_prior_radius, math.pi)
        for w in witnesses:
            if self._if_possible(w, motion) is None:
                continue
            against = window is not None and not window.contains(w.pose.as_array()[None])[0]
            if against and any(o.at_prediction for o in witnesses):
                continue  # the geometry matches where the motion says too: leave it unplaced
            for other in witnesses:
                if other is w:
                    continue
                if against and other.integration.valid and _close(w.pose, other.pose, tt, tr):
                    return w
                if not against and other.agrees(w.pose, tt, tr):
                    return w
        return self._with_motion(witnesses, motion)

    def _with_motion(self, witnesses: list[_Witness], motion: _Motion) -> _Witness | None:
        """Two witnesses that match validly, and agree, where the robot's motion puts the map.

        Where a better match lies elsewhere, geometry alone is ambiguous and motion decides: a
        forward-looking laser in racks that repeat sees more of the known map one rack back than
        where the robot drove, since the part of its view beyond the map matches nothing yet."""
        tt, tr = WITNESS_TRANSLATION, WITNESS_ROTATION
        at = [w for w in witnesses if w.at_prediction]
        for w in at:
            pose = w.motion_pose
            if not motion.possible(pose):
                continue
            if any(other is not w and _close(pose, other.motion_pose, tt, tr) for other in at):
                return _Witness(pose, w.motion_integration, at_prediction=True)
        return None

    def _if_possible(self, w: _Witness, motion: _Motion) -> _Witness | None:
        """``w`` if its integration is valid and the robot can have moved there."""
        return w if w.integration.valid and motion.possible(w.pose) else None

    def _near(self, pose: Transform2D) -> SegmentMap:
        """The built map within :data:`LOCAL_MAP_RADIUS` of ``pose`` (all of it if the radius is 0)."""
        radius = LOCAL_MAP_RADIUS
        seg, vp = self._map.segments, self._all_viewpoints()
        near = (np.abs(seg[:, 0:4:2] - pose.x) <= radius).any(axis=1) & (np.abs(seg[:, 1:4:2] - pose.y) <= radius).any(
            axis=1
        )
        if radius <= 0 or not near.any():
            return with_viewpoints(self._map, vp)
        vp = vp[(np.abs(vp[:, 0] - pose.x) <= radius) & (np.abs(vp[:, 1] - pose.y) <= radius)]
        return with_viewpoints(SegmentMap(seg[near], ordered=False, oriented=self._map.oriented), vp)


@dataclass(frozen=True)
class _Motion:
    """What the robot's motion says of the next map: where it can be, and where it should be."""

    last: Transform2D
    """The last placed map's pose."""
    straight_rotation: float
    """A placement within this (rad) of the predicted heading is one where the robot drove on
    straight: only there does ``along_slack`` bound it."""
    max_motion: float | None = None
    """The farthest it can be from ``last`` (``max_speed``; None: no stamps, no bound)."""
    predicted: Transform2D | None = None
    """Where constant velocity puts it (None: not two placed maps with stamps yet)."""
    along_slack: float | None = None
    """How far from ``predicted``, along the direction of motion, it can be (``max_acceleration``)."""

    def possible(self, pose: Transform2D) -> bool:
        """Whether the robot can have moved to ``pose``: within ``max_motion`` of the last pose and,
        if the robot moves and ``pose`` lies within ``straight_rotation`` of the predicted heading,
        within ``along_slack`` of the prediction along its direction of motion. A placement turned
        more than that is not bounded (a robot that turns may have slowed down to do so: the
        scenarios' robots turn corners on the spot), nor is one while the predicted step is no
        longer than ``along_slack`` (the direction of motion is not known well enough). A
        forward-looking laser in racks or a hallway that repeat aliases along the motion: the
        match one rack back would make a robot driving straight on at 2.4 m/s reverse within a
        second."""
        if self.max_motion is not None and pose.distance(self.last)[0] > self.max_motion:
            return False
        if self.predicted is None or self.along_slack is None:
            return True
        if pose.distance(self.predicted)[1] > self.straight_rotation:
            return True
        sx, sy = self.predicted.x - self.last.x, self.predicted.y - self.last.y
        length = math.hypot(sx, sy)
        if length <= self.along_slack:
            return True
        along = ((pose.x - self.last.x) * sx + (pose.y - self.last.y) * sy) / length
        return abs(along - length) <= self.along_slack


@dataclass(frozen=True)
class _Witness:
    """Where one integration puts the new map in the built map's frame."""

    pose: Transform2D
    integration: Integration
    at_prediction: bool = False
    """The integration has a valid match where the robot's motion puts the map."""
    predicted_pose: Transform2D | None = None
    """The pose of its best match where the robot's motion puts the map, where that is not
    ``pose`` (the best match lies elsewhere): valid if ``at_prediction``."""
    predicted_integration: Integration | None = None
    """That match (the integration within the motion prior's window)."""

    def agrees(self, pose: Transform2D, translation: float, rotation: float) -> bool:
        """Whether this integration puts the map within the tolerances of ``pose``, at its best
        match or at its match where the motion says."""
        return any(
            own is not None and _close(own, pose, translation, rotation) for own in (self.pose, self.predicted_pose)
        )

    @property
    def motion_pose(self) -> Transform2D:
        """Where this witness validly places the map as the robot's motion says (``at_prediction``)."""
        return self.pose if self.predicted_pose is None else self.predicted_pose

    @property
    def motion_integration(self) -> Integration:
        """The integration that places it there."""
        return self.integration if self.predicted_integration is None else self.predicted_integration


def _close(a: Transform2D, b: Transform2D, translation: float, rotation: float) -> bool:
    """Whether two poses agree within ``translation`` (m) and ``rotation`` (rad)."""
    dt, dr = a.distance(b)
    return dt <= translation and dr <= rotation
