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
from typing import Any, Literal

from fleetmap.shared.config import SECTIONS, FleetmapConfig
from fleetmap.shared.config_files import apply_overrides, load_config

HELP_ALL = "--help-all"
BASIC_CONFIG = Path(__file__).resolve().parent / "examples" / "basic.toml"
"""The basic parameters' config file, installed with the package (``--config`` help names it)."""
Mode = Literal["live", "offline"]
PRESETS: dict[str, Path] = {mode: BASIC_CONFIG.with_name(f"{mode}.toml") for mode in ("live", "offline")}
"""The defaults of a live fleet (``fleetmap run``, ``agent``, ``merger``) and of an offline run
(``fleetmap map``, ``merge``) where the two differ, installed with the package (as slam_toolbox
ships one configuration per mode)."""


def preset(mode: Mode) -> FleetmapConfig:
    """The configuration of ``mode``: the defaults with its preset file read on top."""
    return load_config(PRESETS[mode])


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


def add_config_arguments(parser: argparse.ArgumentParser, sections: Sequence[str], mode: Mode | None = None) -> None:
    """Add ``--config FILE`` and one ``--field-name VALUE`` option per parameter of ``sections`` and
    the sections nested in them, each with its tag (paper or fleetmap), the first sentence of its
    docstring and its default (``mode``'s preset's, where the command has one:
    :func:`config_from_args` starts from it). ``--help`` shows the basic parameters; ``--help-all``
    every one."""
    parser.set_defaults(config_mode=mode)
    defaults = (preset(mode) if mode is not None else FleetmapConfig()).flat()
    parser.add_argument(
        "--config",
        metavar="FILE",
        help="a TOML file of algorithm parameters, one table per stage ([extraction], [integration], "
        f"[integration.validity], ...; {BASIC_CONFIG} holds the basic ones: copy it), read on top of the "
        "command's preset (live.toml or offline.toml beside it)",
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
            default = defaults[f"{path}.{f.name}"]
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
def field_docs(cls: type) -> dict[str, str]:
    """Each field's docstring (the string literal after it in the class body), on one line."""
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
            out[field_node.target.id] = " ".join(doc.value.value.split())
    return out


@functools.cache
def field_sentences(cls: type) -> dict[str, str]:
    """The first sentence of each field's docstring, for ``--help``."""
    out: dict[str, str] = {}
    for name, doc in field_docs(cls).items():
        sentence = re.split(r"(?<=[a-z0-9)]\.)\s+(?=[A-Z(])", doc.replace("``", ""), maxsplit=1)[0]
        out[name] = sentence if len(sentence) <= 160 else sentence[:157].rstrip() + "..."
    return out


def config_from_args(args: argparse.Namespace) -> FleetmapConfig:
    """The preset of the command's mode (live or offline, if it has one: :func:`add_config_arguments`),
    the config file named by ``--config`` read on top of it, and the command-line overrides on top."""
    mode = getattr(args, "config_mode", None)
    base = preset(mode) if mode is not None else FleetmapConfig()
    config = load_config(getattr(args, "config", None), base)
    overrides: dict[str, dict[str, Any]] = {}
    for key, value in vars(args).items():
        if key.startswith("cfg__") and value is not None:
            _, section, name = key.split("__", 2)
            overrides.setdefault(section, {})[name] = value
    return apply_overrides(config, overrides, "command line") if overrides else config
