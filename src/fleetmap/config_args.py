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
from pathlib import Path
from typing import Any

from fleetmap.shared.config import SECTIONS, FleetmapConfig, MergeParams, tuned
from fleetmap.shared.config_files import apply_overrides, load_config

HELP_ALL = "--help-all"
BASIC_CONFIG = Path(__file__).resolve().parent / "examples" / "basic.toml"
"""The basic parameters' config file, installed with the package (``--config`` help names it)."""


class _HelpAll(argparse.Action):
    """``--help-all``: the help with every algorithm parameter, not only the basic ones."""

    def __init__(self, option_strings: Sequence[str], dest: str, **kwargs: Any) -> None:
        super().__init__(option_strings, dest, nargs=0, default=argparse.SUPPRESS, **kwargs)

    def __call__(self, parser: argparse.ArgumentParser, *_: Any, **__: Any) -> None:
        for action in parser._actions:
            hidden = getattr(action, "advanced_help", None)
            if hidden is not None:
                action.help = hidden
        parser.print_help()
        parser.exit()


def add_config_arguments(parser: argparse.ArgumentParser, sections: Sequence[str]) -> None:
    """Add ``--config FILE`` and one ``--field-name VALUE`` option per parameter of ``sections`` and
    the sections nested in them, each with its tag (paper or fleetmap) and the first sentence of its
    docstring. ``--help`` shows the basic parameters; ``--help-all`` every one."""
    parser.add_argument(
        "--config",
        metavar="FILE",
        help="a TOML file of algorithm parameters, one table per stage ([extraction], [integration], "
        f"[integration.validity], ...; {BASIC_CONFIG} holds the basic ones: copy it)",
    )
    parser.add_argument(HELP_ALL, action=_HelpAll, help="show this help with every algorithm parameter, and exit")
    basic = parser.add_argument_group("basic parameters (override --config)")
    for path in SECTIONS:
        if path.split(".")[0] not in sections:
            continue
        said = field_sentences(SECTIONS[path])
        group = parser.add_argument_group(f"advanced parameters: [{path}] (shown by {HELP_ALL})")
        for f in fields(SECTIONS[path]):
            if "origin" not in f.metadata:
                continue
            default = f.default
            text = f"[{f.metadata['origin']}] {said.get(f.name, '')} (default {default!r})"
            shown = f.metadata.get("basic", False)
            action = (basic if shown else group).add_argument(
                "--" + f.name.replace("_", "-"),
                dest=f"cfg__{path}__{f.name}",
                metavar=type(default).__name__.upper() if not isinstance(default, str) else "NAME",
                default=None,
                help=text if shown else argparse.SUPPRESS,
            )
            if not shown:
                action.advanced_help = text  # type: ignore[attr-defined]


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


def offline(config: FleetmapConfig, args: argparse.Namespace) -> FleetmapConfig:
    """``config`` for a command that maps or merges a user's own data (``fleetmap map``, ``fleetmap
    merge``): no budget of work per integration unless one was asked for, on the command line or
    in the config file. The budget bounds what a robot's submaps can cost a live merger, and its
    replay repeats it (:mod:`fleetmap.shared.core.work`); a user's own logs and maps are no
    attacker's, and two halves of one building mapped apart need more than a live fleet's submaps
    (mit-csail's: tests/test_map.py)."""
    # without it on the command line, the value is the config file's (or the default)
    asked = getattr(args, "cfg__merge__max_integration_work", None) is not None or (
        getattr(args, "config", None) is not None
        and config.merge.max_integration_work != MergeParams().max_integration_work
    )
    return config if asked else tuned(config, max_integration_work=0)
