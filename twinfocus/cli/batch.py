"""``twinfocus batch MANIFEST --out DIR [--workers N | --scheduler tcp://HOST:PORT] [--no-resume]``:
focus every scan of a manifest on Dask distributed (docs/batch.md)."""

from __future__ import annotations

import argparse
import sys

from twinfocus.option_types import positive_int


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "manifest",
        help="CSV or YAML: one item per scan with 'scan' and any 'twinfocus focus' option "
        "(reference_roi, target_roi, template / template_scan / digital_twin / method, size, ...), "
        "optional 'name'; relative paths from the manifest's folder",
    )
    p.add_argument("--out", required=True, help="output folder: items/NAME/ (focus's files), summary.csv, summary.png")
    where = p.add_mutually_exclusive_group()
    where.add_argument(
        "--workers",
        type=positive_int,
        default=None,
        help="local cluster of this many worker processes (default: one per core)",
    )
    where.add_argument(
        "--scheduler",
        default=None,
        help="an existing Dask cluster (tcp://HOST:PORT of 'dask scheduler'); workers must see the "
        "manifest's files and --out under the same paths",
    )
    p.add_argument(
        "--no-resume",
        action="store_true",
        help="focus every item again, replacing its earlier output (default: items finished earlier with the same options are kept)",
    )
    p.add_argument("--quiet", action="store_true", help="no progress output")


def run(args: argparse.Namespace) -> int:
    from twinfocus.cli.batch_jobs import BatchInterrupted, run_batch  # lazy: numpy (+1.31 s on twinfocus batch --help)
    from twinfocus.jobs.progress import Progress  # lazy: twinfocus.jobs (+0.02 s on twinfocus batch --help)

    log = (lambda msg: None) if args.quiet else (lambda msg: print(msg, file=sys.stderr, flush=True))
    try:
        rows = run_batch(
            args.manifest,
            args.out,
            scheduler=args.scheduler,
            workers=args.workers,
            resume=not args.no_resume,
            progress=Progress("batch", enabled=not args.quiet),
            log=log,
        )
    except BatchInterrupted as exc:
        print(f"twinfocus batch: {exc}", file=sys.stderr)
        return 130
    failed = [r for r in rows if r.get("status") != "ok"]
    print(f"{len(rows) - len(failed)} of {len(rows)} items focused, {len(failed)} failed; {args.out}/summary.csv")
    # Failed items are recorded, not fatal; the status still tells a script that some need a look.
    return 1 if failed else 0
