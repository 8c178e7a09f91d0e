"""Reading a configuration: a TOML file, or overrides by name, each value checked against its
parameter's type (:mod:`fleetmap.shared.config` is the configuration itself).

A file names its tables as :data:`~fleetmap.shared.config.SECTIONS` does; a parameter in the wrong
table, an unknown name, a value of the wrong type or sign is a :class:`~fleetmap.shared.errors.ConfigError`
naming the file, the table and the parameter. Parameters retired since (:data:`RETIRED`) still load,
ignored and said at INFO, so an old recording's config replays.
"""

from __future__ import annotations

import logging
import math
import tomllib
from collections.abc import Mapping
from pathlib import Path
from typing import Any, get_args, get_type_hints

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


RETIRED: dict[str, frozenset[str]] = {
    "merge": frozenset({"carried_max_ambiguity", "histogram_bins", "bridge_min_value"}),
    "tracking": frozenset({"registration"}),
}
"""Parameters the code does not read: a config file or a recording's config that names one still
loads (it is ignored, said at INFO)."""


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

    def take(path: str, table: Any) -> None:
        if not isinstance(table, Mapping):
            raise ConfigError(source, f"[{path}] must be a table")
        types = get_type_hints(SECTIONS[path])
        for name, value in table.items():
            if f"{path}.{name}" in SECTIONS:
                take(f"{path}.{name}", value)
                continue
            if name in RETIRED.get(path, ()):
                log.info("%s: [%s] %s is retired and ignored", source, path, name)
                continue
            where = path
            if name not in types:
                if not home.get(name, "").startswith(path + "."):
                    known = ", ".join(f.name for f in _leaves(SECTIONS[path]))
                    raise ConfigError(f"{source}: [{path}] {name}", f"unknown parameter (known: {known})")
                where = home[name]
                log.info("%s: [%s] %s is a parameter of [%s]: read there", source, path, name, where)
            kind = get_type_hints(SECTIONS[where])[name]
            changes.setdefault(where, {})[name] = _coerce(where, name, kind, value, source)

    for path, table in overrides.items():
        if path not in SECTIONS:
            top = ", ".join(p for p in SECTIONS if "." not in p)
            raise ConfigError(source, f"unknown section [{path}] (known: {top})")
        take(path, table)
    for path, values in changes.items():
        config = _with_section(config, path, values)
    return config


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
    except UnicodeDecodeError:
        raise ConfigError(str(p), "not a text file (not UTF-8)") from None
    except OSError as exc:
        raise ConfigError(str(p), f"cannot read: {exc.strerror}") from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(str(p), f"not valid TOML: {exc}") from None
    return apply_overrides(config, data, str(p))
