"""``twinfocus bench paper``: the source paper's evaluation in simulation, the speed/accuracy trade
and the limits, written as a report folder (markdown, PNG figures, raw JSON); ``twinfocus bench
beyond``: the improvements of the twin estimate beyond the paper, one row each.

    twinfocus bench paper [--quick] [--out DIR] [--draws N] [--only EXPERIMENTS] [--markdown FILE] [--resume]
    twinfocus bench paper --report-only [--out DIR] [--markdown FILE]
    twinfocus bench beyond [--quick] [--out DIR] [--draws N] [--markdown FILE] [--resume] [--report-only]
    twinfocus bench where [--quick] [--out DIR] [--draws N] [--markdown FILE]
    ... [--workers N | --scheduler tcp://HOST:PORT]: the experiments as Dask tasks (docs/batch.md)
"""

from __future__ import annotations

import argparse
import shlex
import sys
from pathlib import Path
from typing import Any

from twinfocus.errors import TwinFocusError
from twinfocus.evaluation.beyond import run_beyond, write_beyond_report
from twinfocus.evaluation.experiments import EXPERIMENT_NAMES
from twinfocus.evaluation.report import write_report
from twinfocus.evaluation.where import run_where, write_where_report
from twinfocus.imaging.device import resolve_device
from twinfocus.option_types import positive_int

SUITES = ("paper", "beyond", "where")


def add_arguments(p: argparse.ArgumentParser) -> None:

    p.add_argument(
        "suite",
        choices=SUITES,
        help="what to run: 'paper' (the source paper's evaluation), 'beyond' "
        "(the twin estimate's improvements beyond the paper, docs/beyond.md) or 'where' (focus finding the "
        "regions, depth and reference it is not given, one row each)",
    )
    p.add_argument(
        "--quick",
        action="store_true",
        help="smoke run: two baseline pairs and two tracking errors on small scans (240 positions, 32 x 32, 60 iterations)",
    )
    p.add_argument("--out", default=None, help="report folder (default bench_<suite>/)")
    p.add_argument(
        "--draws",
        type=positive_int,
        default=None,
        help="tracking-error draws per pair and condition for every experiment (default 1; the paper used 5)",
    )
    p.add_argument(
        "--only", default="", help=f"comma-separated experiments: {', '.join(EXPERIMENT_NAMES)}, trade (default all)"
    )
    p.add_argument("--markdown", default=None, help="where to write the report markdown (default OUT/report.md)")
    p.add_argument("--resume", action="store_true", help="keep experiments already in OUT/raw with the same settings")
    p.add_argument("--report-only", action="store_true", help="only rewrite the report from the raw results in OUT/raw")
    p.add_argument(
        "--trade-scenes",
        type=positive_int,
        default=None,
        help="scenes in the speed/accuracy trade (default 1; pairs A>F, R>X)",
    )
    p.add_argument("--device", default="cpu", help="torch device for the optimiser and back-projection (cpu, cuda)")
    where = p.add_mutually_exclusive_group()
    where.add_argument(
        "--workers",
        type=positive_int,
        default=None,
        help="spread the experiments over a local Dask cluster of this many worker processes "
        "(default: one after the other in this process)",
    )
    where.add_argument(
        "--scheduler",
        default=None,
        help="spread the experiments over an existing Dask cluster (tcp://HOST:PORT of 'dask scheduler'; "
        "docs/batch.md); the results equal the serial run's",
    )
    p.add_argument("--quiet", action="store_true", help="no progress lines")


def run(args: argparse.Namespace) -> int:

    from twinfocus.evaluation.runner import run_paper  # lazy: numba, scipy.fft, cv2 (+2.1 s at import)

    args.out = args.out or f"bench_{args.suite}"
    if args.suite != "paper" and (args.only or args.trade_scenes is not None):
        raise TwinFocusError("--only and --trade-scenes apply to the 'paper' suite only")
    if args.suite == "where" and (args.resume or args.workers is not None or args.scheduler):
        raise TwinFocusError("--resume, --workers and --scheduler apply to the 'paper' and 'beyond' suites only")
    if args.report_only:
        if not (Path(args.out) / "raw").is_dir():
            raise TwinFocusError(
                f"--report-only: {Path(args.out) / 'raw'} holds no raw results; run the benchmark first"
            )

        writer = {"beyond": write_beyond_report, "where": write_where_report}.get(args.suite, write_report)
        print(writer(args.out, args.markdown))
        return 0
    only = [s.strip() for s in args.only.split(",") if s.strip()] or None

    resolve_device(args.device)  # a CUDA device that is not there fails before any work
    if args.trade_scenes is not None and args.trade_scenes < 1:
        raise TwinFocusError(f"--trade-scenes must be at least 1, got {args.trade_scenes}")
    if args.workers is not None and args.workers < 1:
        raise TwinFocusError(f"--workers must be at least 1, got {args.workers}")
    cluster = {"scheduler": args.scheduler} if args.scheduler else {"workers": args.workers} if args.workers else None
    command = (
        "twinfocus bench " + " ".join(shlex.quote(a) for a in sys.argv[2:]) if sys.argv[1:2] == ["bench"] else None
    )
    if args.suite == "where":
        print(run_where(args.out, draws=args.draws or 1, quick=args.quick, markdown=args.markdown, command=command))
        return 0
    # what the beyond and the paper suites are both given: these options as they are, the command,
    # the cluster, and with --quiet a log that prints nothing
    common: dict[str, Any] = {k: getattr(args, k) for k in ("quick", "resume", "markdown", "device")}
    common.update(command=command, cluster=cluster)
    if args.quiet:
        common["log"] = lambda msg: None
    if args.suite == "beyond":
        print(run_beyond(args.out, draws=args.draws or 1, **common))
        return 0
    print(run_paper(args.out, draws=args.draws, only=only, trade_scenes=args.trade_scenes, **common))
    return 0
