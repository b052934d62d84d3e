"""The Dask cluster both ``twinfocus batch`` and ``twinfocus bench --workers/--scheduler`` use:
the client (a local cluster or an existing scheduler), each worker's thread budget and the one
loop that hands tasks out and collects them in the order they finish (docs/batch.md)."""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import threading
import uuid
from typing import Any

from twinfocus.errors import TwinFocusError


def limit_threads(threads: int | dict | None) -> int:
    """Set this process's numba / torch / BLAS threads; ``threads`` is a count, or {worker address:
    count} from :func:`thread_budget` (a worker missing from it gets cores / its task slots).
    Returns the count set. numba's count is per calling thread, so every task calls this."""
    import numba
    import torch

    n: Any = threads
    if isinstance(threads, dict) or threads is None:
        n = None
        try:
            from distributed import get_worker

            w = get_worker()
            n = (threads or {}).get(w.address) or max(1, (os.cpu_count() or 1) // max(1, w.state.nthreads))
        except ValueError:  # not on a worker
            n = os.cpu_count() or 1
    n = max(1, int(n))
    numba.set_num_threads(min(n, numba.config.NUMBA_NUM_THREADS))
    if torch.get_num_threads() != n:
        torch.set_num_threads(n)
    with contextlib.suppress(ImportError):
        from threadpoolctl import threadpool_limits

        threadpool_limits(n)
    return n


@contextlib.contextmanager
def dask_client(scheduler: str | None = None, workers: int | None = None, log=None):
    """A Dask client: connected to ``scheduler`` (tcp://HOST:PORT, started with ``dask scheduler``),
    or to a local cluster of ``workers`` single-task processes (default: one per core)."""
    log = log or (lambda msg: None)
    try:
        from distributed import Client, LocalCluster
    except ImportError:
        raise TwinFocusError("Dask distributed is not installed: pip install 'dask[distributed]'") from None
    if scheduler:
        try:
            client = Client(scheduler, timeout="20s")
        except (OSError, TimeoutError) as exc:
            raise TwinFocusError(f"cannot reach the Dask scheduler at {scheduler} ({exc})") from None
        try:
            try:
                client.wait_for_workers(1, timeout=60)
            except TimeoutError:
                raise TwinFocusError(
                    f"the Dask scheduler at {scheduler} has no workers (start some: "
                    f"dask worker {scheduler} --nthreads 1)"
                ) from None
            log(f"[batch] scheduler {scheduler}: {len(client.scheduler_info(n_workers=-1)['workers'])} workers")
            yield client
        finally:
            client.close()
        return
    cores = os.cpu_count() or 1
    n = int(workers or cores)
    if n < 1:
        raise TwinFocusError(f"--workers must be at least 1, got {n}")
    threads = max(1, cores // n)
    # Set before the worker processes import numba/torch/BLAS: their pools start at these sizes.
    env = {k: str(threads) for k in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS", "NUMBA_NUM_THREADS")}
    # A terminal's Ctrl-C goes to every process of the foreground group: the worker processes,
    # started while SIGINT is ignored, keep ignoring it (Python leaves an ignored SIGINT alone), so
    # only this process sees it and closes the cluster; else each worker prints its traceback.
    in_main = threading.current_thread() is threading.main_thread()
    old = signal.signal(signal.SIGINT, signal.SIG_IGN) if in_main else None
    try:
        # No dashboard: dashboard_address=None turns the dashboard off, but the scheduler still serves
        # its health and metrics pages on 8787 unless told another address (a free loopback port).
        cluster = LocalCluster(
            n_workers=n,
            threads_per_worker=1,
            processes=True,
            host="127.0.0.1",
            dashboard_address=None,
            scheduler_kwargs={"dashboard_address": "127.0.0.1:0"},
            silence_logs=logging.ERROR,
            env=env,
        )
    finally:
        if in_main:
            signal.signal(signal.SIGINT, old)
    before = signal.signal(signal.SIGINT, _quiet_interrupt) if in_main else None
    local: Client | None = None
    try:
        local = Client(cluster)
        log(f"[batch] local cluster: {n} workers x {threads} threads")
        yield local
    finally:
        if in_main:
            signal.signal(signal.SIGINT, before)
        if local is not None:
            local.close()
        cluster.close()


def _quiet_interrupt(signum, frame) -> None:
    """Ctrl-C during a local cluster's run: Dask and its event loop are silenced *before* the
    KeyboardInterrupt is raised, since the loop thread logs each lost task and connection (and a
    cancelled wait's callback error) while the main thread unwinds: not news after Ctrl-C."""
    # dask's logging configuration sets tornado.application's own level: named, not inherited
    for name in ("distributed", "tornado", "tornado.application"):
        logging.getLogger(name).setLevel(logging.CRITICAL)
    raise KeyboardInterrupt


def thread_budget(client) -> dict:
    """{worker address: threads}: each host's cores shared out among the task slots of its workers
    (so workers x threads never exceeds a machine's cores)."""
    info = client.scheduler_info(n_workers=-1)["workers"]
    cores = client.run(os.cpu_count)
    slots: dict = {}
    for w in info.values():
        slots[w["host"]] = slots.get(w["host"], 0) + int(w.get("nthreads", 1))
    return {addr: max(1, int(cores.get(addr) or 1) // max(1, slots[w["host"]])) for addr, w in info.items()}


def run_tasks(client, fn, items: list, keys: list[str], on_result, *, progress=None, extra=()) -> None:
    """``fn(item, thread budget, *extra)`` for every item on the cluster, ``on_result(item, result,
    error)`` in the order they finish (``error`` a one-line string when the task itself failed, e.g.
    its worker died more often than Dask retries). A worker lost mid-task is not a failure: Dask runs
    its tasks again elsewhere."""
    from distributed import as_completed

    if not items:
        return
    budget = thread_budget(client)
    run_id = uuid.uuid4().hex[:8]
    futures = client.map(
        fn,
        items,
        [budget] * len(items),
        *[[e] * len(items) for e in extra],
        key=[f"{k}-{run_id}" for k in keys],
        pure=False,
    )
    index = {f.key: i for i, f in enumerate(futures)}
    done = 0
    for fut in as_completed(futures):
        item = items[index[fut.key]]
        try:
            res, err = fut.result(), None
        except Exception as exc:  # noqa: BLE001 - recorded, the rest goes on
            res, err = None, f"{type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}"
        on_result(item, res, err)
        done += 1
        if progress:
            progress(done, len(items))
        fut.release()
