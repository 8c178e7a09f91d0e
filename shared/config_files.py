"""Reading a configuration: a TOML file, or overrides by name, each value checked against its
parameter's type (:mod:`fleetmap.shared.config` is the configuration itself).

A file names its tables as :data:`~fleetmap.shared.config.SECTIONS` does; a parameter in the wrong
table, an unknown name, a value of the wrong type or sign is a :class:`~fleetmap.shared.errors.ConfigError`
naming the file, the table and the parameter. Parameters retired since (:data:`RETIRED`: module
constants now) still load, so an old recording's config replays: at their fixed value said at INFO,
at another with a WARNING.
"""

from __future__ import annotations

import logging
import math
import tomllib
from collections.abc import Mapping
from pathlib import Path
from typing import Any, NamedTuple, get_args, get_type_hints

from fleetmap.shared.config import SECTIONS, FleetmapConfig, _leaves, _with_section, parameters
from fleetmap.shared.errors import ConfigError

log = logging.getLogger(__name__)


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


class Retired(NamedTuple):
    """A parameter that is now a module constant: its fixed value, and where it lives (under
    ``fleetmap.``); None: a feature removed, its value ignored whatever it was."""

    value: Any
    constant: str


RETIRED: dict[str, dict[str, Retired]] = {
    "extraction": {
        "noisy_kappa_share": Retired(1.25, "shared.core.extraction.NOISY_KAPPA_SHARE"),
        "noise_span": Retired(0.3, "shared.core.extraction.NOISE_SPAN"),
        "breakpoint_angle": Retired(0.1745, "shared.core.extraction.BREAKPOINT_ANGLE"),
        "min_cluster_points": Retired(3, "shared.core.extraction.MIN_CLUSTER_POINTS"),
        "line_fit": Retired(True, "shared.core.extraction.LINE_FIT"),
    },
    "integration": {
        "refuse_range_slope": Retired(0.01, "shared.core.transformation_value.REFUSE_RANGE_SLOPE"),
        "seed": Retired(0, "shared.core.candidates.SEED"),
        "max_angles": Retired(300, "shared.core.candidates.MAX_ANGLES"),
        "max_search_segments": Retired(150, "shared.core.integration.MAX_SEARCH_SEGMENTS"),
        "max_evaluated": Retired(8000, "shared.core.integration.MAX_EVALUATED"),
        "pair_angle_limit": Retired(0.5, "shared.core.transformation_value.PAIR_ANGLE_LIMIT"),
        "min_vertex_angle": Retired(0.35, "shared.core.candidates.MIN_VERTEX_ANGLE"),
        "distinct_translation": Retired(0.1, "shared.core.distinct.DISTINCT_TRANSLATION"),
        "distinct_rotation": Retired(0.035, "shared.core.distinct.DISTINCT_ROTATION"),
        "shortlist": Retired(64, "shared.core.integration.SHORTLIST"),
        "also_by_value": Retired(4, "shared.core.integration.ALSO_BY_VALUE"),
        "refine": Retired(True, "shared.core.integration.REFINE"),
        "refine_candidates": Retired(12, "shared.core.integration.REFINE_CANDIDATES"),
        "refine_first_steps": Retired(3, "shared.core.integration.REFINE_FIRST_STEPS"),
        "refine_keep": Retired(0.6, "shared.core.integration.REFINE_KEEP"),
        "refine_coarse_factor": Retired(8.0, "shared.core.integration.REFINE_COARSE_FACTOR"),
        "rivals": Retired(8, "shared.core.integration.RIVALS"),
        "auto_max_all_candidates": Retired(4000, "shared.core.distinct.AUTO_MAX_ALL_CANDIDATES"),
        "near_prior_translation": Retired(1.0, "shared.core.near.NEAR_PRIOR_TRANSLATION"),
        "near_prior_rotation": Retired(0.35, "shared.core.near.NEAR_PRIOR_ROTATION"),
        "grid_resolution": Retired(0.1, "shared.core.mapgrid.GRID_RESOLUTION"),
        "simplify_tolerance": Retired(0.05, "shared.core.simplify.SIMPLIFY_TOLERANCE"),
    },
    "integration.validity": {
        "valid_min_fraction": Retired(0.2, "shared.core.validity.VALID_MIN_FRACTION"),
        "valid_max_violation": Retired(0.2, "shared.core.validity.VALID_MAX_VIOLATION"),
        "valid_max_ambiguity": Retired(0.8, "shared.core.validity.VALID_MAX_AMBIGUITY"),
        "ambiguity_translation": Retired(0.5, "shared.core.validity.AMBIGUITY_TRANSLATION"),
        "ambiguity_rotation": Retired(0.17, "shared.core.validity.AMBIGUITY_ROTATION"),
        "free_space_margin": Retired(0.1, "shared.core.integration.FREE_SPACE_MARGIN"),
        "map_free_space_margin": Retired(0.2, "shared.core.mapgrid.MAP_FREE_SPACE_MARGIN"),
        "map_free_space_slope": Retired(0.02, "shared.core.mapgrid.MAP_FREE_SPACE_SLOPE"),
        "map_free_space_min_length": Retired(0.0, "shared.core.integration.MAP_FREE_SPACE_MIN_LENGTH"),
        "valid_min_map_value": Retired(8.0, "shared.core.validity.VALID_MIN_MAP_VALUE"),
        "valid_min_map_scans": Retired(5, "shared.core.validity.VALID_MIN_MAP_SCANS"),
        "valid_max_map_violation": Retired(0.1, "shared.core.validity.VALID_MAX_MAP_VIOLATION"),
        "valid_max_map_ambiguity": Retired(0.5, "shared.core.validity.VALID_MAX_MAP_AMBIGUITY"),
        "valid_strong_map_value": Retired(16.0, "shared.core.validity.VALID_STRONG_MAP_VALUE"),
        "valid_max_strong_map_violation": Retired(0.15, "shared.core.validity.VALID_MAX_STRONG_MAP_VIOLATION"),
        "valid_refute_violation": Retired(3.0, "shared.core.validity.VALID_REFUTE_VIOLATION"),
        "valid_refute_clean": Retired(0.025, "shared.core.validity.VALID_REFUTE_CLEAN"),
    },
    "integration.ransac": {
        "ransac_support_distance": Retired(0.2, "shared.core.ransac.SUPPORT_DISTANCE"),
        "ransac_min_supports": Retired(3, "shared.core.ransac.MIN_SUPPORTS"),
        "ransac_iterations": Retired(2000, "shared.core.ransac.ITERATIONS"),
    },
    "integration.pivot": {
        "pivot_refine_slack_translation": Retired(0.1, "shared.core.refine.SLACK_TRANSLATION"),
        "pivot_refine_slack_rotation": Retired(0.035, "shared.core.refine.SLACK_ROTATION"),
        "local_map_radius": Retired(20.0, "shared.core.pivotmap.LOCAL_MAP_RADIUS"),
        "corner_turn": Retired(math.pi / 4, "shared.core.pivotmap.CORNER_TURN"),
        "simplify_from": Retired(200, "shared.core.pivotmap.SIMPLIFY_FROM"),
        "witness_translation": Retired(0.3, "shared.core.pivotmap.WITNESS_TRANSLATION"),
        "witness_rotation": Retired(0.0524, "shared.core.pivotmap.WITNESS_ROTATION"),
    },
    "tracking": {
        "sample_spacing": Retired(0.1, "shared.core.tracking.SAMPLE_SPACING"),
        "voxel_size": Retired(0.05, "shared.core.tracking.VOXEL_SIZE"),
        "residual_sigma": Retired(0.03, "shared.core.tracking.RESIDUAL_SIGMA"),
        "max_correspondence": Retired(1.0, "shared.core.tracking.MAX_CORRESPONDENCE"),
        "min_correspondence": Retired(0.25, "shared.core.tracking.MIN_CORRESPONDENCE"),
        "loss_scale": Retired(0.2, "shared.core.tracking.LOSS_SCALE"),
        "iterations_per_stage": Retired(8, "shared.core.tracking.ITERATIONS_PER_STAGE"),
        "max_iterations": Retired(30, "shared.core.tracking.MAX_ITERATIONS"),
        "convergence_translation": Retired(0.001, "shared.core.tracking.CONVERGENCE_TRANSLATION"),
        "convergence_rotation": Retired(0.001, "shared.core.tracking.CONVERGENCE_ROTATION"),
        "max_normal_angle": Retired(1.0472, "shared.core.tracking.MAX_NORMAL_ANGLE"),
        "odometry_translation_sigma": Retired(0.05, "shared.core.motion.ODOMETRY_TRANSLATION_SIGMA"),
        "odometry_translation_rate": Retired(0.1, "shared.core.motion.ODOMETRY_TRANSLATION_RATE"),
        "odometry_rotation_rate": Retired(0.5, "shared.core.motion.ODOMETRY_ROTATION_RATE"),
        "velocity_translation_sigma": Retired(0.05, "shared.core.motion.VELOCITY_TRANSLATION_SIGMA"),
        "velocity_rotation_sigma": Retired(0.087, "shared.core.motion.VELOCITY_ROTATION_SIGMA"),
        "max_angular_acceleration": Retired(6.0, "shared.core.motion.MAX_ANGULAR_ACCELERATION"),
        "insert_distance": Retired(0.1, "agents.submap.INSERT_DISTANCE"),
        "insert_rotation": Retired(0.035, "agents.submap.INSERT_ROTATION"),
        "insert_interval": Retired(5.0, "agents.submap.INSERT_INTERVAL"),
        "submap_scans": Retired(100, "agents.submap.SUBMAP_SCANS"),
        "typical_score_share": Retired(0.5, "agents.fitcheck.TYPICAL_SCORE_SHARE"),
        "recent_fits": Retired(20, "agents.tracker.RECENT_FITS"),
        "min_matched_share": Retired(0.3, "agents.fitcheck.MIN_MATCHED_SHARE"),
        "min_matched_length": Retired(1.0, "agents.fitcheck.MIN_MATCHED_LENGTH"),
        "max_see_through": Retired(0.5, "agents.fitcheck.MAX_SEE_THROUGH"),
        "see_through_margin": Retired(0.3, "shared.core.tracking.SEE_THROUGH_MARGIN"),
        "see_through_slope": Retired(0.02, "shared.core.tracking.SEE_THROUGH_SLOPE"),
        "see_through_beams": Retired(5.0, "shared.core.tracking.SEE_THROUGH_BEAMS"),
        "drift_translation": Retired(0.02, "shared.core.tracking.DRIFT_TRANSLATION"),
        "drift_rotation": Retired(0.004, "shared.core.tracking.DRIFT_ROTATION"),
        "link_min_sigma_translation": Retired(0.01, "agents.submap.LINK_MIN_SIGMA_TRANSLATION"),
        "link_min_sigma_rotation": Retired(0.005, "agents.submap.LINK_MIN_SIGMA_ROTATION"),
        "odometry_rotation_sigma": Retired(0.087, "shared.core.motion.ODOMETRY_ROTATION_SIGMA"),
        # the point-to-curve residual (eICP) was dropped: docs/decisions/012-the-other-papers.md
        "registration": Retired("point_to_line", "shared.core.tracking.RESIDUAL"),
    },
    "merge": {
        "carried_max_ambiguity": Retired(None, ""),
        "histogram_bins": Retired(None, ""),
        "bridge_min_value": Retired(None, ""),
        "cycle_translation_tolerance": Retired(0.3, "merger.graph.CYCLE_TRANSLATION_TOLERANCE"),
        "cycle_rotation_tolerance": Retired(0.087, "merger.graph.CYCLE_ROTATION_TOLERANCE"),
        "max_candidates": Retired(0, "merger.graph.MAX_CANDIDATES"),
        "near_candidates": Retired(3, "merger.schedule.NEAR_CANDIDATES"),
        "far_candidates": Retired(3, "merger.schedule.FAR_CANDIDATES"),
        "far_budget": Retired(12, "merger.schedule.FAR_BUDGET"),
        "loop_sweep_every": Retired(4, "merger.schedule.LOOP_SWEEP_EVERY"),
        "search_growth": Retired(2, "merger.schedule.SEARCH_GROWTH"),
        "descriptor_step": Retired(0.5, "merger.graph.DESCRIPTOR_STEP"),
        "descriptor_reach": Retired(12.0, "merger.graph.DESCRIPTOR_REACH"),
        "join_support": Retired(2, "merger.joins.JOIN_SUPPORT"),
        "join_hypotheses": Retired(3, "merger.joins.JOIN_HYPOTHESES"),
        "polish_iterations": Retired(30, "merger.executor.POLISH_ITERATIONS"),
        "edge_information": Retired(True, "merger.executor.EDGE_INFORMATION"),
        "edge_sigma_translation": Retired(0.05, "merger.graph.EDGE_SIGMA_TRANSLATION"),
        "edge_sigma_rotation": Retired(0.01, "merger.graph.EDGE_SIGMA_ROTATION"),
        "isotropic_share": Retired(0.01, "merger.refinement.ISOTROPIC_SHARE"),
        "robust_scale": Retired(2.0, "merger.refinement.ROBUST_SCALE"),
        "max_rejection_rounds": Retired(5, "merger.posegraph.MAX_REJECTION_ROUNDS"),
        "scan_constraints": Retired(True, "merger.scangraph.SCAN_CONSTRAINTS"),
        "scan_key_spacing": Retired(1.0, "merger.scangraph.SCAN_KEY_SPACING"),
        "scan_key_rotation": Retired(0.35, "merger.scangraph.SCAN_KEY_ROTATION"),
        "scan_search_radius": Retired(2.0, "merger.scangraph.SCAN_SEARCH_RADIUS"),
        "scan_prior_translation": Retired(0.3, "merger.scangraph.SCAN_PRIOR_TRANSLATION"),
        "scan_prior_rotation": Retired(0.087, "merger.scangraph.SCAN_PRIOR_ROTATION"),
        "scan_max_correction": Retired(0.5, "merger.scangraph.SCAN_MAX_CORRECTION"),
        "scan_min_matched_share": Retired(0.5, "merger.scangraph.SCAN_MIN_MATCHED_SHARE"),
        "max_submap_segments": Retired(5000, "merger.intake.MAX_SUBMAP_SEGMENTS"),
        "max_queued_pairs": Retired(20000, "merger.schedule.MAX_QUEUED_PAIRS"),
    },
}
"""Parameters that are module constants now (docs/decisions/005-parameters-beyond-the-paper.md), by
the table a config named them in: a config file or a recording's config that names one still loads.
At its fixed value it is said at INFO; at any other a WARNING names the file, the table, the
parameter, its value and the value the run uses instead (a replay's map may then differ from the
recording's). ``[integration.ransac]`` is retired whole."""


def _retired(path: str, name: str) -> tuple[str, Retired] | None:
    """The retired parameter ``name`` named in table ``path`` (or in a table it is nested in, as
    configs written before the nested tables name them): its table and entry."""
    for table, entries in RETIRED.items():
        if name in entries and (table == path or table.startswith(path + ".")):
            return table, entries[name]
    return None


def _home() -> dict[str, str]:
    """Each parameter's section (parameter names are unique across sections)."""
    return {f.name: path for path, f in parameters()}


def apply_overrides(config: FleetmapConfig, overrides: Mapping[str, Any], source: str) -> FleetmapConfig:
    """Return ``config`` with ``overrides`` applied: a TOML document's tables (``{"integration":
    {..., "validity": {...}}}``) or ``{"integration.validity": {name: value}}``; unknown names are
    errors. A parameter named in the table its own table is nested in (``valid_min_value`` in
    ``[integration]``, as configs and recordings written before ``[integration.validity]`` name it)
    is read in its own, said at INFO."""
    changes: dict[str, dict[str, Any]] = {}
    home = _home()
    fixed: list[str] = []

    def take(path: str, table: Any) -> None:
        if not isinstance(table, Mapping):
            raise ConfigError(source, f"[{path}] must be a table")
        types = get_type_hints(SECTIONS[path]) if path in SECTIONS else {}
        for name, value in table.items():
            if f"{path}.{name}" in SECTIONS or f"{path}.{name}" in RETIRED:
                take(f"{path}.{name}", value)
                continue
            retired = None if name in types else _retired(path, name)
            if retired is not None:
                _said_retired(source, path, name, value, retired[1], fixed)
                continue
            where = path
            if name not in types:
                if not home.get(name, "").startswith(path + "."):
                    known = ", ".join(f.name for f in _leaves(SECTIONS[path])) if path in SECTIONS else "none"
                    raise ConfigError(f"{source}: [{path}] {name}", f"unknown parameter (known: {known})")
                where = home[name]
                log.info("%s: [%s] %s is a parameter of [%s]: read there", source, path, name, where)
            kind = get_type_hints(SECTIONS[where])[name]
            changes.setdefault(where, {})[name] = _coerce(where, name, kind, value, source)

    for path, table in overrides.items():
        if path not in SECTIONS and path not in RETIRED:
            top = ", ".join(p for p in SECTIONS if "." not in p)
            raise ConfigError(source, f"unknown section [{path}] (known: {top})")
        take(path, table)
    if fixed:
        log.info("%s: %s: no longer parameters, at their fixed values (ignored)", source, ", ".join(fixed))
    for path, values in changes.items():
        config = _with_section(config, path, values)
    return config


def _said_retired(source: str, path: str, name: str, value: Any, retired: Retired, fixed: list[str]) -> None:
    """A retired parameter in a config: at its fixed value (or a removed feature's), noted for one
    INFO line; at another value, a WARNING: the run does not use it."""
    if retired.value is None or (value == retired.value and type(value) is type(retired.value)):
        fixed.append(f"[{path}] {name}")
        return
    log.warning(
        "%s: [%s] %s = %r is no longer a parameter: it is fixed at %r (fleetmap.%s); this run uses %r",
        source,
        path,
        name,
        value,
        retired.value,
        retired.constant,
        retired.value,
    )


def load_config(path: str | Path | None = None, base: FleetmapConfig | None = None) -> FleetmapConfig:
    """``base`` (default: the defaults), updated from a TOML file when one is given."""
    config = base or FleetmapConfig()
    if path is None:
        return config
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ConfigError(str(p), "no such config file") from None
    except UnicodeDecodeError:
        raise ConfigError(str(p), "not a text file (not UTF-8)") from None
    except OSError as exc:
        raise ConfigError(str(p), f"cannot read: {exc.strerror}") from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(str(p), f"not valid TOML: {exc}") from None
    return apply_overrides(config, data, str(p))
