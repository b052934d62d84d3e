"""``twinfocus devices``: the radars, capture boards and cameras attached over USB."""

from __future__ import annotations

import argparse
import json
from dataclasses import asdict

from twinfocus.sensors.usb_devices import list_devices


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--all", action="store_true", help="also list USB devices TwinFocus does not recognise")
    p.add_argument("--json", action="store_true", help="print a JSON list instead of lines")


def run(args: argparse.Namespace) -> int:

    devices = list_devices(include_unknown=args.all)
    if args.json:
        print(json.dumps([asdict(d) for d in devices], indent=1))
        return 0
    if not devices:
        print("no recognised radar, capture board or camera is attached (twinfocus devices --all lists everything)")
        return 0
    for d in devices:
        print(d.describe())
    return 0
