"""One typed configuration, with the paper's parameter names and defaults.

Amigoni, Gasparini & Gini (2006) name their parameters in capitals (POINTDISTANCETOLERANCE, ...);
here they are snake_case fields with the same meaning and the paper's defaults, in metres and
radians. Every run writes the resolved configuration next to its outputs (``to_dict``/``to_toml``).

A config file is TOML with one table per section::

    [extraction]
    max_range = 8.0

    [integration]
    point_distance_tolerance = 0.010
    heuristic = "consecutive"

Command-line overrides use the field names with dashes (``--point-distance-tolerance 0.01``).
"""

from __future__ import annotations

import dataclasses
import logging
import math
import tomllib
from collections.abc import Mapping
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Any, Literal, get_args, get_type_hints

from fleetmap.shared.errors import ConfigError

Heuristic = Literal["all", "consecutive", "random", "histogram", "auto"]
HEURISTICS: tuple[str, ...] = get_args(Heuristic)
FrontEnd = Literal["tracking", "pivot"]
Odometry = Literal["auto", "on", "off"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ExtractionParams:
    """Segment extraction from a range scan (paper III-D)."""

    tau: float = 0.20
    """Clustering threshold: consecutive points closer than this are in one cluster (m)."""
    kappa: float = 0.025
    """Polyline tolerance: every point of a cluster lies within this of its segment (m)."""
    kappa_noise_factor: float = 3.0
    """fleetmap: a noisy scan's polyline tolerance is this times its noise (the median distance of
    a point from the chord of its two neighbours), where that exceeds kappa by a quarter
    (:func:`fleetmap.shared.core.extraction.kappa_for`), so a noisy laser's straight wall stays one
    segment (edmonton's laser: 2.2 cm, so kappa 6.6 cm); 0 keeps kappa always."""
    max_range: float = 20.0
    """Ranges beyond this are treated as no return (m). The paper's SICK LMS 200 was set to 8 m;
    real logs reach further, and far walls are what tells a corridor's length (the simulator's
    8 m laser is unaffected)."""
    breakpoint_angle: float = 0.1745
    """Adaptive clustering (Borges & Aldon 2004; fleetmap, 0 = the paper's fixed tau): walls seen at
    incidence down to this angle (rad, 10 degrees) stay one cluster however far apart their points are."""
    min_cluster_points: int = 3
    """Clusters with fewer points give no segment (a lone return is not a wall)."""
    line_fit: bool = True
    """Merge split pieces that fit one line and put segments on fitted lines (fleetmap, not the
    paper: see fleetmap.shared.core.extraction); false gives the paper's polylines through the points."""


@dataclass(frozen=True)
class IntegrationParams:
    """INTEGRATE (paper III, Algorithms 1-5) and what fleetmap adds to it."""

    point_distance_tolerance: float = 0.015
    """POINTDISTANCETOLERANCE: two points closer than this coincide (m)."""
    angle_difference_tolerance: float = 0.2
    """ANGLEDIFFERENCETOLERANCE: two angles closer than this are equal (rad)."""
    segment_distance_threshold: float = 5.0
    """SEGMENTDISTANCETHRESHOLD: pairs with d / POINTDISTANCETOLERANCE above this do not match."""
    segment_length_refuse: float = 0.8
    """SEGMENTLENGTHREFUSE: a transformation that makes two segments longer than this cross is
    discarded (m)."""
    refuse_range_slope: float = 0.01
    """fleetmap: for a scan's segment, the margin by which two long segments must reach past each
    other's lines to cross (SEGMENTLENGTHREFUSE; SEGMENTDISTANCETHRESHOLD *
    POINTDISTANCETOLERANCE) grows by this (m) per metre of its distance from the sensor: a far wall
    is fixed by a few sparse points (a 1 degree laser's beams lie 0.3 m apart on a wall 17 m away).
    In edmonton's log such far 1 m segments crossed the other scan's line of the same wall at
    14-31 degrees at the true alignment, refusing it: of its first 199 consecutive scan pairs,
    165 integrate right (0.3 m, 3 degrees) and valid with 0.01, 147 with 0 (the paper's rule),
    and the wrong valid ones stay 2; aces, orebro, the infinite corridor, csail and freiburg-101
    are unchanged (``benchmarks/scan_pairs.py``; measured with the old beam step too: 159 and 142,
    and 0.04 gives the same)."""
    fusion_tolerance: float = 0.015
    """FUSIONTOLERANCE: the largest distance of a fused segment from its polyline (m)."""
    segment_length_percentage: float = 20.0
    """SEGMENTLENGTHPERCENTAGE: consecutive segments shorter than this percentage of the longest
    segment form no angle (non-touching variant of the consecutive heuristic)."""
    consecutive_touching_only: bool = False
    """Consecutive heuristic, plain variant: only segments with a common extreme form an angle."""
    segment_division_factor: float = 0.5
    """SEGMENTDIVISIONFACTOR: random heuristic threshold base (Algorithm 3)."""
    random_iterations: int = 9
    """K of Algorithm 3; N_k = random_base_samples * 2**k draws in iteration k."""
    random_base_samples: int = 20
    """The 20 of N_k = 20 * 2**k (Algorithm 3)."""
    nslots: int = 18
    """Buckets of the orientation histogram (histogram heuristic)."""
    penalization_base: float = 0.95
    """Matching values of non-intersecting pairs are multiplied by base**(d / POINTDISTANCETOLERANCE)."""
    heuristic: Heuristic = "auto"
    """Which transformations to try: all, consecutive, random, histogram, or auto (the best of them)."""
    seed: int = 0
    """Seed of the random heuristic, so results are reproducible."""
    max_angles: int = 300
    """The consecutive and histogram heuristics use at most this many angles per map, those of the
    longest segments (fleetmap: large partial maps would give hundreds of millions of matches)."""
    max_search_segments: int = 150
    """Maps with more segments are searched on their longest this many (fleetmap: large partial maps);
    the best transformations are then refined and valued on the full maps."""
    max_evaluated: int = 8000
    """At most this many distinct transformations are evaluated, the most supported first."""
    min_vertex_angle: float = 0.35
    """Two segments closer to parallel than this (rad) form no angle: their vertex is ill defined."""
    refine: bool = True
    """Refine the best transformation by least squares on the matched segment pairs."""
    refine_candidates: int = 12
    """How many of the best distinct transformations are refined before the best is chosen."""
    refine_coarse_factor: float = 8.0
    """fleetmap: a scan-to-scan candidate picked for its value alone is refined first with
    POINTDISTANCETOLERANCE this many times larger (the pairs matched, and the robust loss's scale),
    then with it as given, so a candidate a few tenths of a metre or a few degrees off still finds
    its walls (a noisy laser's short segments give such candidates); 1 refines at the given
    tolerance only."""
    auto_max_all_candidates: int = 4000
    """auto also tries the all heuristic when it yields at most this many transformations."""
    free_space_margin: float = 0.10
    """A wall point closer to a scan's sensor than the wall it saw, by more than this (m), lies in
    the scan's seen free space (fleetmap's free-space check, see fleetmap.shared.core.visibility)."""
    valid_min_value: float = 1.0
    """An integration is valid only if its value is at least this (m) ..."""
    valid_min_fraction: float = 0.2
    """... and at least this fraction of the smaller map's total segment length ..."""
    valid_max_violation: float = 0.2
    """... and puts at most this fraction of its value in the other scan's seen free space ..."""
    valid_max_ambiguity: float = 0.8
    """... and no clearly different transformation scores more than this fraction of its score."""
    grid_resolution: float = 0.10
    """Large maps (fleetmap, see fleetmap.shared.core.mapgrid): cell size (m) of the grids that rank
    candidate transformations by matched wall length and wall length in seen free space."""
    map_free_space_margin: float = 0.20
    """Large maps: a wall point closer to a viewpoint than the map's wall in that bearing by more than
    this (m) lies in the seen free space (a local map's own small errors need more than a scan's)."""
    map_free_space_slope: float = 0.02
    """Large maps: the free-space margin grows by this much per metre of range (far walls move most
    under a small rotation error)."""
    map_free_space_clearance: float = 0.3
    """Large maps (fleetmap): between two partial maps, the validity rule's free-space limit on the
    best transformation (``valid_max_map_violation``) leaves out the wall that lies within this
    (m) of the other map's own walls (0: none left out). Two local maps, each built from its own
    scans, disagree on a wall's place by a few tenths of a metre, which a viewpoint seeing the
    wall at a grazing angle puts metres along its ray, beyond ``map_free_space_margin``: at the
    right alignments of real local maps (csail, edmonton, aces) 8-50 % of the value lay in each
    other's free space that way, 0-30 % outside a 0.3 m clearance. The score, and so the choice,
    the ambiguity and the refutation of rivals, counts every wall in the free space: a rack's
    posts a bay off, 8 cm from where the right alignment puts them, still refute an alias."""
    map_free_space_min_length: float = 0.0
    """Large maps (fleetmap): between two partial maps, the validity rule's free-space limit on the
    best transformation (``valid_max_map_violation``) counts only the walls of segments at least
    this long (m); 0: every wall. The score, and so the choice, the ambiguity and the refutation of
    rivals, counts every wall. Short segments are mostly clutter (chairs, desks, people) that moves
    between visits, or that one viewpoint sees and another sees past: at the right alignment of two
    local maps of a furnished lab (freiburg-079) they lay 5-11 m in each other's free space, 15-30 %
    of its value. Measured before ``map_free_space_clearance`` (which merges those maps without
    it): at 0.8 (the paper's SEGMENTLENGTHREFUSE: only segments that long refuse a
    transformation) all 13 of freiburg-079's local maps merged right, against 4
    (``benchmarks/merge.py``). Off by default: on
    the seven real logs it also let an edmonton map through turned 92 degrees, and merged the
    orebro map built 2.5 m off its first scan (a log without times) with the others (14 maps
    wrong, against 5). The simulated scenarios do not change."""
    simplify_tolerance: float = 0.05
    """Partial maps (fleetmap, see fleetmap.shared.core.simplify): segments within this (m) of one line
    are replaced by one segment per covered stretch (0: never simplify)."""
    pivot_witnesses: bool = True
    """The pivot builder places a scan only when two integrations agree on its pose (fleetmap: one
    valid integration with the last or the one-before-last placed scan, or the built map, and
    another of them within the witness tolerances), so one wrong integration cannot place it."""
    pivot_refine: bool = True
    """The pivot builder refines each placed map's pose by least squares on the built map near it
    (fleetmap: scan-to-map; the paper's pivot method composes scan-to-scan transforms only), never
    moving it farther than ``witness_translation`` and ``witness_rotation`` from where its
    integrations placed it (a small scan at a corner slides along the corridor it turns into)."""
    pivot_refine_slack: float = 0.01
    """The scan-to-map refinement (``pivot_refine``) is kept if it lowers the value by at most
    this fraction, after a move of at most ``pivot_refine_slack_translation`` and
    ``pivot_refine_slack_rotation`` (fleetmap): the transformation value, which counts overlap
    within tolerances, is flat near the true pose, and a scan turned half a degree can score a
    little more than the least-squares pose (a warehouse lane turned 2 degrees in 17 scans).
    Farther, or for more, only a higher value keeps it: in racks or a corridor it may have slid a
    bay along. (On the corrected logs, 2 % lost a fifth of the maps placed right; 1 % none.)"""
    pivot_refine_slack_translation: float = 0.10
    """The largest move (m) of a refinement kept for less value (``pivot_refine_slack``) ..."""
    pivot_refine_slack_rotation: float = 0.035
    """... and the largest turn (rad, 2 degrees)."""
    witness_translation: float = 0.30
    """Two integrations agree when they put the new scan within this (m) ..."""
    witness_rotation: float = 0.0524
    """... and this (rad, 3 degrees) of each other."""
    local_map_radius: float = 20.0
    """The pivot builder's map fallback integrates a scan with the built map within this (m) of the
    last placed pose (0: all of it)."""
    valid_min_map_value: float = 8.0
    """Two large partial maps: an integration is valid only if its value is at least this (m) ..."""
    valid_min_map_scans: int = 5
    """... and each map that carries its scans' viewpoints has at least this many (a local map of
    two or three scans in a symmetric building matches turned round as well as where it is) ..."""
    valid_max_map_violation: float = 0.1
    """... and it puts at most this fraction of its value in the maps' seen free space ..."""
    valid_max_map_ambiguity: float = 0.5
    """... and no clearly different transformation scores more than this fraction of its score
    (on the large-map path; see fleetmap.shared.core.integration for how these were measured)."""
    valid_strong_map_value: float = 16.0
    """Two partial maps (fleetmap): an integration of at least this value (m; 0: no such tier) ..."""
    valid_max_strong_map_violation: float = 0.15
    """... may put up to this fraction of its value in the maps' seen free space (instead of
    ``valid_max_map_violation``, if this is more). Two local maps whose own scan-to-scan errors
    differ place their shared walls a little apart, and their lasers see the far ones at grazing
    angles, so a right merge of large overlapping maps violates in proportion to the overlap:
    11-14 % for maps built from SLAM-corrected poses. The wrong ones that pass the other rules are
    small overlaps (values 8-13 m), which stay held to ``valid_max_map_violation``."""
    valid_refute_violation: float = 3.0
    """Two large partial maps (fleetmap): a clearly different transformation that puts at least
    this much wall (m), and more than ``valid_max_map_violation`` of its value, in the maps' seen
    free space is refuted and does not count against the best (0: never; every clearly different
    alignment, up to 8, is still judged a rival) ..."""
    valid_refute_clean: float = 0.025
    """... provided the best puts at most this fraction of its value there (the seen free space
    then tells them apart: in a warehouse lane the alignments a rack off match more wall than the
    right one, but put rack ends where a laser saw through the forklift's bay)."""
    max_speed: float = 3.0
    """Robot agents (fleetmap): the fastest a robot moves (m/s). A scan whose integrations put it
    farther from the last placed scan than this times the time between them (plus
    ``witness_translation``) is not placed: a robot cannot be there, so the match is wrong (a
    look-alike corridor) or the robot was carried off. 0: no bound. This is a physical limit, not
    a pose: the robot still knows nothing of where it is."""
    max_acceleration: float = 3.0
    """Robot agents (fleetmap): the hardest a robot speeds up or brakes (m/s^2). While it moves (its
    predicted step is longer than the bound below), a scan placed within ``motion_prior_rotation``
    of the predicted heading is not placed farther from where constant velocity puts it, along its
    direction of motion, than half this times the time squared (plus ``witness_translation``). A
    placement turned more than that is not bounded: a robot that turns may have slowed down to do
    so (the scenarios' robots turn corners on the spot). 0: no bound."""
    motion_prior_radius: float = 0.5
    """Robot agents (fleetmap): a scan whose integration is ambiguous (a hallway matches one door
    further, or turned round), or matches best elsewhere, is integrated again within this (m) of
    where the robot's own recent motion puts it (constant velocity since its last two placed scans;
    after a corner, straight ahead in the new heading) ... 0: never."""
    motion_prior_rotation: float = 0.26
    """... and this (rad, 15 degrees); the match found there is taken only if it is valid there and
    scores at least ``valid_max_ambiguity`` of the best match anywhere. A scan placed farther than
    ``motion_prior_radius`` from the prediction needs two valid integrations that agree (a
    kidnapped robot's first view can match one well enough, and the other almost), and is not
    placed there if one of them also matches validly where the motion says; where two of them
    match validly, and agree, where the motion says, it is placed there."""


@dataclass(frozen=True)
class MergeParams:
    """Merging many maps (paper IV and the map graph)."""

    cycle_translation_tolerance: float = 0.30
    """A non-tree edge that disagrees with its tree path by more than this (m) is rejected."""
    cycle_rotation_tolerance: float = 0.087
    """... or by more than this (rad, 5 degrees)."""
    max_candidates: int = 0
    """``fleetmap merge``: integrate a new map against at most this many existing maps, most
    similar first (0: all)."""
    near_candidates: int = 3
    """The merger: a placed robot's submap is registered on at most this many submaps near where the
    graph puts it, nearest first (``fleetmap.merger.service``) ..."""
    far_candidates: int = 3
    """... and integrated (pose-free) with at most this many of the other components' submaps most
    like it ..."""
    far_budget: int = 12
    """... and, while nobody has placed its robot, with at most this many of them in all (the next
    most similar in turn, when the merger has nothing else to do) ..."""
    join_support: int = 2
    """An integration joins two groups of submaps only if at least this many pairs of their
    submaps, itself included, bear it out and none contradicts it
    (:meth:`fleetmap.merger.posegraph.PoseGraph._join_holds`): one wrong integration cannot join
    two robots' maps."""
    loop_sweep_every: int = 4
    """... and every this-many-th final submap of a placed robot also with the most similar submap of
    its own component beyond its reach (a loop its drift hides from the near search; 0: never)."""
    bridge_min_value: float = 10.0
    """A valid integration of two partial maps that no cycle can check (a bridge of the graph of
    valid edges: without it, the maps on either side fall apart) joins them only if its value is
    at least this (m; fleetmap, 0: no such rule); it is rejected otherwise. The paper's right
    merges of local maps scored about 10 m, its wrong ones about 5 m, and ``valid_min_map_value``
    is 8 m. On the corrected logs' local maps built with 1-degree beam steps, one edmonton edge of
    8.3 m (rival 1.6 m, no violation) joined two groups of maps 55 m along a corridor, 5 maps
    wrong; with 10 m none is, and no right merge is lost (64 of 154 within either way). On the
    maps fused from the corrected poses it changes nothing (67 of 84 within with and without it,
    before the beam-step change; ``benchmarks/merge.py``). Only a cycle that agrees checks an
    edge: one that is a bridge once the edges the cycle check rejected are gone is held to this
    too (two weak edges joined the same two groups of edmonton maps, a 90-degree alias of 8.4 m
    and the 55 m one of 8.3 m; the check rejected the weaker, and the other put 4 maps 28-48 m
    off)."""
    polish_edges: bool = True
    """A valid integration of two maps either of which was integrated simplified (a partial map) has
    its transform fitted again by least squares on the maps as they are (fleetmap): partial maps
    are integrated simplified (``simplify_tolerance``), and the integration keeps the
    transformation of highest value, which is flat near the truth. On the local maps fused from
    edmonton's corrected poses, two edges were 0.41 and 0.28 degrees off that way, and 0.02 and
    0.00 once fitted on the unsimplified maps; chained, they put three maps 0.27-0.52 m off
    (``benchmarks/merge.py --local-maps truth``). A fit that moves the transform farther than the
    witness tolerances (``witness_translation``, ``witness_rotation``) is not a polish and is not
    kept. The edge keeps the value, violation and rivals of the integration (the fit moves it a
    few centimetres or tenths of a degree)."""
    max_submap_segments: int = 5000
    """The merger refuses a submap of more segments than this (dropped, logged and counted): one
    integration's time grows with the segments (about a millisecond per segment here, so about 5 s
    at this limit), and an agent's submaps hold tens to a few hundred."""
    max_robots: int = 256
    """The merger keeps track of at most this many robots; messages of one more are dropped, logged
    and counted (a flood of made-up robots cannot queue work without end)."""
    max_queued_pairs: int = 20000
    """Pairs of submaps waiting to be integrated, at most; a pair due beyond it is dropped, logged and
    counted (each new submap queues a few, ``near_candidates`` + ``far_candidates`` + 2)."""
    edge_information: bool = True
    """When the poses of a component are refined together, an edge weighs as firmly as its walls fix
    each direction of its transform (fleetmap; the normal matrix of its least-squares fit on the
    two maps), not by its value alone in every direction: along a corridor the walls leave the
    translation nearly free. On the maps fused from orebro's corrected poses, an edge 0.29 m off
    along a corridor pulled a map 0.23 m off, against the cycle of three edges that placed it
    right (``benchmarks/merge.py --local-maps truth``)."""


@dataclass(frozen=True)
class TrackingParams:
    """The robot agent's front end: scan-to-submap tracking (fleetmap; ``fleetmap.shared.core.tracking``
    and ``fleetmap.agents.tracker``, ``docs/decisions/001-tracking-front-end.md``)."""

    front_end: FrontEnd = "tracking"
    """tracking: predict each scan from odometry or constant velocity, register it on the active
    submap, check the fit; pivot: the paper's pivot method (IV-C, Algorithm 6), one local map per
    epoch, each scan placed by pose-free integration (reproduces the paper)."""
    odometry: Odometry = "auto"
    """auto: use the source's odometry when it has some; on: require it (an error if the source
    has none); off: constant velocity only."""
    sample_spacing: float = 0.10
    """Metres between the points sampled along a scan's segments for registration."""
    voxel_size: float = 0.05
    """Cell size (m) of a submap's registration grid (the mean point and normal of each cell)."""
    residual_sigma: float = 0.03
    """The standard deviation (m) of a matched point's distance from the submap's wall (laser
    noise and the submap's own blur): it weighs the walls against the prior."""
    max_correspondence: float = 1.0
    """Registration runs in stages, coarse to fine: its first stage matches a scan point to submap
    walls up to this far (m), each later stage to half as far, down to ``min_correspondence``; a
    stage ends when the fit stops moving or after ``iterations_per_stage``. A prediction a few tens
    of centimetres or ten degrees off finds its walls that way, nearby walls pulling first."""
    min_correspondence: float = 0.25
    """The last stage's correspondence radius (m)."""
    loss_scale: float = 0.2
    """The robust (Cauchy) loss's scale, as a share of the stage's correspondence radius."""
    iterations_per_stage: int = 8
    max_iterations: int = 30
    convergence_translation: float = 0.001
    """A Gauss-Newton step shorter than this (m) ..."""
    convergence_rotation: float = 0.001
    """... and turned less than this (rad) has converged."""
    max_normal_angle: float = 1.0472
    """A scan point matches a submap wall only if their normals are within this (rad, 60 degrees):
    the two sides of a thin wall are different walls."""
    odometry_translation_sigma: float = 0.05
    """Odometry's uncertainty per scan step: this (m) ..."""
    odometry_translation_rate: float = 0.1
    """... plus this share of the distance driven ..."""
    odometry_rotation_sigma: float = 0.087
    """... and this (rad, 5 degrees) ...; deliberately loose: the odometry of real robots is off by
    10-25 degrees on single fast turns (mit-csail), and where the walls fix the pose they decide."""
    odometry_rotation_rate: float = 0.5
    """... plus this share of the turn."""
    velocity_translation_sigma: float = 0.05
    """Constant velocity's uncertainty per scan step: this (m) plus ``max_acceleration`` times
    the step's time squared over two ..."""
    velocity_rotation_sigma: float = 0.087
    """... and this (rad) plus ``max_angular_acceleration`` times the step's time squared over two."""
    max_angular_acceleration: float = 6.0
    """The hardest a robot starts or stops turning (rad/s^2): constant velocity's rotation
    uncertainty."""
    insert_distance: float = 0.10
    """A tracked scan is inserted into the submaps when the robot has moved this far (m) ..."""
    insert_rotation: float = 0.035
    """... or turned this much (rad, 2 degrees) since the last inserted scan ..."""
    insert_interval: float = 5.0
    """... or this much time (s) has passed (a robot standing still refreshes its view)."""
    submap_length: float = 10.0
    """A submap covers this much of the robot's path (m) ..."""
    submap_scans: int = 100
    """... or this many inserted scans, whichever comes first; the next submap starts halfway, so
    consecutive submaps overlap by half."""
    typical_score_share: float = 0.5
    """A fit whose score (:attr:`fleetmap.shared.core.tracking.Registration.score`) is below this share of
    the robot's recent fits' median is not taken at once: the robot standing still, the other
    motion model and the pose-free integration are tried too, and the best taken."""
    min_matched_share: float = 0.3
    """A fit is good only if at least this share of the scan's wall length lies on the submap's
    walls (the rest is new ground) ..."""
    min_matched_length: float = 1.0
    """... and at least this much of it (m) ..."""
    max_see_through: float = 0.5
    """... and the scan's beams pass through at most this share of the submap wall they could
    have seen (:func:`fleetmap.shared.core.tracking.see_through`): a laser cannot see through walls."""
    see_through_margin: float = 0.3
    """A beam passes through a submap wall when its return lies this much (m) beyond it ..."""
    see_through_slope: float = 0.02
    """... plus the range change a heading error of this much (rad) makes on that wall, at its
    range and incidence (:func:`fleetmap.shared.core.tracking.see_through`) ..."""
    see_through_beams: float = 5.0
    """... and only walls wide enough to span this many of the laser's beams at their range count
    (a thin thing between two beams is not seen through)."""
    drift_translation: float = 0.02
    """How a submap link's uncertainty grows with the way between the two submaps' frames (a random
    walk, m per square root of the metres driven: 5 cm over 6 m): registering on a submap built by
    tracking carries the submap's own small errors, which add up along a robot's chain of links.
    The pose graph weighs links by it and lets a loop closure correct what it allows."""
    drift_rotation: float = 0.004
    """... and of its heading (rad per square root of the metres driven: 0.56 degrees over 6 m)."""
    kidnap_after: int = 5
    """After this many scans in a row that neither fit the submap nor re-acquire it by pose-free
    integration, the robot has lost its place: a new epoch (a kidnap)."""
    publish_every: int = 5
    """The active submap is published after every this many inserted scans (a finished one once,
    as final)."""


@dataclass(frozen=True)
class FleetmapConfig:
    """The whole configuration: one section per stage."""

    extraction: ExtractionParams = field(default_factory=ExtractionParams)
    integration: IntegrationParams = field(default_factory=IntegrationParams)
    merge: MergeParams = field(default_factory=MergeParams)
    tracking: TrackingParams = field(default_factory=TrackingParams)

    def to_dict(self) -> dict[str, dict[str, Any]]:
        return {f.name: dataclasses.asdict(getattr(self, f.name)) for f in fields(self)}

    def to_toml(self) -> str:
        lines: list[str] = []
        for section, values in self.to_dict().items():
            lines.append(f"[{section}]")
            for key, value in values.items():
                lines.append(f"{key} = {_toml_value(value)}")
            lines.append("")
        return "\n".join(lines)


SECTIONS: dict[str, type] = {
    "extraction": ExtractionParams,
    "integration": IntegrationParams,
    "merge": MergeParams,
    "tracking": TrackingParams,
}


def _toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return '"' + value.replace("\\", "\\\\").replace('"', '\\"') + '"'
    return repr(value)


def _coerce(section: str, name: str, kind: Any, value: Any, source: str) -> Any:
    """Check one value against its field type; the error names the file and the field."""
    where = f"{source}: [{section}] {name}"
    if kind is bool:
        if isinstance(value, bool):
            return value
        if isinstance(value, str) and value.lower() in ("true", "false", "1", "0", "yes", "no"):
            return value.lower() in ("true", "1", "yes")
        raise ConfigError(where, f"expected true or false, got {value!r}")
    if kind is int:
        if isinstance(value, bool):
            raise ConfigError(where, f"expected an integer, got {value!r}")
        try:
            number = int(value) if isinstance(value, (int, str)) else None
        except ValueError:
            number = None
        if number is None or (isinstance(value, str) and str(number) != value.strip()):
            raise ConfigError(where, f"expected an integer, got {value!r}")
        if number < 0:
            raise ConfigError(where, f"must not be negative, got {number}")
        return number
    if kind is float:
        if isinstance(value, bool):
            raise ConfigError(where, f"expected a number, got {value!r}")
        try:
            number_f = float(value)
        except (TypeError, ValueError):
            raise ConfigError(where, f"expected a number, got {value!r}") from None
        if not math.isfinite(number_f):
            raise ConfigError(where, f"must be finite, got {value!r}")
        if number_f < 0:
            raise ConfigError(where, f"must not be negative, got {number_f}")
        return number_f
    choices = get_args(kind)
    if choices:
        if value not in choices:
            raise ConfigError(where, f"expected one of {', '.join(choices)}, got {value!r}")
        return value
    raise ConfigError(where, f"unsupported type {kind!r}")  # pragma: no cover - a field we forgot


def _field_types(cls: type) -> dict[str, Any]:
    return get_type_hints(cls)


RETIRED: dict[str, frozenset[str]] = {"merge": frozenset({"carried_max_ambiguity"})}
"""Parameters the code no longer reads: a config file or a recording's config that names one still
loads (it is ignored, said at INFO)."""


def apply_overrides(config: FleetmapConfig, overrides: Mapping[str, Mapping[str, Any]], source: str) -> FleetmapConfig:
    """Return ``config`` with ``{section: {field: value}}`` applied; unknown names are errors."""
    sections: dict[str, Any] = {}
    for section, values in overrides.items():
        if section not in SECTIONS:
            raise ConfigError(source, f"unknown section [{section}] (known: {', '.join(SECTIONS)})")
        if not isinstance(values, Mapping):
            raise ConfigError(source, f"[{section}] must be a table")
        cls = SECTIONS[section]
        types = _field_types(cls)
        current = getattr(config, section)
        changes = {}
        for name, value in values.items():
            if name in RETIRED.get(section, ()):
                log.info("%s: [%s] %s is retired and ignored", source, section, name)
                continue
            if name not in types:
                raise ConfigError(f"{source}: [{section}] {name}", f"unknown parameter (known: {', '.join(types)})")
            changes[name] = _coerce(section, name, types[name], value, source)
        sections[section] = replace(current, **changes)
    return replace(config, **sections)


def load_config(path: str | Path | None = None) -> FleetmapConfig:
    """The defaults, updated from a TOML file when one is given."""
    config = FleetmapConfig()
    if path is None:
        return config
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ConfigError(str(p), "no such config file") from None
    except OSError as exc:
        raise ConfigError(str(p), f"cannot read: {exc.strerror}") from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(str(p), f"not valid TOML: {exc}") from None
    return apply_overrides(config, data, str(p))
