"""``twinfocus topic list|echo|hz``: look at the topics of a running graph."""

from __future__ import annotations

import argparse
import sys

from nodes.runtime.introspect import TopicEcho, TopicHz, TopicList
from twinfocus.option_types import non_negative_float, non_negative_int, positive_float


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--broker", default=None, help="broker control endpoint (default $TWINFOCUS_BROKER or tcp://127.0.0.1:7447)"
    )
    sub = parser.add_subparsers(dest="action", metavar="ACTION")
    sub.required = True
    p = sub.add_parser("list", help="topics with their types (from the nodes' heartbeats)")
    p.add_argument("-v", "--verbose", action="store_true", help="also publishers, subscribers and counts")
    p.add_argument("--wait", type=positive_float, default=1.5, metavar="S", help="how long to listen for heartbeats")
    p = sub.add_parser("echo", help="print the messages of a topic")
    p.add_argument("topic")
    p.add_argument(
        "-n", "--count", type=non_negative_int, default=0, help="stop after N messages (default: until Ctrl-C)"
    )
    p.add_argument("--once", action="store_true", help="same as -n 1")
    p = sub.add_parser("hz", help="print the rate of a topic")
    p.add_argument("topic")
    p.add_argument("--window", type=positive_float, default=1.0, metavar="S", help="report period, seconds")
    p.add_argument(
        "--duration", type=non_negative_float, default=0.0, metavar="S", help="stop after S seconds (default: Ctrl-C)"
    )


def run(args: argparse.Namespace) -> int:
    common = {"out": sys.stdout, "broker": args.broker}
    node: TopicList | TopicEcho | TopicHz
    if args.action == "list":
        node = TopicList(duration_s=args.wait, verbose=args.verbose, **common)
    elif args.action == "echo":
        node = TopicEcho(topic=args.topic, count=1 if args.once else args.count, **common)
    else:
        node = TopicHz(topic=args.topic, window_s=args.window, duration_s=args.duration, **common)
    return node.spin()
