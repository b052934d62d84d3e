"""``twinfocus launch FILE [name:=value ...]``: start the broker and a graph of nodes.

See :mod:`nodes.runtime.launch` for the launch-file format and the shutdown rules.
"""

from __future__ import annotations

import argparse

from nodes.runtime import launch
from twinfocus.option_types import positive_float


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "file", help="launch file (a path, or a name in launch/: sim, replay, live); options go before it"
    )
    parser.add_argument("assignments", nargs="*", metavar="name:=value", help="launch arguments")
    parser.add_argument("--show", action="store_true", help="print the resolved graph and exit")
    parser.add_argument(
        "--grace",
        type=positive_float,
        default=10.0,
        help="seconds a stopping node may go without a heartbeat before SIGKILL (one still heartbeating gets up to 120 s)",
    )


def run(args: argparse.Namespace) -> int:
    graph = launch.load(args.file, args.assignments)
    if args.show:
        print(f"# {graph.path}: {graph.description}")
        print(f"broker: {graph.broker}")
        print("arguments: " + ", ".join(f"{k}={v!r}" for k, v in graph.arguments.items()))
        for n in graph.nodes:
            respawn = f" respawn (delay {n.respawn_delay_s:g} s, at most {n.respawn_max})" if n.respawn else ""
            print(f"- {n.name} ({n.module}) on_exit={n.on_exit}{respawn}")
            for k, v in n.parameters.items():
                print(f"    {k}: {v!r}")
        return 0
    return launch.Launcher(graph, grace_s=args.grace).run()
