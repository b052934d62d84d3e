"""Many scans on Dask distributed: the manifest, one item's focus, the cluster and the summary.

``twinfocus batch MANIFEST --out DIR`` focuses every row of a manifest exactly as ``twinfocus
focus`` would (the same parser and the same :func:`twinfocus.cli.focus.run`, so an item's files
equal those of a separate ``focus`` run with the same options). :func:`twinfocus.jobs.cluster.run_tasks` is the one place
that talks to Dask; ``twinfocus bench --scheduler/--workers`` spreads its experiments through it.

Manifest: CSV (a header row) or YAML (a list of mappings, or ``{defaults: {...}, items: [...]}``).
Every item has ``scan`` and any ``twinfocus focus`` option spelled as its flag without the dashes
(``reference_roi`` or ``reference-roi``: "X0 X1 Y0 Y1 Z" in metres, ``template`` /
``template_scan`` / ``digital_twin`` (with ``rig``) / ``method``, ``size``, ``estimator``, ...); ``name``
(optional) is the item's output folder ``OUT/items/NAME``. Relative paths are taken from the
manifest's folder. Workers read the files themselves, so every worker must see the paths (and
``OUT``) under the same names: a shared file system on a cluster.
"""

from __future__ import annotations

import argparse
import contextlib
import csv
import io
import json
import os
import re
import socket
import time
from dataclasses import dataclass, field
from pathlib import Path

from twinfocus.cli import focus
from twinfocus.errors import TwinFocusError
from twinfocus.io.atomic import atomic_writer, write_text_atomic
from twinfocus.io.png import pyplot
from twinfocus.io.safe_paths import child_path
from twinfocus.jobs.cluster import dask_client, limit_threads, run_tasks

#: focus options that name input files (resolved against the manifest's folder, checked on the worker).
PATH_OPTIONS = ("scan", "template", "template_scan", "digital_twin", "rig")
#: Columns of summary.csv, before the item's options.
SUMMARY_FIELDS = (
    "name",
    "status",
    "error",
    "seconds",
    "worker",
    "peak_rss_mb",
    "target_ssim_uncorrected",
    "target_ssim_corrected",
    "target_ssim_oracle_phase",
    "warnings",
    "out",
)


class _Parser(argparse.ArgumentParser):
    """focus's parser, raising instead of exiting, so a bad manifest row is one line naming it."""

    def error(self, message):
        raise TwinFocusError(message)


def focus_parser() -> argparse.ArgumentParser:
    p = _Parser(prog="twinfocus focus", add_help=False)
    focus.add_arguments(p)
    return p


@dataclass
class BatchItem:
    """One manifest row: its output name and the ``twinfocus focus`` argument list (absolute paths,
    ``--out`` and ``--quiet`` included)."""

    name: str
    argv: list[str]
    paths: list[str]
    out: str
    options: dict
    #: input files that do not exist where ``batch`` runs (a worker may still see them elsewhere)
    missing_here: list[str] = field(default_factory=list)


def _flag_values(key: str, value, actions: dict) -> list[str]:
    act = actions[key]
    if isinstance(act, argparse._StoreTrueAction):
        on = value if isinstance(value, bool) else str(value).strip().lower() in ("1", "true", "yes", "on")
        return [act.option_strings[0]] if on else []
    if value is None or (isinstance(value, str) and not value.strip()):
        return []
    vals = (
        [str(v) for v in value]
        if isinstance(value, (list, tuple))
        else str(value).split()
        if act.nargs
        else [str(value)]
    )
    return [act.option_strings[0], *vals]


def read_manifest(path: str | os.PathLike, out_dir: str | os.PathLike) -> list[BatchItem]:
    """Read and check a manifest (every row parsed by focus's own parser before any work)."""
    import yaml

    path = Path(path)
    if not path.is_file():
        raise TwinFocusError(f"manifest {path} does not exist")
    text = path.read_text()
    if path.suffix.lower() in (".yaml", ".yml"):
        try:
            doc = yaml.safe_load(text)
        except yaml.YAMLError as exc:
            raise TwinFocusError(f"manifest {path}: not valid YAML ({str(exc).splitlines()[0]})") from None
        defaults: dict = {}
        if isinstance(doc, dict):
            defaults, doc = doc.get("defaults") or {}, doc.get("items")
        if not isinstance(doc, list) or not all(isinstance(r, dict) for r in doc):
            raise TwinFocusError(f"manifest {path}: expected a list of items (mappings), or 'defaults' + 'items'")
        rows = [{**defaults, **r} for r in doc]
    else:
        rows = [{k.strip(): v for k, v in r.items() if k is not None} for r in csv.DictReader(io.StringIO(text))]
    if not rows:
        raise TwinFocusError(f"manifest {path} has no items")
    parser = focus_parser()
    actions = {a.dest: a for a in parser._actions if a.option_strings}
    base = path.resolve().parent
    out_dir = Path(out_dir).resolve()
    items, seen = [], set()
    for i, row in enumerate(rows, start=1):
        row = {str(k).strip().replace("-", "_"): v for k, v in row.items()}
        where = f"manifest {path} item {i}"
        scan = row.pop("scan", None)
        if not scan:
            raise TwinFocusError(f"{where}: no 'scan'")
        name = str(row.pop("name", None) or f"{i:04d}_{Path(str(scan)).stem}")
        if not re.fullmatch(r"[\w.+-]+", name) or name in (".", ".."):
            raise TwinFocusError(f"{where}: name {name!r} is not a plain folder name")
        if name in seen:
            raise TwinFocusError(f"{where}: name {name!r} is used twice")
        seen.add(name)
        for k in ("out", "quiet"):
            if k in row:
                raise TwinFocusError(f"{where}: '{k}' is set by twinfocus batch, not the manifest")
        unknown = [k for k in row if k not in actions]
        if unknown:
            raise TwinFocusError(f"{where}: unknown option {unknown[0]!r} (not a twinfocus focus option)")
        paths = {"scan": scan, **{k: row[k] for k in PATH_OPTIONS[1:] if row.get(k)}}
        paths = {k: str((base / str(v)).resolve()) for k, v in paths.items()}
        row.update({k: v for k, v in paths.items() if k != "scan"})
        if row.get("save_template"):
            # an output named by the manifest stays inside the batch's --out (resolved against it)
            row["save_template"] = str(
                child_path(out_dir, str(row["save_template"]), what=f"{where}: save_template", subfolders=True)
            )
        item_out = str(out_dir / "items" / name)
        argv = [paths["scan"]]
        for k, v in row.items():
            argv += _flag_values(k, v, actions)
        argv += ["--out", item_out, "--quiet"]
        try:
            parser.parse_args(argv)
        except TwinFocusError as exc:
            raise TwinFocusError(f"{where}: {exc}") from None
        files = list(paths.values())
        missing = [p for p in files if not os.path.isfile(p)]
        items.append(BatchItem(name, argv, files, item_out, {k: v for k, v in row.items()}, missing))
    return items


# --- on the worker ------------------------------------------------------------------------------


def check_visible(paths, missing_here=()) -> None:
    """One line naming the first input file this machine cannot read: missing everywhere (absent
    where ``batch`` runs too: ``missing_here``), or only on this worker (no shared file system)."""
    for p in paths:
        if not os.path.isfile(p):
            if p in missing_here:
                raise TwinFocusError(f"no such file: {p}")
            raise TwinFocusError(
                f"worker on {socket.gethostname()} cannot see {p}, which exists where batch runs (every "
                f"worker needs the manifest's files under the same path: a shared file system)"
            )


def _peak_rss_mb() -> float | None:
    try:
        import resource

        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # kB on Linux
    except (ImportError, OSError):
        return None


def _worker_name() -> str:
    try:
        from distributed import get_worker

        return get_worker().address
    except ValueError:
        return f"{socket.gethostname()}:{os.getpid()}"


def focus_item(item: BatchItem, threads=None, again: bool = False) -> dict:
    """Focus one item exactly as ``twinfocus focus ARGV`` would; returns its summary row. A failure
    is returned as a row with status 'failed' and the one-line error, so the batch goes on.

    An item already finished with the same options is returned as it is: Dask runs a finished task
    again when the worker holding its row dies before the row is gathered, and the item's folder
    is whole by then. ``again`` (``--no-resume``) focuses it anew, replacing the batch's earlier
    output of it."""
    prev = None if again else finished(item)
    if prev:
        return {**prev, "status": "ok"}
    t0 = time.perf_counter()
    row: dict = {"name": item.name, "status": "ok", "error": "", "worker": _worker_name(), "out": item.out}
    try:
        limit_threads(threads)
        check_visible(item.paths, item.missing_here)
        args = focus_parser().parse_args(item.argv + (["--overwrite"] if again else []))
        err = io.StringIO()
        # focus's summary line and warnings; the row carries the metrics and the warnings
        with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(err):
            focus.run(args)
        row["warnings"] = " | ".join(
            ln.split("warning: ", 1)[1] for ln in err.getvalue().splitlines() if "warning: " in ln
        )
        m = json.loads((Path(item.out) / "metrics.json").read_text())
        for k in ("target_ssim_uncorrected", "target_ssim_corrected", "target_ssim_oracle_phase"):
            row[k] = m.get(k)
    except TwinFocusError as exc:
        row.update(status="failed", error=str(exc))
    except Exception as exc:  # noqa: BLE001 - a batch records any item's failure and goes on
        row.update(status="failed", error=f"{type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}")
    row["seconds"] = round(time.perf_counter() - t0, 3)
    row["peak_rss_mb"] = _peak_rss_mb()
    if row["status"] == "ok":
        write_text_atomic(Path(item.out) / "batch_item.json", json.dumps({"argv": item.argv, **row}, indent=1))
    return row


def finished(item: BatchItem) -> dict | None:
    """The summary row of an item finished earlier with the same options, else None."""
    p = Path(item.out) / "batch_item.json"
    try:
        doc = json.loads(p.read_text())
    except (OSError, ValueError):
        return None
    if doc.get("argv") != item.argv or doc.get("status") != "ok" or not (Path(item.out) / "metrics.json").is_file():
        return None
    return {k: v for k, v in doc.items() if k != "argv"}


# --- the whole batch ----------------------------------------------------------------------------


def run_batch(
    manifest,
    out_dir,
    *,
    scheduler: str | None = None,
    workers: int | None = None,
    resume: bool = True,
    progress=None,
    log=None,
) -> list[dict]:
    """Focus every item of ``manifest`` into ``out_dir/items/NAME``; write ``out_dir/summary.csv`` and
    ``summary.png``. Returns the summary rows in manifest order."""
    log = log or (lambda msg: None)
    items = read_manifest(manifest, out_dir)
    out = Path(out_dir)
    rows: dict[str, dict] = {}
    todo = []
    for it in items:
        prev = finished(it) if resume else None
        if prev:
            rows[it.name] = {**prev, "status": "ok"}
        else:
            todo.append(it)
    kept = len(items) - len(todo)
    if kept:
        log(f"[batch] {kept} of {len(items)} items kept from an earlier run")
    write_summary(out, items, rows)  # from the start: every item not yet run is listed as pending

    def record(item, res, err):
        rows[item.name] = (
            res if res is not None else {"name": item.name, "status": "failed", "error": err, "out": item.out}
        )
        r = rows[item.name]
        if r["status"] != "ok":
            log(f"[batch] {item.name} failed: {r['error']}")
        write_summary(out, items, rows)  # after every item, so an interrupted batch still has its table

    t0 = time.perf_counter()
    try:
        if todo:
            with dask_client(scheduler, workers, log) as client:
                run_tasks(
                    client,
                    focus_item,
                    todo,
                    [f"focus-{it.name}" for it in todo],
                    record,
                    progress=progress,
                    extra=(not resume,),
                )
    except KeyboardInterrupt:
        write_summary(out, items, rows)
        n_done = sum(1 for it in todo if it.name in rows)
        raise BatchInterrupted(
            f"interrupted: {n_done} of the {len(todo)} items to run finished; {out / 'summary.csv'} lists the "
            f"rest as pending (run the same command again to go on)"
        ) from None
    write_summary(out, items, rows, figure=True)
    n_ok = sum(rows[it.name].get("status") == "ok" for it in items)
    ran = f" ({kept} kept from an earlier run)" if kept else ""
    log(
        f"[batch] {n_ok} ok, {len(items) - n_ok} failed of {len(items)} items{ran} in "
        f"{time.perf_counter() - t0:.1f} s; {out / 'summary.csv'}"
    )
    return [rows[it.name] for it in items]


class BatchInterrupted(KeyboardInterrupt):
    """Ctrl-C during a batch: the one line to print (what finished, where the table is)."""


def write_summary(out: Path, items: list[BatchItem], rows: dict, figure: bool = False) -> None:
    """summary.csv: one row per item (not yet run: status 'pending'), metrics then options."""
    opt_keys = sorted({k for it in items for k in it.options})
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=list(SUMMARY_FIELDS) + opt_keys, extrasaction="ignore", lineterminator="\n")
    w.writeheader()
    for it in items:
        r = rows.get(it.name, {"name": it.name, "status": "pending", "out": it.out})
        opts = {k: " ".join(map(str, v)) if isinstance(v, (list, tuple)) else v for k, v in it.options.items()}
        w.writerow({**opts, **{k: ("" if r.get(k) is None else r.get(k)) for k in SUMMARY_FIELDS}})
    write_text_atomic(Path(out) / "summary.csv", buf.getvalue())
    if figure:
        write_summary_figure(
            Path(out) / "summary.png", [rows.get(it.name, {"name": it.name, "status": "pending"}) for it in items]
        )


def write_summary_figure(path: Path, rows: list[dict]) -> None:
    """Target SSIM per item, uncorrected and corrected (with the oracle-phase ceiling); failed items
    marked in red."""
    import numpy as np

    plt = pyplot()
    n = len(rows)
    x = np.arange(n)
    get = lambda k: np.array([np.nan if r.get(k) in (None, "") else float(r[k]) for r in rows])  # noqa: E731
    fig, ax = plt.subplots(figsize=(max(6.0, 0.35 * n + 2), 3.6))
    ax.bar(x - 0.2, get("target_ssim_uncorrected"), 0.4, label="uncorrected", color="0.65")
    ax.bar(x + 0.2, get("target_ssim_corrected"), 0.4, label="corrected", color="tab:blue")
    ax.plot(x + 0.2, get("target_ssim_oracle_phase"), "k_", ms=10, label="oracle phase")
    for i, r in enumerate(rows):
        if r.get("status") != "ok":
            ax.text(
                i, 0.02, r.get("status", "failed"), rotation=90, color="tab:red", ha="center", va="bottom", fontsize=8
            )
    ax.set_xticks(x, [r["name"] for r in rows], rotation=60, ha="right", fontsize=7)
    ax.set_ylim(0, 1.05)
    ax.set_ylabel("target SSIM")
    n_ok = sum(r.get("status") == "ok" for r in rows)
    ax.set_title(f"twinfocus batch: {n_ok}/{n} items focused")
    ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.0, 1.0))
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_writer(path) as f:
        fig.savefig(f, format="png", dpi=110)
    plt.close(fig)
