"""The ``fleetmap`` command line: one subcommand per module of ``fleetmap.commands``.

Every command exits 0 on success, 2 on bad input (one line on stderr naming the input and what is
wrong with it) and 1 on any other failure.
"""

from __future__ import annotations

import argparse
import contextlib
import faulthandler
import importlib
import io
import logging
import signal
import sys
from collections.abc import Sequence

from fleetmap import __version__
from fleetmap.shared.errors import BadInput, FleetmapError

COMMANDS = (
    "extract",
    "integrate",
    "merge",
    "map",
    "simulate",
    "run",
    "replay",
    "recover",
    "agent",
    "merger",
    "record",
    "view",
    "router",
    "secure",
    "play",
)
"""Modules of fleetmap.commands, in the order ``--help`` lists them."""

log = logging.getLogger("fleetmap")


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The parser of every command; with ``command``, only that command's module is imported (the
    others are named, so a misspelt command still lists them): a command starts in a fraction of
    the time, without loading the engine, zenoh and the plotting of every other one."""
    parser = argparse.ArgumentParser(
        prog="fleetmap",
        description="Pose-free segment maps for robot fleets (Amigoni, Gasparini & Gini 2006).",
    )
    parser.add_argument("--version", action="version", version=f"fleetmap {__version__}")
    parser.add_argument(
        "-v", "--verbose", action="count", default=0, help="more log output (-vv: debug); anywhere on the line"
    )
    parser.add_argument(
        "-q", "--quiet", action="count", default=0, help="less log output (-qq: errors only); anywhere on the line"
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name in COMMANDS:
        if command in COMMANDS and name != command:
            sub.add_parser(name)
        else:
            importlib.import_module(f"fleetmap.commands.{name}").register(sub)
            short_usage(sub.choices[name])
    return parser


def short_usage(p: argparse.ArgumentParser) -> None:
    """A usage line a person can read: the positionals, the required options, then [options] (the
    command's dozens of algorithm parameters are listed, grouped, below it)."""
    parts = [p.prog]
    grouped: set[argparse.Action] = set()
    for group in p._mutually_exclusive_groups:
        if group.required:
            grouped.update(group._group_actions)
            parts.append(
                "("
                + " | ".join(
                    a.option_strings[-1] + ("" if a.nargs == 0 else f" {a.metavar or a.dest.upper()}")
                    for a in group._group_actions
                )
                + ")"
            )
    for a in p._actions:
        if a in grouped or isinstance(a, argparse._HelpAction):
            continue
        if not a.option_strings:
            name = str(a.metavar or a.dest)
            parts.append({"+": f"{name} [{name} ...]", "?": f"[{name}]", "*": f"[{name} ...]"}.get(str(a.nargs), name))
        elif a.required:
            parts.append(f"{a.option_strings[-1]} {a.metavar or a.dest.upper()}")
    p.usage = " ".join([*parts, "[options]"])


SERVICES = ("agent", "merger", "record", "router")
"""Commands that run until stopped: they log at INFO by default."""
VERBOSITY = {"-v": 1, "--verbose": 1, "-vv": 2, "-vvv": 3, "-q": -1, "--quiet": -1, "-qq": -2}


def _verbosity(argv: list[str]) -> tuple[list[str], int]:
    """``argv`` without its -v/-q flags (accepted anywhere before a ``--``), and how much louder
    they make the log (negative: quieter)."""
    out: list[str] = []
    louder = 0
    for i, arg in enumerate(argv):
        if arg == "--":
            return out + argv[i:], louder
        if arg in VERBOSITY:
            louder += VERBOSITY[arg]
        else:
            out.append(arg)
    return out, louder


def main(argv: Sequence[str] | None = None) -> int:
    argv, louder = _verbosity(list(sys.argv[1:] if argv is None else argv))
    # The global options take no value, so the first word that is not an option is the command.
    command = next((a for a in argv if not a.startswith("-")), None)
    args = build_parser(command).parse_args(argv)
    louder += args.verbose - args.quiet
    # services say what they do (robots joining, maps merging, a status line) at INFO; commands
    # that run once say only what went wrong
    base = logging.INFO if command in SERVICES else logging.WARNING
    level = min(max(base - 10 * louder, logging.DEBUG), logging.CRITICAL)
    logging.basicConfig(level=level, format="%(asctime)s %(name)s %(levelname)s %(message)s", stream=sys.stderr)
    if command in SERVICES and hasattr(signal, "SIGUSR1"):
        # `kill -USR1 PID` writes every thread's stack to stderr: what a service that does not stop is
        # doing (where stderr is a file: called in-process, as by a test capturing it, it may not be)
        with contextlib.suppress(AttributeError, ValueError, io.UnsupportedOperation):
            faulthandler.register(signal.SIGUSR1, all_threads=True)
    try:
        return int(args.func(args) or 0)
    except BadInput as exc:
        print(f"fleetmap {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except FleetmapError as exc:
        print(f"fleetmap {args.command}: failed: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"fleetmap {args.command}: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:
        return 1
    except Exception as exc:  # the CLI's one handler: anything unexpected is exit 1, traceback with -v
        log.debug("unexpected failure", exc_info=True)
        print(f"fleetmap {args.command}: failed: {type(exc).__name__}: {exc}", file=sys.stderr)
        return 1
