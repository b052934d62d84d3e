"""``twinfocus record -o FILE [TOPIC ...]``: record topics of a running graph to MCAP."""

from __future__ import annotations

import argparse

from nodes.recorder import Recorder


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("topics", nargs="*", help="topics to record (default: all but graph/...)")
    parser.add_argument("-o", "--output", required=True, help="MCAP file to write")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing file")
    parser.add_argument(
        "--broker", default=None, help="broker control endpoint (default $TWINFOCUS_BROKER or tcp://127.0.0.1:7447)"
    )
    parser.add_argument(
        "--foxglove",
        action="store_true",
        help="also write Foxglove channels (images, poses, clouds, plots, log) so the file opens in Foxglove",
    )
    parser.add_argument("--name", default="recorder", help="node name on the graph")


def run(args: argparse.Namespace) -> int:
    node = Recorder(
        name=args.name,
        params={"out": args.output, "topics": args.topics, "overwrite": args.overwrite, "foxglove": args.foxglove},
        broker=args.broker,
    )
    return node.spin()
