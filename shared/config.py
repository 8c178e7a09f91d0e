"""One typed configuration, with the paper's parameter names and defaults.

Amigoni, Gasparini & Gini (2006) name their parameters in capitals (POINTDISTANCETOLERANCE, ...);
here they are snake_case fields with the same meaning and the paper's defaults, in metres and
radians. Every run writes the resolved configuration next to its outputs (``to_dict``/``to_toml``).

One section per stage, in data-flow order (:data:`SECTIONS`); each field is tagged ``paper`` (the
paper's parameter, with its default) or ``fleetmap`` (added here; the decision records in
``docs/decisions/`` say what each was measured on), and ``basic`` marks the few a user may touch
(``fleetmap/examples/basic.toml``). A config file is TOML with one table per section::

    [extraction]
    max_range = 8.0

    [integration]
    point_distance_tolerance = 0.010

    [integration.validity]
    valid_min_map_value = 10.0

Command-line overrides use the field names with dashes (``--point-distance-tolerance 0.01``). Reading
a file or overrides, each value checked: :mod:`fleetmap.shared.config_files`.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Mapping
from dataclasses import dataclass, field, fields, replace
from typing import Any, Literal, TypeVar, get_args

from fleetmap.shared.errors import ConfigError

Heuristic = Literal["all", "consecutive", "random", "histogram", "auto"]
HEURISTICS: tuple[str, ...] = get_args(Heuristic)
Aligner = Literal["paper", "ransac"]
FrontEnd = Literal["tracking", "pivot"]
Odometry = Literal["auto", "on", "off"]
WallFusion = Literal["unweighted", "weighted"]

log = logging.getLogger(__name__)

T = TypeVar("T")


def paper(default: Any, *, basic: bool = False) -> Any:
    """A field with the paper's meaning and default (Amigoni, Gasparini & Gini 2006)."""
    return field(default=default, metadata={"origin": "paper", "basic": basic})


def ours(default: Any, *, basic: bool = False) -> Any:
    """A field fleetmap adds to the paper; the decision records say what each was measured on."""
    return field(default=default, metadata={"origin": "fleetmap", "basic": basic})


def section(cls: type) -> Any:
    """A stage's parameters nested in another's (a ``[parent.name]`` TOML table)."""
    return field(default_factory=cls)


@dataclass(frozen=True)
class ExtractionParams:
    """Segment extraction from a range scan (paper III-D)."""

    tau: float = paper(0.20)
    """Clustering threshold: consecutive points closer than this are in one cluster (m)."""
    kappa: float = paper(0.025)
    """Polyline tolerance: every point of a cluster lies within this of its segment (m)."""
    kappa_noise_factor: float = ours(3.0)
    """A noisy scan's polyline tolerance is this times its noise, where that exceeds ``kappa`` by
    ``noisy_kappa_share`` (0: always ``kappa``; docs/decisions/005-parameters-beyond-the-paper.md)."""
    noisy_kappa_share: float = ours(1.25)
    """A scan's noise sets its polyline tolerance only where that is this many times ``kappa``."""
    noise_span: float = ours(0.3)
    """Neighbouring beams whose outer two points lie farther apart than this (m) do not measure noise."""
    max_range: float = ours(20.0, basic=True)
    """Ranges beyond this are no return (m); far walls tell a corridor's length (the paper's laser: 8 m)."""
    breakpoint_angle: float = ours(0.1745)
    """Adaptive clustering (Borges & Aldon 2004): walls seen at incidence down to this angle (rad)
    stay one cluster however far apart their points are; 0 keeps the paper's fixed ``tau``."""
    min_cluster_points: int = ours(3)
    """Clusters with fewer points give no segment (a lone return is not a wall)."""
    line_fit: bool = ours(True)
    """Merge split pieces that fit one line and put segments on fitted lines; false gives the
    paper's polylines through the points (:mod:`fleetmap.shared.core.extraction`)."""


@dataclass(frozen=True)
class ValidityParams:
    """Whether an integration's best transformation is trusted (:mod:`fleetmap.shared.core.validity`;
    docs/decisions/005-parameters-beyond-the-paper.md)."""

    valid_min_value: float = paper(1.0)
    """An integration is valid only if its value is at least this (m) (the paper's threshold, V-B) ..."""
    valid_min_fraction: float = ours(0.2)
    """... and at least this fraction of the smaller map's total segment length ..."""
    valid_max_violation: float = ours(0.2)
    """... and puts at most this fraction of its value in the other scan's seen free space ..."""
    valid_max_ambiguity: float = ours(0.8)
    """... and no clearly different transformation scores more than this fraction of its score."""
    ambiguity_translation: float = ours(0.5)
    """A transformation is clearly different from the best when it moves the overlap more than this
    (m) from where the best puts it ..."""
    ambiguity_rotation: float = ours(0.17)
    """... or turns more than this (rad, 10 degrees) from it."""
    free_space_margin: float = ours(0.10)
    """A wall point closer to a scan's sensor than the wall it saw, by more than this (m), lies in the
    scan's seen free space (:mod:`fleetmap.shared.core.visibility`)."""
    map_free_space_margin: float = ours(0.20)
    """Large maps: a wall point this much (m) closer to a viewpoint than the map's wall in that
    bearing lies in the seen free space ..."""
    map_free_space_slope: float = ours(0.02)
    """... plus this much per metre of range (far walls move most under a small rotation error)."""
    map_free_space_clearance: float = ours(0.3)
    """Two partial maps: the free-space limit on the best leaves out wall within this (m) of the other
    map's own walls (two maps place one wall a little apart); 0: none left out."""
    map_free_space_min_length: float = ours(0.0)
    """Two partial maps: the free-space limit on the best counts only segments at least this long (m);
    0: every wall."""
    valid_min_map_value: float = ours(8.0)
    """Two partial maps: an integration is valid only if its value is at least this (m) ..."""
    valid_min_map_scans: int = ours(5)
    """... and each map that carries its scans' viewpoints has at least this many ..."""
    valid_max_map_violation: float = ours(0.1)
    """... and it puts at most this fraction of its value in the maps' seen free space ..."""
    valid_max_map_ambiguity: float = ours(0.5)
    """... and no clearly different transformation scores more than this fraction of its score."""
    valid_strong_map_value: float = ours(16.0)
    """Two partial maps: an integration of at least this value (m; 0: no such tier) ..."""
    valid_max_strong_map_violation: float = ours(0.15)
    """... may put up to this fraction of its value in the maps' seen free space."""
    valid_refute_violation: float = ours(3.0)
    """Two partial maps: a rival putting at least this much wall (m), and more than
    ``valid_max_map_violation`` of its value, in the seen free space is refuted (0: never) ..."""
    valid_refute_clean: float = ours(0.025)
    """... provided the best puts at most this fraction of its value there."""


@dataclass(frozen=True)
class MotionParams:
    """What a robot can physically do: bounds on where a scan can be placed (fleetmap)."""

    max_speed: float = ours(3.0, basic=True)
    """The fastest a robot moves (m/s): a scan placed farther than this allows is not placed there."""
    max_acceleration: float = ours(3.0, basic=True)
    """The hardest a robot speeds up or brakes (m/s^2): bounds a placement along its motion, and
    constant velocity's uncertainty; 0: no bound."""
    motion_prior_radius: float = ours(0.5)
    """The pivot builder: an ambiguous or far integration is tried again within this (m) of where the
    robot's recent motion puts it (0: never) ..."""
    motion_prior_rotation: float = ours(0.26)
    """... and this (rad, 15 degrees) of it."""


@dataclass(frozen=True)
class PivotParams:
    """The pivot method's local-map builder (paper IV-C, Algorithm 6;
    :class:`fleetmap.shared.core.pivotmap.PivotMapBuilder`), and what fleetmap adds to it."""

    pivot_witnesses: bool = ours(True)
    """A scan is placed only when two integrations agree on its pose (one wrong one cannot place it)."""
    witness_translation: float = ours(0.30)
    """Two integrations agree when they put the new scan within this (m) ..."""
    witness_rotation: float = ours(0.0524)
    """... and this (rad, 3 degrees) of each other."""
    pivot_refine: bool = ours(True)
    """A placed scan's pose is refined by least squares on the built map near it (scan-to-map)."""
    pivot_refine_slack: float = ours(0.01)
    """That refinement is kept if it lowers the value by at most this fraction, after a small move ..."""
    pivot_refine_slack_translation: float = ours(0.10)
    """... of at most this (m) ..."""
    pivot_refine_slack_rotation: float = ours(0.035)
    """... and this (rad, 2 degrees)."""
    local_map_radius: float = ours(20.0)
    """A scan that integrates with no previous scan is integrated with the built map within this (m)
    of the last placed pose (0: all of it)."""
    corner_turn: float = ours(math.pi / 4)
    """A step that turned more than this (rad, 45 degrees) took a corner: the motion prior then
    drives on straight ahead in the new heading."""
    simplify_from: int = ours(200)
    """The built map is simplified once it holds more segments than this (and half again each time)."""


@dataclass(frozen=True)
class RansacParams:
    """The RANSAC aligner over landmark correspondences (Ballesta et al. 2009, Section 3.1;
    :mod:`fleetmap.shared.core.ransac`; docs/decisions/012-the-other-papers.md)."""

    ransac_support_distance: float = ours(0.2)
    """A correspondence supports a transformation that maps it within this (m) (the paper's th2)."""
    ransac_min_supports: int = ours(3)
    """A transformation with fewer supports aligns nothing (the paper's min, 20 visual landmarks)."""
    ransac_iterations: int = ours(2000)
    """Pairs of correspondences tried (the paper's M, 70): every pair while there are at most this many."""


@dataclass(frozen=True)
class IntegrationParams:
    """INTEGRATE (paper III, Algorithms 1-5), its validity, and the pivot builder that uses it."""

    point_distance_tolerance: float = paper(0.015)
    """POINTDISTANCETOLERANCE: two points closer than this coincide (m)."""
    angle_difference_tolerance: float = paper(0.2)
    """ANGLEDIFFERENCETOLERANCE: two angles closer than this are equal (rad)."""
    segment_distance_threshold: float = paper(5.0)
    """SEGMENTDISTANCETHRESHOLD: pairs with d / POINTDISTANCETOLERANCE above this do not match."""
    segment_length_refuse: float = paper(0.8)
    """SEGMENTLENGTHREFUSE: a transformation that makes two segments longer than this cross is
    discarded (m)."""
    refuse_range_slope: float = ours(0.01)
    """The margin by which two long segments must cross to refuse grows by this (m) per metre of a
    scan segment's range (a far wall is fixed by a few sparse points)."""
    fusion_tolerance: float = paper(0.015)
    """FUSIONTOLERANCE: the largest distance of a fused segment from its polyline (m)."""
    segment_length_percentage: float = paper(20.0)
    """SEGMENTLENGTHPERCENTAGE: consecutive segments shorter than this percentage of the longest
    segment form no angle (non-touching variant of the consecutive heuristic)."""
    consecutive_touching_only: bool = paper(False)
    """Consecutive heuristic, plain variant: only segments with a common extreme form an angle."""
    segment_division_factor: float = paper(0.5)
    """SEGMENTDIVISIONFACTOR: random heuristic threshold base (Algorithm 3)."""
    random_iterations: int = paper(9)
    """K of Algorithm 3; N_k = random_base_samples * 2**k draws in iteration k."""
    random_base_samples: int = paper(20)
    """The 20 of N_k = 20 * 2**k (Algorithm 3)."""
    nslots: int = paper(18)
    """Buckets of the orientation histogram (histogram heuristic)."""
    penalization_base: float = paper(0.95)
    """Matching values of non-intersecting pairs are multiplied by base**(d / POINTDISTANCETOLERANCE)."""
    heuristic: Heuristic = ours("auto")
    """Which transformations to try: all, consecutive, random, histogram (the paper's), or auto (the
    best of them)."""
    seed: int = ours(0)
    """Seed of the random heuristic, so results are reproducible."""
    max_angles: int = ours(300)
    """The consecutive and histogram heuristics use at most this many angles per map, those of the
    longest segments (large partial maps would give hundreds of millions of matches)."""
    max_search_segments: int = ours(150)
    """Maps with more segments are searched on their longest this many; the best transformations
    are then refined and valued on the full maps."""
    max_evaluated: int = ours(8000)
    """At most this many distinct transformations are evaluated, the most supported first."""
    pair_angle_limit: float = ours(0.5)
    """Segment pairs further from parallel than this (rad) are not evaluated: their matching value is
    at most 2D cot(angle), under 0.15 m at the default D."""
    min_vertex_angle: float = ours(0.35)
    """Two segments closer to parallel than this (rad) form no angle: their vertex is ill defined."""
    distinct_translation: float = ours(0.10)
    """Candidates within this (m) ..."""
    distinct_rotation: float = ours(0.035)
    """... and this (rad, 2 degrees) of a better one are the same transformation."""
    shortlist: int = ours(64)
    """Candidates (best values first) whose free-space consistency is measured before the choice."""
    also_by_value: int = ours(4)
    """Between scans, this many of the best-valued candidates are refined too, beside the best-scored."""
    refine: bool = ours(True)
    """Refine the best transformation by least squares on the matched segment pairs."""
    refine_candidates: int = ours(12)
    """How many of the best distinct transformations are refined before the best is chosen."""
    refine_first_steps: int = ours(3)
    """Each pick is refined this many steps first ..."""
    refine_keep: float = ours(0.6)
    """... and refined further only if it scores at least this fraction of the best so far."""
    refine_coarse_factor: float = ours(8.0)
    """A scan-to-scan candidate picked for its value alone is refined first with
    POINTDISTANCETOLERANCE this many times larger, then as given (1: as given only)."""
    rivals: int = ours(8)
    """An integration keeps this many of its best-scoring clearly different transformations."""
    auto_max_all_candidates: int = ours(4000)
    """auto also tries the all heuristic when it yields at most this many transformations."""
    near_prior_translation: float = ours(1.0)
    """How far (m) registration near a prediction lets the prediction pull (loosely: the walls decide) ..."""
    near_prior_rotation: float = ours(0.35)
    """... and how far it turns (rad, 20 degrees)."""
    grid_resolution: float = ours(0.10)
    """Large maps: cell size (m) of the grids that rank candidate transformations by matched wall
    length and wall in seen free space (:mod:`fleetmap.shared.core.mapgrid`)."""
    simplify_tolerance: float = ours(0.05)
    """Partial maps: segments within this (m) of one line become one segment per covered stretch
    (0: never simplify; :mod:`fleetmap.shared.core.simplify`)."""
    aligner: Aligner = ours("paper", basic=True)
    """paper: the paper's integration (Algorithms 1-4); ransac: RANSAC over corner and wall-end
    landmarks matched by their descriptors (Ballesta et al. 2009), valued and judged alike."""
    validity: ValidityParams = section(ValidityParams)
    ransac: RansacParams = section(RansacParams)
    motion: MotionParams = section(MotionParams)
    pivot: PivotParams = section(PivotParams)


@dataclass(frozen=True)
class MergeParams:
    """Merging many maps: the map graph and the fleet pose graph (paper IV; docs/decisions/002-pose-graph.md)."""

    cycle_translation_tolerance: float = ours(0.30)
    """A non-tree edge that disagrees with its tree path by more than this (m) is rejected ..."""
    cycle_rotation_tolerance: float = ours(0.087)
    """... or by more than this (rad, 5 degrees)."""
    max_candidates: int = ours(0)
    """``fleetmap merge``: integrate a new map against at most this many existing maps, most similar
    first (0: all)."""
    near_candidates: int = ours(3)
    """A placed robot's submap is registered on at most this many submaps near where the graph puts
    it, nearest first ..."""
    far_candidates: int = ours(3)
    """... and integrated (pose-free) with at most this many of the other components' submaps most
    like it ..."""
    far_budget: int = ours(12)
    """... and, while nobody has placed its robot, with at most this many of them in all."""
    loop_sweep_every: int = ours(4)
    """Every this-many-th final submap of a placed robot also tries the most similar submap of its
    own component beyond its reach (a loop its drift hides; 0: never)."""
    search_growth: int = ours(2)
    """An unplaced robot's active submap is searched again once its version is this many times the
    version last searched (a submap of v versions costs about log(v) searches)."""
    descriptor_step: float = ours(0.5)
    """The cheap descriptor that ranks far candidates (a pairwise geometric histogram of the walls,
    fleetmap.shared.core.descriptor) bins how far two walls lie apart in steps of this (m) ...
    """
    descriptor_reach: float = ours(12.0)
    """... up to this (m; farther in the last bin): about a submap's extent."""
    join_support: int = ours(2)
    """An integration joins two groups of submaps only if at least this many pairs of their submaps,
    itself included, bear it out and none contradicts it."""
    join_hypotheses: int = ours(3)
    """An ambiguous integration proposes to a cycle its alignment and its next best rivals, this many
    in all (it joins no two groups)."""
    polish_edges: bool = ours(True)
    """An integration of a partial map integrated simplified is fitted again by least squares on the
    maps as they are (within the witness tolerances)."""
    polish_iterations: int = ours(30)
    """That fit's Gauss-Newton steps, at most."""
    edge_information: bool = ours(True)
    """An edge weighs as firmly as its walls fix each direction of its transform (the normal matrix
    of its least-squares fit), not by its value alone in every direction."""
    edge_sigma_translation: float = ours(0.05)
    """How far (m) a wall of one map may lie from the same wall of another when their poses are
    refined together (the scale of the least-squares residuals) ..."""
    edge_sigma_rotation: float = ours(0.01)
    """... and an integration weighed by its value alone: its rotation's standard deviation at unit
    weight (rad)."""
    isotropic_share: float = ours(0.01)
    """The share of the value-based weight an integration with known information keeps (no direction
    is entirely free)."""
    robust_scale: float = ours(2.0)
    """The Cauchy loss of an integration in the refinement, in standard deviations of its information."""
    max_rejection_rounds: int = ours(5)
    """The refined poses are solved again, without the integrations they disagree with, at most this
    many times."""
    scan_constraints: bool = ours(True)
    """Once the submaps are merged, key scans are registered on the submaps they revisit and every
    placed scan's pose is refined with them (a scan is rigid; a submap bends a little)."""
    scan_key_spacing: float = ours(1.0)
    """A submap's next key scan is this far (m) along the robot's path from its last ..."""
    scan_key_rotation: float = ours(0.35)
    """... or turned this much from it (rad, 20 degrees)."""
    scan_search_radius: float = ours(2.0)
    """A key scan is registered on every submap of its component with a key scan this near (m) ..."""
    scan_prior_translation: float = ours(0.3)
    """... from where the merged submaps put it, as uncertain as this (m) ..."""
    scan_prior_rotation: float = ours(0.087)
    """... and this (rad, 5 degrees), which is also the most the fit may turn it ..."""
    scan_max_correction: float = ours(0.5)
    """... and the most (m) it may move it ..."""
    scan_min_matched_share: float = ours(0.5)
    """... and the fit must match at least this share of the scan's walls."""
    wall_fusion: WallFusion = ours("unweighted")
    """How the copies of a wall that several submaps see make the global map's wall: unweighted, by
    their length (the paper's Algorithm 5); weighted, each also by its submap's pose covariance in the
    solved graph and its segment fit (Ballesta et al. 2009, Section 4; docs/decisions/012-the-other-papers.md)."""
    start_pose_sigma_translation: float = ours(1.0)
    """A robot's known start pose (``--start-poses``; Dugarjav & Lee 2015, Section III) is off by
    this (m, each axis, one standard deviation) ..."""
    start_pose_sigma_rotation: float = ours(0.087)
    """... and this (rad, 5 degrees). Loose on purpose: the prior only holds the robots in one frame
    until their maps meet, and there their integrations correct it
    (docs/decisions/012-the-other-papers.md)."""
    max_submap_segments: int = ours(5000)
    """The merger refuses a submap of more segments than this (dropped, logged and counted)."""
    max_integration_work: int = ours(80_000_000)
    """One integration of two submaps stops past this many units of work (grid lookups and segment
    pairs compared: fleetmap.shared.core.work) and is not valid (logged and counted; 0: no limit):
    its cost is bounded whatever the submaps hold, and a replay stops where the live merger
    stopped. The real logs' submaps need at most 50 M (docs/decisions/013-input-that-looks-legitimate.md).
    ``fleetmap map`` and ``fleetmap merge`` set none unless asked: a user's own data is no attacker's."""
    max_robots: int = ours(256, basic=True)
    """The merger keeps track of at most this many robots; messages of more are dropped and counted."""
    max_queued_pairs: int = ours(20000)
    """Pairs of submaps waiting to be integrated, at most; more are dropped, logged and counted."""


@dataclass(frozen=True)
class TrackingParams:
    """The robot agent's front end: scan-to-submap tracking (:mod:`fleetmap.shared.core.tracking`,
    :mod:`fleetmap.agents.tracker`; docs/decisions/001-tracking-front-end.md)."""

    front_end: FrontEnd = ours("tracking", basic=True)
    """tracking: predict, register on the active submap, check; pivot: the paper's pivot method
    (IV-C, Algorithm 6), one local map per epoch, each scan placed by pose-free integration."""
    odometry: Odometry = ours("auto", basic=True)
    """auto: use the source's odometry when it has some; on: require it; off: constant velocity only."""
    sample_spacing: float = ours(0.10)
    """Metres between the points sampled along a scan's segments for registration."""
    voxel_size: float = ours(0.05)
    """Cell size (m) of a submap's registration grid (the mean point and normal of each cell)."""
    residual_sigma: float = ours(0.03)
    """Standard deviation (m) of a matched point's distance from the submap's wall: weighs the walls
    against the prior."""
    max_correspondence: float = ours(1.0)
    """Registration's first stage matches a scan point to submap walls up to this far (m), each
    later stage half as far ..."""
    min_correspondence: float = ours(0.25)
    """... down to this (m)."""
    loss_scale: float = ours(0.2)
    """The robust (Cauchy) loss's scale, as a share of the stage's correspondence radius."""
    iterations_per_stage: int = ours(8)
    """Gauss-Newton steps per registration stage, at most ..."""
    max_iterations: int = ours(30)
    """... and in all."""
    convergence_translation: float = ours(0.001)
    """A Gauss-Newton step shorter than this (m) ..."""
    convergence_rotation: float = ours(0.001)
    """... and turned less than this (rad) has converged."""
    max_normal_angle: float = ours(1.0472)
    """A scan point matches a submap wall only if their normals are within this (rad, 60 degrees)."""
    odometry_translation_sigma: float = ours(0.05)
    """Odometry's uncertainty per scan step: this (m) ..."""
    odometry_translation_rate: float = ours(0.1)
    """... plus this share of the distance driven ..."""
    odometry_rotation_sigma: float = ours(0.087)
    """... and this (rad, 5 degrees; real robots' odometry is off by 10-25 degrees on fast turns) ..."""
    odometry_rotation_rate: float = ours(0.5)
    """... plus this share of the turn."""
    velocity_translation_sigma: float = ours(0.05)
    """Constant velocity's uncertainty per scan step: this (m) plus ``max_acceleration`` dt^2 / 2 ..."""
    velocity_rotation_sigma: float = ours(0.087)
    """... and this (rad) plus ``max_angular_acceleration`` dt^2 / 2."""
    max_angular_acceleration: float = ours(6.0)
    """The hardest a robot starts or stops turning (rad/s^2)."""
    insert_distance: float = ours(0.10)
    """A tracked scan is inserted into the submaps when the robot has moved this far (m) ..."""
    insert_rotation: float = ours(0.035)
    """... or turned this much (rad, 2 degrees) since the last inserted scan ..."""
    insert_interval: float = ours(5.0)
    """... or this much time (s) has passed (a robot standing still refreshes its view)."""
    submap_length: float = ours(10.0, basic=True)
    """A submap covers this much of the robot's path (m) ..."""
    submap_scans: int = ours(100)
    """... or this many inserted scans; the next starts halfway, so consecutive submaps overlap by half."""
    typical_score_share: float = ours(0.5)
    """A fit scoring below this share of the robot's recent fits' median is checked against the
    other motion models and pose-free integration, and the best taken."""
    recent_fits: int = ours(20)
    """The recent fits that median is taken over."""
    min_matched_share: float = ours(0.3)
    """A fit is good only if at least this share of the scan's wall length lies on the submap's walls ..."""
    min_matched_length: float = ours(1.0)
    """... and at least this much of it (m) ..."""
    max_see_through: float = ours(0.5)
    """... and the scan's beams pass through at most this share of the submap wall they could have seen."""
    see_through_margin: float = ours(0.3)
    """A beam passes through a submap wall when its return lies this much (m) beyond it ..."""
    see_through_slope: float = ours(0.02)
    """... plus the range change a heading error of this much (rad) makes on that wall ..."""
    see_through_beams: float = ours(5.0)
    """... and only walls spanning this many beams at their range count."""
    drift_translation: float = ours(0.02)
    """A submap link's uncertainty grows with the way between the two frames: m per square root of
    the metres driven ..."""
    drift_rotation: float = ours(0.004)
    """... and rad per square root of the metres driven."""
    link_min_sigma_translation: float = ours(0.01)
    """A submap link's standard deviation is at least this (m) ..."""
    link_min_sigma_rotation: float = ours(0.005)
    """... and this (rad)."""
    kidnap_after: int = ours(5)
    """After this many scans in a row that neither fit nor re-acquire the submap, the robot has lost
    its place: a new epoch."""
    publish_every: int = ours(5)
    """The active submap is published after every this many inserted scans (a finished one once)."""


@dataclass(frozen=True)
class FleetmapConfig:
    """The whole configuration: one section per stage."""

    extraction: ExtractionParams = section(ExtractionParams)
    integration: IntegrationParams = section(IntegrationParams)
    tracking: TrackingParams = section(TrackingParams)
    merge: MergeParams = section(MergeParams)

    def to_dict(self) -> dict[str, Any]:
        """Nested: ``{"integration": {..., "validity": {...}}, ...}``."""
        return dataclasses.asdict(self)

    def flat(self) -> dict[str, Any]:
        """Every parameter as ``{"section.name": value}`` (``integration.validity.valid_min_value``)."""
        return {f"{path}.{f.name}": getattr(_section_of(self, path), f.name) for path, f in parameters()}

    def to_toml(self) -> str:
        lines: list[str] = []
        for path in SECTIONS:
            lines.append(f"[{path}]")
            obj = _section_of(self, path)
            lines += [f"{f.name} = {_toml_value(getattr(obj, f.name))}" for f in _leaves(type(obj))]
            lines.append("")
        return "\n".join(lines)


SECTIONS: dict[str, type] = {
    "extraction": ExtractionParams,
    "integration": IntegrationParams,
    "integration.validity": ValidityParams,
    "integration.ransac": RansacParams,
    "integration.motion": MotionParams,
    "integration.pivot": PivotParams,
    "tracking": TrackingParams,
    "merge": MergeParams,
}
"""Every table of a config file, by its dotted path: the stages in data-flow order."""


def _leaves(cls: type) -> list[dataclasses.Field[Any]]:
    """A section's own parameters (not its nested sections)."""
    return [f for f in fields(cls) if "origin" in f.metadata]


def parameters() -> list[tuple[str, dataclasses.Field[Any]]]:
    """Every parameter: (its section's dotted path, its field)."""
    return [(path, f) for path, cls in SECTIONS.items() for f in _leaves(cls)]


def _section_of(config: Any, path: str) -> Any:
    for part in path.split("."):
        config = getattr(config, part)
    return config


def _with_section(config: Any, path: str, changes: Mapping[str, Any]) -> Any:
    head, _, rest = path.partition(".")
    inner = getattr(config, head)
    return replace(config, **{head: _with_section(inner, rest, changes) if rest else replace(inner, **changes)})


def tuned(params: T, **changes: Any) -> T:
    """``params`` (a section, or the whole config) with parameters changed by name wherever they sit
    among its nested sections: ``tuned(IntegrationParams(), max_speed=1.0)``."""
    unknown = set(changes) - _names(params)
    if unknown:
        raise ConfigError(type(params).__name__, f"no such parameter: {', '.join(sorted(unknown))}")
    out: dict[str, Any] = {}
    for f in fields(params):  # type: ignore[arg-type]
        if "origin" in f.metadata:
            if f.name in changes:
                out[f.name] = changes[f.name]
            continue
        inner = getattr(params, f.name)
        take = {k: v for k, v in changes.items() if k in _names(inner)}
        if take:
            out[f.name] = tuned(inner, **take)
    return replace(params, **out)  # type: ignore[type-var]


def _names(params: Any) -> set[str]:
    """The parameters of a section and of the sections nested in it."""
    out: set[str] = set()
    for f in fields(params):
        out |= {f.name} if "origin" in f.metadata else _names(getattr(params, f.name))
    return out


def _toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return '"' + value.replace("\\", "\\\\").replace('"', '\\"') + '"'
    return repr(value)
