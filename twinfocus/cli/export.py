"""``twinfocus export LOG.mcap --to foxglove OUT.mcap``: a log in Foxglove's well-known schemas."""

from __future__ import annotations

import argparse
import sys

from nodes.foxglove_convert import export_log
from twinfocus.jobs.progress import Progress


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("log", help="MCAP log written by `twinfocus record` (or a recorder node)")
    parser.add_argument(
        "--to",
        required=True,
        choices=["foxglove"],
        help="target format: foxglove (protobuf / JSON-schema channels Foxglove draws: images, poses, clouds, plots, log)",
    )
    parser.add_argument("output", help="MCAP file to write")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing output file")
    parser.add_argument("-q", "--quiet", action="store_true", help="no progress output")


def run(args: argparse.Namespace) -> int:

    counts = export_log(
        args.log,
        args.output,
        overwrite=args.overwrite,
        progress=Progress("export", enabled=not args.quiet),
        say=lambda line: print(line, file=sys.stderr),
    )
    per = ", ".join(f"{t}: {n}" for t, n in sorted(counts.items()))
    print(
        f"wrote {sum(counts.values())} Foxglove message(s) to {args.output}" + (f" ({per})" if per else ""),
        file=sys.stderr,
    )
    return 0
