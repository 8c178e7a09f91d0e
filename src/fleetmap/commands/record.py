"""``fleetmap record``: every message of a fleet, and every robot coming and going, into MCAP."""

from __future__ import annotations

import argparse
import datetime
import logging
import math
import sys
import time
from pathlib import Path

from fleetmap import __version__
from fleetmap.merger.recorder import KEY_BURST, KEY_RATE, Recorder, RecorderService
from fleetmap.scenarios import load_scenario
from fleetmap.shared.config_files import load_config
from fleetmap.shared.errors import BadInput
from fleetmap.shared.io.outputs import output_file
from fleetmap.shared.io.recording import RecordingWriter, config_metadata
from fleetmap.shared.io.zenoh_bus import ZenohBus
from fleetmap.shared.io.zenoh_config import describe, zenoh_config
from fleetmap.zenoh_args import add_zenoh_arguments, stop_on_signals, zenoh_options_from_args

log = logging.getLogger(__name__)


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "record",
        help="record a fleet's messages to MCAP (raw for replay, Foxglove views for people)",
        description="Record every message under fleet/<fleet>/** and every liveliness change into an MCAP "
        "file: one raw msgpack channel per key (exact bytes, for fleetmap replay) and Foxglove channels "
        "(scene line lists of scans, local and global maps; frame transforms of robots). Runs until "
        "SIGINT or SIGTERM (or --duration), then finishes the file and prints messages per topic. The "
        "file is flushed every half second, so a crash loses at most about a second. A write that fails (a "
        "full disk) ends it with exit code 1, so that a supervisor starts it again into a new file once "
        "there is room (docker-compose.yml: restart: unless-stopped).",
    )
    p.add_argument(
        "--out",
        required=True,
        metavar="FILE",
        help="the MCAP file to write; if it exists, the next free numbered one beside it (session-1.mcap, ...): "
        "a restarted recorder never overwrites a recording",
    )
    p.add_argument("--overwrite", action="store_true", help="replace --out if it exists")
    p.add_argument("--config", metavar="FILE", help="the fleet's TOML config, stored in the file (default: defaults)")
    p.add_argument("--duration", type=float, default=None, metavar="S", help="stop after S seconds")
    p.add_argument(
        "--scenario",
        metavar="FILE",
        help="the scenario being run (TOML), stored in the file so a replay can score against its truth",
    )
    p.add_argument("--no-foxglove", action="store_true", help="raw channels only (no Foxglove views)")
    p.add_argument(
        "--max-key-rate",
        type=float,
        default=KEY_RATE / 1e6,
        metavar="MB/S",
        help=f"a robot (all its keys together; a key that is no robot's on its own) that writes faster than "
        f"this in the long run (bursts of {KEY_BURST / 1e6:g} MB pass) has its messages dropped and counted: one "
        f"flooding publisher cannot fill the disk; 0: no limit (default {KEY_RATE / 1e6:g})",
    )
    add_zenoh_arguments(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    if not (args.max_key_rate >= 0 and math.isfinite(args.max_key_rate)):
        raise BadInput("--max-key-rate", f"must be 0 (no limit) or a number of MB/s, got {args.max_key_rate}")
    if args.duration is not None and not args.duration > 0:
        raise BadInput("--duration", f"must be a positive number of seconds, got {args.duration}")
    options = zenoh_options_from_args(args)
    config = zenoh_config(options)
    fleet_config = load_config(args.config)
    out = recording_path(Path(args.out), args.overwrite)
    if out != Path(args.out):
        print(f"{args.out} exists: recording to {out}", file=sys.stderr)
    metadata = {
        "fleetmap.session": {
            "fleet": options.fleet,
            "started": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
            "recorder": f"fleetmap {__version__}",
            "command": " ".join(sys.argv),
        },
        "fleetmap.zenoh": describe(config),
        "fleetmap.config": config_metadata(fleet_config),
    }
    if args.scenario:
        # Validated first: a recording should not carry a scenario that cannot be read back.
        load_scenario(args.scenario)
        metadata["fleetmap.scenario"] = {"toml": Path(args.scenario).read_text(encoding="utf-8")}
    with ZenohBus.open(options) as bus:  # options, not config: it waits --connect-wait for a router
        writer = RecordingWriter(out)
        recorder = Recorder(
            writer,
            options.keys,
            metadata=metadata,
            foxglove=not args.no_foxglove,
            key_rate=args.max_key_rate * 1e6,
        )
        service = RecorderService(bus, recorder, options.keys)
        started = time.monotonic()
        with stop_on_signals() as stop:
            service.start()
            print(f"recording {options.keys.everything} to {out} (Ctrl-C or SIGTERM to stop)", file=sys.stderr)
            # A failed write ends the recording: the file cannot go on past a cut chunk, and a recorder
            # that stayed up recording nothing would never be restarted by its supervisor.
            while not stop.wait(0.1) and not recorder.error:
                if args.duration is not None and time.monotonic() - started >= args.duration:
                    break
            summary = service.stop()
    seconds = time.monotonic() - started
    size = out.stat().st_size
    print(f"{out}: {summary.total} messages on {len(summary.messages)} topics in {seconds:.1f} s, {size} bytes")
    print(summary.table())
    if summary.total_malformed:
        print(f"{summary.total_malformed} malformed messages recorded raw (no Foxglove view)")
    if summary.error:
        log.error(
            "%s: %s; %d messages lost; exiting (fleetmap recover rewrites what the file holds; started again, "
            "the recorder writes a new file beside it)",
            out,
            summary.error,
            summary.lost,
        )
        return 1
    return 0


def recording_path(out: Path, overwrite: bool = False) -> Path:
    """Where to record: ``out``, or where it exists (and ``overwrite`` is not given) the first of
    ``<stem>-1<suffix>``, ``<stem>-2<suffix>``, ... that does not: a recorder that restarts
    (``restart: unless-stopped``) starts a new file beside the last. Its folder must exist."""
    output_file(out, "--out")
    if overwrite or not out.exists():
        return out
    n = 1
    while (candidate := out.with_name(f"{out.stem}-{n}{out.suffix}")).exists():
        n += 1
    return candidate
