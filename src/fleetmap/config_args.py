"""The configuration on the command line: ``--config FILE`` and one option per field."""

from __future__ import annotations

import argparse
import ast
import functools
import inspect
import itertools
import re
import textwrap
from collections.abc import Sequence
from dataclasses import fields
from typing import Any

from fleetmap.shared.config import SECTIONS, FleetmapConfig, apply_overrides, load_config


def add_config_arguments(parser: argparse.ArgumentParser, sections: Sequence[str]) -> None:
    """Add ``--config FILE`` and one ``--field-name VALUE`` option per field of ``sections``, in
    "advanced algorithm parameters" groups, each with the first sentence of its field's docstring."""
    parser.add_argument(
        "--config",
        metavar="FILE",
        help="a TOML file of algorithm parameters, one table per section ([integration], ...)",
    )
    for section in sections:
        cls = SECTIONS[section]
        said = field_sentences(cls)
        group = parser.add_argument_group(
            f"advanced algorithm parameters: {section} (override --config; fleetmap/shared/config.py explains each)"
        )
        for f in fields(cls):
            default = f.default
            group.add_argument(
                "--" + f.name.replace("_", "-"),
                dest=f"cfg__{section}__{f.name}",
                metavar=type(default).__name__.upper() if not isinstance(default, str) else "NAME",
                default=None,
                help=f"{said.get(f.name, '')} (default {default!r})".lstrip(),
            )


@functools.cache
def field_sentences(cls: type) -> dict[str, str]:
    """The first sentence of each field's docstring (the string literal after it in the class body),
    for ``--help``."""
    try:
        body = ast.parse(textwrap.dedent(inspect.getsource(cls))).body[0]
    except (OSError, TypeError, SyntaxError):
        return {}
    out: dict[str, str] = {}
    statements = body.body if isinstance(body, ast.ClassDef) else []
    for field_node, doc in itertools.pairwise(statements):
        if (
            isinstance(field_node, ast.AnnAssign)
            and isinstance(field_node.target, ast.Name)
            and isinstance(doc, ast.Expr)
            and isinstance(doc.value, ast.Constant)
            and isinstance(doc.value.value, str)
        ):
            text = " ".join(doc.value.value.replace("``", "").split())
            sentence = re.split(r"(?<=[a-z0-9)]\.)\s+(?=[A-Z(])", text, maxsplit=1)[0]
            out[field_node.target.id] = sentence if len(sentence) <= 160 else sentence[:157].rstrip() + "..."
    return out


def config_from_args(args: argparse.Namespace) -> FleetmapConfig:
    """The config file named by ``--config`` (or the defaults) with the command-line overrides."""
    config = load_config(getattr(args, "config", None))
    overrides: dict[str, dict[str, Any]] = {}
    for key, value in vars(args).items():
        if key.startswith("cfg__") and value is not None:
            _, section, name = key.split("__", 2)
            overrides.setdefault(section, {})[name] = value
    return apply_overrides(config, overrides, "command line") if overrides else config
