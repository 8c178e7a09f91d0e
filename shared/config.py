"""One typed configuration, with the paper's parameter names and defaults.

Amigoni, Gasparini & Gini (2006) name their parameters in capitals (POINTDISTANCETOLERANCE, ...);
here they are snake_case fields with the same meaning and the paper's defaults, in metres and
radians. Every run writes the resolved configuration next to its outputs (``to_dict``/``to_toml``).

At most 40 parameters, one section per stage, in data-flow order (:data:`SECTIONS`): the paper's,
those a user sets for their robots, and the few choices with a decision record behind them
(docs/decisions/005-parameters-beyond-the-paper.md); every other value is a constant in the module
that reads it, with its reason. Each field is tagged ``paper`` (the paper's parameter, with its
default) or ``fleetmap`` (added here), and ``basic`` marks those a user sets for their robots
(``fleetmap/examples/basic.toml``). The defaults are a live fleet's; ``fleetmap/examples/live.toml``
and ``offline.toml`` hold the values where the modes differ. A config file is TOML with one table
per section::

    [extraction]
    max_range = 8.0

    [integration]
    point_distance_tolerance = 0.010

    [integration.validity]
    map_free_space_clearance = 0.2

Command-line overrides use the field names with dashes (``--point-distance-tolerance 0.01``). Reading
a file or overrides, each value checked: :mod:`fleetmap.shared.config_files`.
"""

from __future__ import annotations

import dataclasses
import logging
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
    """A noisy scan's polyline tolerance is this times its noise, where that clearly exceeds ``kappa``
    (0: always ``kappa``; docs/decisions/006-real-lasers-extraction-and-refusal.md)."""
    max_range: float = ours(20.0, basic=True)
    """Ranges beyond this are no return (m); far walls tell a corridor's length (the paper's laser: 8 m)."""


@dataclass(frozen=True)
class ValidityParams:
    """Whether an integration's best transformation is trusted (:mod:`fleetmap.shared.core.validity`;
    docs/decisions/005-parameters-beyond-the-paper.md)."""

    valid_min_value: float = paper(1.0)
    """An integration is valid only if its value is at least this (m) (the paper's threshold, V-B) ..."""
    map_free_space_clearance: float = ours(0.3)
    """Two partial maps: the free-space limit on the best leaves out wall within this (m) of the other
    map's own walls (two maps place one wall a little apart); 0: none left out."""


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
    pivot_refine: bool = ours(True)
    """A placed scan's pose is refined by least squares on the built map near it (scan-to-map)."""
    pivot_refine_slack: float = ours(0.01)
    """That refinement is kept if it lowers the value by at most this fraction, after a small move
    (docs/decisions/005-parameters-beyond-the-paper.md)."""


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
    aligner: Aligner = ours("paper", basic=True)
    """paper: the paper's integration (Algorithms 1-4); ransac: RANSAC over corner and wall-end
    landmarks matched by their descriptors (Ballesta et al. 2009), valued and judged alike."""
    validity: ValidityParams = section(ValidityParams)
    motion: MotionParams = section(MotionParams)
    pivot: PivotParams = section(PivotParams)


@dataclass(frozen=True)
class MergeParams:
    """Merging many maps: the map graph and the fleet pose graph (paper IV; docs/decisions/002-pose-graph.md)."""

    polish_edges: bool = ours(True)
    """An integration of a partial map integrated simplified is fitted again by least squares on the
    maps as they are (within the witness tolerances)."""
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
    max_integration_work: int = ours(80_000_000)
    """One integration of two submaps stops past this many units of work (grid lookups and segment
    pairs compared: fleetmap.shared.core.work) and is not valid (logged and counted; 0: no limit):
    its cost is bounded whatever the submaps hold, and a replay stops where the live merger
    stopped. The real logs' submaps need at most 50 M (docs/decisions/013-input-that-looks-legitimate.md).
    The offline preset (``fleetmap map``, ``fleetmap merge``) sets none: a user's own data is no attacker's."""
    max_robots: int = ours(256, basic=True)
    """The merger keeps track of at most this many robots; messages of more are dropped and counted."""
    step_seconds: float = ours(0.25)
    """Seconds of one merger step: live, the time budget of the integrations of a step that takes new
    submaps in (0: every pending one); offline, the fleet time between two steps (0: one a scan). The
    presets set it per mode (fleetmap/examples/live.toml, offline.toml; docs/decisions/004)."""


@dataclass(frozen=True)
class TrackingParams:
    """The robot agent's front end: scan-to-submap tracking (:mod:`fleetmap.shared.core.tracking`,
    :mod:`fleetmap.agents.tracker`; docs/decisions/001-tracking-front-end.md)."""

    front_end: FrontEnd = ours("tracking", basic=True)
    """tracking: predict, register on the active submap, check; pivot: the paper's pivot method
    (IV-C, Algorithm 6), one local map per epoch, each scan placed by pose-free integration."""
    odometry: Odometry = ours("auto", basic=True)
    """auto: use the source's odometry when it has some; on: require it; off: constant velocity only."""
    submap_length: float = ours(10.0, basic=True)
    """A submap covers this much of the robot's path (m), or a hundred inserted scans; the next starts
    halfway, so consecutive submaps overlap by half."""
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
