"""``fleetmap recover``: a recording cut short (a crash, SIGKILL, a full disk) rewritten whole."""

from __future__ import annotations

import argparse
from pathlib import Path

from fleetmap.shared.errors import BadInput
from fleetmap.shared.io.outputs import output_file
from fleetmap.shared.io.recording_reader import RecordingReader


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "recover",
        help="rewrite a recording cut short as a finished MCAP file any reader opens",
        description="Read every complete record of CUT.mcap (a recorder killed, or stopped by a full disk, "
        "leaves a file without its summary, which many readers refuse) and write them to FIXED.mcap with "
        "indexes and a summary: raw channels, Foxglove views, metadata. Like `mcap recover` and "
        "`ros2 bag reindex`. fleetmap replay reads cut files directly; Foxglove and the mcap library's "
        "ordinary reader need the rewritten one.",
    )
    p.add_argument("cut", metavar="CUT.mcap", help="the recording to recover")
    p.add_argument("fixed", metavar="FIXED.mcap", help="the file to write")
    p.add_argument("--overwrite", action="store_true", help="replace FIXED.mcap if it exists")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    source, target = Path(args.cut), output_file(args.fixed, "FIXED.mcap")
    if target.exists() and not args.overwrite:
        raise BadInput(str(target), "exists (--overwrite replaces it)")
    if target.exists() and source.exists() and target.samefile(source):
        raise BadInput(str(target), "is CUT.mcap itself; write the recovered file elsewhere")
    partial = target.with_name(target.name + ".partial")
    with RecordingReader(source) as reader, open(partial, "wb") as out:
        report = reader.recover(out)
    partial.replace(target)
    whole = "the whole file" if report.bytes_read >= report.size else f"{report.bytes_read} of {report.size} bytes"
    print(f"{target}: {report.messages} messages on {report.channels} channels recovered from {whole} of {source}")
    return 0
