"""``twinfocus play FILE``: publish a recorded MCAP log onto a running graph."""

from __future__ import annotations

import argparse

from nodes.player import Player
from twinfocus.option_types import non_negative_float


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("log", help="MCAP file to play")
    parser.add_argument(
        "--rate", type=non_negative_float, default=1.0, help="speed factor (default 1; 0 = as fast as possible)"
    )
    parser.add_argument("--loop", action="store_true", help="start again at the end")
    parser.add_argument("--topics", nargs="+", default=[], help="topics to play (default: all but graph/...)")
    parser.add_argument(
        "--start-offset", type=non_negative_float, default=0.0, metavar="S", help="skip the first S seconds of the log"
    )
    parser.add_argument(
        "--wait-for",
        nargs="+",
        default=[],
        metavar="NODE",
        help="nodes that must be ready (subscribed) before the first message",
    )
    parser.add_argument(
        "--broker", default=None, help="broker control endpoint (default $TWINFOCUS_BROKER or tcp://127.0.0.1:7447)"
    )
    parser.add_argument("--name", default="player", help="node name on the graph")


def run(args: argparse.Namespace) -> int:
    node = Player(
        name=args.name,
        params={
            "log": args.log,
            "rate": args.rate,
            "loop": args.loop,
            "topics": args.topics,
            "start_offset_s": args.start_offset,
            "wait_for": args.wait_for,
        },
        broker=args.broker,
    )
    code = node.spin()
    # the end-of-log line has said what was lost; a log that lacked anything is no clean replay
    return 1 if code == 0 and node.loss() else code
