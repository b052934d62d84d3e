"""``twinfocus batch`` and ``bench --workers/--scheduler``: manifests, a two-worker local cluster,
and a real ``dask scheduler`` + two ``dask worker`` processes losing one worker mid-run."""

import csv
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from tests.helpers import cli
from twinfocus.cli import main
from twinfocus.errors import TwinFocusError

pytest.importorskip("distributed")

REF = "-0.15 0.0 -0.11 0.12 0.6"
TGT = "0.02 0.13 -0.11 0.12 0.6"
ROOT = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent


@pytest.fixture(scope="module")
def scans(tmp_path_factory):
    d = tmp_path_factory.mktemp("sim")
    for seed in (3, 4):
        scene = ("--columns 3 --rows 30 --quiet --seed", seed)
        assert cli("simulate --out", d / f"scan{seed}.npz", "--template-out", d / f"tpl{seed}.npz", *scene) == 0
    return d


def _write_csv(path, rows):
    keys = sorted({k for r in rows for k in r})
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=keys)
        w.writeheader()
        w.writerows(rows)
    return path


def _rows(names, **fields):
    """Manifest rows, one per name: the scene's regions, no pictures, and ``fields``."""
    return [{"name": name, "reference_roi": REF, "target_roi": TGT, "no_pictures": "true", **fields} for name in names]


def _summary(out):
    with open(out / "summary.csv") as f:
        return {r["name"]: r for r in csv.DictReader(f)}


def test_manifest_rows_become_focus_arguments(tmp_path):
    from twinfocus.cli.batch_jobs import read_manifest

    (tmp_path / "m").mkdir()
    m = tmp_path / "m" / "list.yaml"
    m.write_text(
        f"defaults: {{reference_roi: {REF}, target-roi: [{TGT.replace(' ', ', ')}], size: 24}}\n"
        "items:\n  - {scan: a.npz, template_scan: ../t.npz, name: one}\n"
        "  - {scan: b.npz, method: none, no_pictures: true, size: 16}\n"
    )
    a, b = read_manifest(m, tmp_path / "out")
    assert a.name == "one" and b.name == "0002_b"
    assert a.argv[0] == str(tmp_path / "m" / "a.npz")
    assert a.argv[a.argv.index("--template-scan") + 1] == str(tmp_path / "t.npz")
    assert a.argv[a.argv.index("--reference-roi") + 1 :][:5] == REF.split()
    assert b.argv[b.argv.index("--size") + 1] == "16" and "--no-pictures" in b.argv and "--no-pictures" not in a.argv
    assert a.argv[-3:] == ["--out", str(tmp_path / "out" / "items" / "one"), "--quiet"]
    assert a.paths == [str(tmp_path / "m" / "a.npz"), str(tmp_path / "t.npz")]
    for bad, words in (
        (f"- {{scan: a.npz, reference_roi: {REF}, target_roi: {TGT}, methd: none}}", "unknown option 'methd'"),
        (f"- {{scan: a.npz, reference_roi: {REF}, target_roi: {TGT}}}", "item 1: one of the arguments"),
        (f"- {{scan: a.npz, reference_roi: 1 2, target_roi: {TGT}, method: none}}", "--reference-roi"),
        ("- {reference_roi: 1}", "no 'scan'"),
        (
            f"- {{scan: a.npz, name: x, method: none, reference_roi: {REF}, target_roi: {TGT}}}\n"
            f"- {{scan: b.npz, name: x, method: none, reference_roi: {REF}, target_roi: {TGT}}}",
            "used twice",
        ),
        (f"- {{scan: a.npz, name: ../x, method: none, reference_roi: {REF}, target_roi: {TGT}}}", "plain folder"),
        (f"- {{scan: a.npz, out: x, method: none, reference_roi: {REF}, target_roi: {TGT}}}", "set by twinfocus batch"),
    ):
        m.write_text(bad + "\n")
        with pytest.raises(TwinFocusError, match="manifest") as e:
            read_manifest(m, tmp_path / "out")
        assert words in str(e.value) and "\n" not in str(e.value)
    assert main(["batch", str(tmp_path / "nope.csv"), "--out", str(tmp_path / "o")]) == 2
    with pytest.raises(SystemExit) as exc:  # refused while the options are read
        main(["bench", "paper", "--quick", "--workers", "0", "--out", str(tmp_path / "b")])
    assert exc.value.code == 2
    assert not (tmp_path / "o").exists() and not (tmp_path / "b").exists()


@pytest.mark.slow
def test_batch_on_a_two_worker_local_cluster_equals_separate_focus_runs(scans, tmp_path, capsys):
    """Every item's files equal a separate ``twinfocus focus`` run; a missing template is recorded
    with its one-line error while the others finish; a re-run keeps finished items."""
    items = [
        {"name": "phys3", "scan": "scan3.npz", "template_scan": "tpl3.npz"},
        {"name": "phys4", "scan": "scan4.npz", "template_scan": "tpl4.npz", "estimator": "projection"},
        {"name": "none4", "scan": "scan4.npz", "method": "none"},
        {"name": "lost", "scan": "scan3.npz", "template_scan": "gone.npz"},
    ]
    for it in items:
        it.update(reference_roi=REF, target_roi=TGT, size="24", no_pictures="true")
    manifest = _write_csv(scans / "manifest.csv", items)
    out = tmp_path / "batch"
    assert main(["batch", str(manifest), "--out", str(out), "--workers", "2", "--quiet"]) == 1  # one item failed
    rows = _summary(out)
    assert [rows[n]["status"] for n in ("phys3", "phys4", "none4", "lost")] == ["ok", "ok", "ok", "failed"]
    # absent where batch runs too: a missing file, not a file system the worker cannot see
    assert rows["lost"]["error"] == f"no such file: {scans / 'gone.npz'}"
    assert "3 of 4 items focused, 1 failed" in capsys.readouterr().out
    assert len({rows[n]["worker"] for n in ("phys3", "phys4", "none4", "lost")}) == 2  # both workers took items
    assert (out / "summary.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    for it in items[:3]:
        sep = tmp_path / "separate" / it["name"]
        src = (
            ["--template-scan", str(scans / it["template_scan"])]
            if "template_scan" in it
            else ["--method", it["method"]]
        )
        extra = ["--estimator", it["estimator"]] if "estimator" in it else []
        assert (
            main(
                [
                    "focus",
                    str(scans / it["scan"]),
                    "--reference-roi",
                    *REF.split(),
                    "--target-roi",
                    *TGT.split(),
                    "--size",
                    "24",
                    "--no-pictures",
                    "--quiet",
                    "--out",
                    str(sep),
                    *src,
                    *extra,
                ]
            )
            == 0
        )
        got = out / "items" / it["name"]
        for f in ("target.npy", "reference.npy", "phase.npy"):
            # equal up to the order of parallel sums (workers run numba on 1 thread, this process on 2)
            np.testing.assert_allclose(
                np.load(got / f), np.load(sep / f), rtol=1e-4, atol=1e-4 * np.abs(np.load(sep / f)).max()
            )
        m_sep = json.loads((sep / "metrics.json").read_text())
        assert float(rows[it["name"]]["target_ssim_corrected"]) == pytest.approx(
            m_sep["target_ssim_corrected"], abs=1e-4
        )
    assert float(rows["phys3"]["target_ssim_corrected"]) > float(rows["phys3"]["target_ssim_uncorrected"]) + 0.03
    # Re-run: the finished items are kept (not focused again), the failed one is tried again.
    before = (out / "items" / "phys3" / "target.npy").stat().st_mtime_ns
    capsys.readouterr()
    assert main(["batch", str(manifest), "--out", str(out), "--workers", "1"]) == 1
    assert "3 of 4 items kept" in capsys.readouterr().err
    assert (out / "items" / "phys3" / "target.npy").stat().st_mtime_ns == before
    assert _summary(out)["phys3"]["target_ssim_corrected"] == rows["phys3"]["target_ssim_corrected"]


@pytest.mark.slow
def test_an_item_run_again_is_kept_unless_the_batch_focuses_every_item_anew(scans, tmp_path):
    """Dask runs a finished task again when the worker holding its row dies before the row is
    gathered: the item's whole folder is kept, not refused as an existing --out. ``--no-resume``
    focuses every item again and replaces the batch's own earlier output."""
    from twinfocus.cli.batch_jobs import focus_item, read_manifest, run_batch

    manifest = _write_csv(scans / "again.csv", _rows(["a0"], scan="scan3.npz", method="none", size="16"))
    out = tmp_path / "b"
    (item,) = read_manifest(manifest, out)
    first = focus_item(item)
    target = Path(item.out) / "target.npy"
    before = target.stat().st_mtime_ns
    rerun = focus_item(item)
    assert rerun["status"] == first["status"] == "ok" and rerun["error"] == ""
    assert rerun["target_ssim_corrected"] == first["target_ssim_corrected"]
    assert target.stat().st_mtime_ns == before
    (row,) = run_batch(manifest, out, workers=1, resume=False)
    assert row["status"] == "ok", row["error"]
    assert target.stat().st_mtime_ns != before


@pytest.mark.slow
def test_summary_lists_pending_items_from_the_start_and_the_local_cluster_opens_no_dashboard(scans, tmp_path):
    import urllib.error
    import urllib.request

    from twinfocus.cli.batch_jobs import run_batch
    from twinfocus.jobs.cluster import dask_client

    with dask_client(workers=1) as client:
        port = client.run_on_scheduler(lambda dask_scheduler: dask_scheduler.http_server.port)
        # the scheduler's own health page on a free loopback port, and no dashboard behind it
        assert urllib.request.urlopen(f"http://127.0.0.1:{port}/health", timeout=30).read() == b"ok"
        with pytest.raises(urllib.error.HTTPError) as e:
            urllib.request.urlopen(f"http://127.0.0.1:{port}/status", timeout=30)
        assert e.value.code == 404
    assert port != 8787
    items = _rows([f"n{i}" for i in range(2)], scan="scan3.npz", method="none", size="16")
    manifest = _write_csv(scans / "pending.csv", items)
    out = tmp_path / "b"
    seen = {}

    def log(msg):  # the cluster is up: no item has run yet
        if "local cluster" in msg:
            seen.update({n: r["status"] for n, r in _summary(out).items()})

    rows = run_batch(manifest, out, workers=1, log=log)
    assert seen == {"n0": "pending", "n1": "pending"}
    assert [r["status"] for r in rows] == ["ok", "ok"]


@pytest.mark.slow
@pytest.mark.timeout(300)
def test_ctrl_c_stops_a_batch_with_one_line(scans, tmp_path):
    items = _rows([f"i{i}" for i in range(8)], scan="scan3.npz", template_scan="tpl3.npz", size="24")
    manifest = _write_csv(scans / "many.csv", items)
    out = tmp_path / "b"
    # its own process group, as a terminal's foreground job: Ctrl-C reaches every process in it
    p = subprocess.Popen(
        [
            sys.executable,
            "-c",
            "import sys; from twinfocus.cli import main; sys.exit(main())",
            "batch",
            str(manifest),
            "--out",
            str(out),
            "--workers",
            "2",
        ],
        stderr=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
        start_new_session=True,
        cwd=ROOT,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
        # as from a terminal: SIGINT not ignored (a background shell job ignores it)
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )
    lines = []
    for line in p.stderr:  # waits on the batch's own word that the cluster is up
        lines.append(line)
        if "local cluster" in line:
            break
    os.killpg(p.pid, signal.SIGINT)
    _, rest = p.communicate(timeout=240)
    assert p.returncode == 130, rest
    said = [ln for ln in rest.splitlines() if ln.strip() and not ln.startswith("[batch] ")]
    assert len(said) == 1 and said[0].startswith("twinfocus batch: interrupted:"), rest
    assert "pending" in {r["status"] for r in _summary(out).values()}


def test_thread_budget_shares_each_host_among_its_workers():
    from distributed import Client, LocalCluster

    from twinfocus.jobs.cluster import thread_budget

    with (
        LocalCluster(n_workers=2, threads_per_worker=1, processes=False, dashboard_address=None) as cluster,
        Client(cluster) as client,
    ):
        budget = thread_budget(client)
    assert len(budget) == 2 and set(budget.values()) == {max(1, (os.cpu_count() or 1) // 2)}


@pytest.mark.slow
def test_bench_on_dask_equals_the_serial_run(tmp_path):
    """The same experiments through two Dask workers, one task per scene (the baseline's two pairs
    are two tasks, merged), give the records of a serial run (same seeds), to the order of parallel
    sums: the workers run numba and torch on one thread each, the serial run on two.
    The serial run is its own process, as a ``twinfocus bench`` is: a second evaluation in one
    process has been seen to differ from the first by up to 0.4 % SSIM (state a run leaves behind;
    see docs/batch.md), so comparing against this test process's history would test that instead.
    Both run the quick scenes with 20 optimiser iterations instead of 60 and 20 rows instead of 40:
    the claim is the equality, not the focus (the quick benchmark checks that)."""
    from dataclasses import replace

    from twinfocus.evaluation.experiments import paper_experiments
    from twinfocus.evaluation.runner import quick_settings, run_experiments

    exps = paper_experiments(quick=True, only=["baseline", "tracking_error"])
    settings = replace(quick_settings(), iterations=20, n_rows=20)
    for name in ("serial", "dask"):
        (tmp_path / name).mkdir()
    code = (
        "import json, sys; from pathlib import Path; from twinfocus.evaluation.cases import EvalSettings; "
        "from twinfocus.evaluation.experiments import paper_experiments; "
        "from twinfocus.evaluation.runner import run_experiments; "
        "sys.exit(len(run_experiments(paper_experiments(quick=True, only=['baseline', 'tracking_error']), "
        "EvalSettings(**json.loads(sys.argv[2])), Path(sys.argv[1]), log=lambda m: None)))"
    )
    env = {**os.environ, "PYTHONPATH": str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    serial = [sys.executable, "-c", code, str(tmp_path / "serial"), json.dumps(settings.to_dict())]
    subprocess.run(serial, env=env, check=True, timeout=600)
    assert run_experiments(exps, settings, tmp_path / "dask", log=lambda m: None, cluster={"workers": 2}) == []

    def strip(doc):  # timings differ from run to run
        return [{k: v for k, v in r.items() if not k.endswith("_s")} for r in doc["records"]]

    def close(x, y):  # floats equal up to the order of parallel sums (workers on 1 thread, the serial run on 2)
        if isinstance(x, float) and isinstance(y, float):
            return x == pytest.approx(y, rel=1e-4, abs=1e-4)
        return x == y

    for exp in exps:
        a, b = (json.loads((tmp_path / n / f"{exp.name}.json").read_text()) for n in ("serial", "dask"))
        assert len(a["records"]) > 0 and len(a["records"]) == len(b["records"])
        # the twins ran and focused: the records compared hold numbers, not only failures
        assert any(r["method"] == "physical" and r["status"] == "ok" and r["ssim"] > 0 for r in a["records"])
        for ra, rb in zip(strip(a), strip(b)):
            assert ra.keys() == rb.keys() and all(close(ra[k], rb[k]) for k in ra), (ra, rb)
        assert [sc["pair"] for sc in a["scenes"]] == [sc["pair"] for sc in b["scenes"]]
    # the baseline ran as one task per pair, and the merged result keeps the first pair's examples
    base = json.loads((tmp_path / "dask" / "baseline.json").read_text())
    assert len(base["scenes"]) >= 2 and (tmp_path / "dask" / "baseline_examples.npz").is_file()


@pytest.mark.slow
def test_real_scheduler_and_workers_lose_one_worker_mid_run(scans, tmp_path):
    """``dask scheduler`` + two ``dask worker`` processes (no nanny: a killed worker stays dead);
    one is killed once the batch is under way; every item still finishes."""
    from distributed import Client

    env = {**os.environ, "PYTHONPATH": str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    procs = []
    logs = tmp_path / "logs"
    logs.mkdir()

    def start(name, *cmd):
        f = open(logs / f"{name}.log", "w")
        procs.append(
            subprocess.Popen(
                [str(BIN / "dask"), *cmd], env=env, stdout=f, stderr=subprocess.STDOUT, start_new_session=True
            )
        )
        return procs[-1]

    items = [
        {
            "name": f"i{i}",
            "scan": f"scan{3 + i % 2}.npz",
            "reference_roi": REF,
            "target_roi": TGT,
            "size": "24",
            "no_pictures": "true",
            "template_scan": f"tpl{3 + i % 2}.npz",
        }
        for i in range(6)
    ]
    manifest = _write_csv(scans / "six.csv", items)
    out = tmp_path / "batch"
    sched_file = tmp_path / "scheduler.json"
    try:
        # The scheduler and the workers pick their own ports (a port found free beforehand can be
        # taken by another process before they bind it), and the batch starts once both workers
        # are in: three Python processes starting on a loaded 2-core machine can take longer than
        # the 20 s `twinfocus batch` gives a scheduler to answer, and a worker that joined late
        # would find no item left to take. Waiting up to 300 s for them is legitimate here.
        start(
            "scheduler",
            "scheduler",
            "--host",
            "127.0.0.1",
            "--port",
            "0",
            "--no-dashboard",
            "--scheduler-file",
            str(sched_file),
        )
        with Client(scheduler_file=str(sched_file), timeout="300s") as client:
            workers = [
                start(
                    f"worker{i}",
                    "worker",
                    "--scheduler-file",
                    str(sched_file),
                    "--name",
                    f"w{i}",
                    "--nthreads",
                    "1",
                    "--no-nanny",
                    "--no-dashboard",
                    "--host",
                    "127.0.0.1",
                )
                for i in range(2)
            ]
            client.wait_for_workers(2, timeout=300)
            by_name = {w["name"]: a for a, w in client.scheduler_info(n_workers=-1)["workers"].items()}
        addr = json.loads(sched_file.read_text())["address"]
        waddr = [by_name["w0"], by_name["w1"]]
        batch = subprocess.Popen(
            [str(BIN / "twinfocus"), "batch", str(manifest), "--out", str(out), "--scheduler", addr, "--quiet"],
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            start_new_session=True,
        )
        procs.append(batch)
        deadline = time.monotonic() + 300  # the first item (imports, numba's first calls): minutes under load
        done = {}
        while time.monotonic() < deadline and batch.poll() is None and not done:
            if (out / "summary.csv").exists():
                done = {n: r for n, r in _summary(out).items() if r["status"] == "ok"}
            time.sleep(0.1)
        assert batch.poll() is None and 1 <= len(done) < 6, batch.communicate()
        # Kill the worker that has not finished an item yet: it is half-way through its first one.
        first = next(iter(done.values()))["worker"]
        victim = 0 if first == waddr[1] else 1
        workers[victim].send_signal(signal.SIGKILL)
        workers[victim].wait(10)
        _, err = batch.communicate(timeout=300)
        assert batch.returncode == 0, err.decode()[-2000:]
    finally:
        for p in procs:
            if p.poll() is None:
                p.send_signal(signal.SIGTERM)
        for p in procs:
            try:
                p.wait(10)
            except subprocess.TimeoutExpired:
                p.kill()
    rows = _summary(out)
    assert sorted(rows) == [f"i{i}" for i in range(6)] and all(r["status"] == "ok" for r in rows.values())
    # After the kill only the survivor focuses; the victim may have finished the one item it was
    # half-way through in the moment between the snapshot above and the signal.
    late = [r["worker"] for n, r in rows.items() if n not in done]
    assert sum(w != waddr[1 - victim] for w in late) <= 1, late
    # the same scan and template give the same image whichever worker focused it
    for i in range(2, 6):
        np.testing.assert_allclose(
            np.load(out / "items" / f"i{i}" / "phase.npy"),
            np.load(out / "items" / f"i{i % 2}" / "phase.npy"),
            atol=1e-4,
        )
