import os
import threading
import time

import pytest

# Tests share the machine's two cores; numba/torch each default to all cores.
os.environ.setdefault("NUMBA_NUM_THREADS", str(os.cpu_count() or 1))

from tests.helpers import SMALL_SCENE, simulate  # noqa: E402 (imports the library: after the thread count)


@pytest.fixture(autouse=True, scope="session")
def _template_cache_in_tmp(tmp_path_factory):
    """``focus`` caches templates in the user's cache folder; tests (and the processes they
    start) use a fresh one of their own instead."""
    old = os.environ.get("TWINFOCUS_CACHE_DIR")
    os.environ["TWINFOCUS_CACHE_DIR"] = str(tmp_path_factory.mktemp("template-cache"))
    yield
    if old is None:
        os.environ.pop("TWINFOCUS_CACHE_DIR", None)
    else:
        os.environ["TWINFOCUS_CACHE_DIR"] = old


@pytest.fixture(scope="session")
def small_scene(tmp_path_factory):
    """The folder of ``simulate`` on :data:`~tests.helpers.SMALL_SCENE`: ``scan.npz`` and its
    template scan ``tpl.npz``, made once for every file that focuses it (read only: runs write
    into their own ``tmp_path``)."""
    return simulate(tmp_path_factory.mktemp("small-scene"), *SMALL_SCENE)


@pytest.fixture(scope="session")
def deep_scene(tmp_path_factory):
    """As :func:`small_scene` with the target 8 cm behind the reference (0.68 m), for the
    depth search and the volume."""
    return simulate(tmp_path_factory.mktemp("deep-scene"), *SMALL_SCENE, "--target-depth-offset", "0.08")


@pytest.fixture
def no_stray_threads():
    """Fails the test if a thread it started is still alive 2 s after it ends (emulators and
    clients must stop every thread they start): ``pytestmark = pytest.mark.usefixtures(...)``."""
    before = set(threading.enumerate())
    yield
    deadline = time.monotonic() + 2.0
    while set(threading.enumerate()) - before and time.monotonic() < deadline:
        time.sleep(0.01)
    assert not set(threading.enumerate()) - before


def pytest_collection_modifyitems(config, items):
    try:
        import torch

        has_cuda = torch.cuda.is_available()
    except Exception:  # pragma: no cover - torch is a hard dependency
        has_cuda = False
    skip_gpu = pytest.mark.skip(reason="needs a CUDA device")
    for item in items:
        if "gpu" in item.keywords and not has_cuda:
            item.add_marker(skip_gpu)
